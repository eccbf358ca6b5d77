"""drape_survey: caching, cache repair, surfaces from files, and bad surveys."""

from __future__ import annotations

import logging

import numpy as np
import pytest

import sss2bathy.draping.cache as cache_mod
from sss2bathy.draping import DrapedLine, drape_key, drape_line, drape_survey
from sss2bathy.survey import MASK_VALID, Survey


def _survey(make_plane, make_line, tmp_path, starts=((0.0, 0.0), (5.0, 0.0)), crs=None):
    grid = make_plane(a=0.05, b=0.02, x_range=(-45, 45), y_range=(-10, 50), cell=1.0)
    grid.crs = crs
    lines = [
        make_line(n_pings=5, n_bins=60, max_range=30.0, start=s, length=10.0, name=f"l{i}")
        for i, s in enumerate(starts)
    ]
    survey = Survey("tiny", lines, grid, splits={"train": ["l0"], "test": ["l1"]})
    folder = survey.save(tmp_path / "tiny")
    return Survey.load(folder), folder


def test_cache_reused_and_corrupt_file_rebuilt(
    tmp_path, make_plane, make_line, monkeypatch, caplog
):
    survey, folder = _survey(make_plane, make_line, tmp_path)
    first = drape_survey(survey, folder)
    key = drape_key(survey, folder)
    files = sorted((folder / "draped" / key).glob("*.npz"))
    assert [f.stem for f in files] == ["l0", "l1"]
    assert (folder / "draped" / key / "manifest.json").is_file()
    direct = drape_line(survey.line("l0"), survey.grid)
    np.testing.assert_array_equal(first["l0"].mask, direct.mask)

    def fail(*args, **kwargs):
        raise AssertionError("drape_line called although the cache is valid")

    monkeypatch.setattr(cache_mod, "drape_line", fail)
    again = drape_survey(survey, folder)
    np.testing.assert_array_equal(again["l1"].n_lat, first["l1"].n_lat)
    monkeypatch.undo()

    files[0].write_bytes(b"garbage")
    with caplog.at_level(logging.WARNING, logger="sss2bathy.draping.cache"):
        repaired = drape_survey(survey, folder, lines=["l0"])
    assert "unreadable" in caplog.text
    assert list(repaired) == ["l0"]
    np.testing.assert_array_equal(repaired["l0"].mask, first["l0"].mask)
    assert DrapedLine.load(files[0]).meta["line"] == "l0"


def test_stale_file_and_config_change(tmp_path, make_plane, make_line, caplog):
    survey, folder = _survey(make_plane, make_line, tmp_path)
    drape_survey(survey, folder)
    key = drape_key(survey, folder)
    path = folder / "draped" / key / "l0.npz"
    other = DrapedLine.load(folder / "draped" / key / "l1.npz")
    other.save(path)  # a valid file with the wrong line's provenance
    with caplog.at_level(logging.WARNING, logger="sss2bathy.draping.cache"):
        drape_survey(survey, folder, lines=["l0"])
    assert "stale" in caplog.text
    assert DrapedLine.load(path).meta["line"] == "l0"
    assert drape_key(survey, folder, {"rays_per_bin": 3.0}) != key
    assert drape_key(survey, folder, {"pings_per_chunk": 7}) == key
    assert drape_key(survey, folder, {"threads": 3}) == key


def test_mesh_path_surface(tmp_path, make_plane, make_line):
    survey, folder = _survey(make_plane, make_line, tmp_path)
    survey.grid.to_mesh().export(folder / "mbes.ply")
    from_mesh = drape_survey(survey, folder, {"mesh_path": "mbes.ply"})
    from_grid = drape_survey(survey, folder)
    assert drape_key(survey, folder, {"mesh_path": "mbes.ply"}) != drape_key(survey, folder)
    both = (from_mesh["l0"].mask == MASK_VALID) & (from_grid["l0"].mask == MASK_VALID)
    assert both.mean() > 0.5
    np.testing.assert_allclose(from_mesh["l0"].n_lat[both], from_grid["l0"].n_lat[both], atol=1e-5)


def test_bad_surveys(tmp_path, make_plane, make_line, caplog):
    survey, folder = _survey(make_plane, make_line, tmp_path)
    no_grid = Survey("nogrid", survey.lines, None, survey.splits)
    with pytest.raises(ValueError, match="no MBES grid"):
        drape_survey(no_grid, tmp_path / "nogrid")
    with pytest.raises(ValueError, match="unknown"):
        drape_survey(survey, folder, lines=["l0", "nope"])
    with pytest.raises(ValueError, match="mesh_path"):
        drape_survey(survey, folder, {"mesh_path": "missing.ply"})

    crs_survey, crs_folder = _survey(make_plane, make_line, tmp_path / "c", crs="EPSG:32633")
    crs_survey.origin = {"crs": "EPSG:32634", "easting": 0.0, "northing": 0.0}
    with pytest.raises(ValueError, match="differs from the lines' CRS"):
        drape_survey(crs_survey, crs_folder)

    far, far_folder = _survey(
        make_plane, make_line, tmp_path / "far", starts=((9000.0, 0.0), (9005.0, 0.0))
    )
    with pytest.raises(ValueError, match="do not overlap"):
        drape_survey(far, far_folder)

    half, half_folder = _survey(
        make_plane, make_line, tmp_path / "half", starts=((0.0, 0.0), (9000.0, 0.0))
    )
    with caplog.at_level(logging.WARNING, logger="sss2bathy.draping.cache"):
        out = drape_survey(half, half_folder)
    assert "line 'l1': no valid bin" in caplog.text
    assert out["l0"].valid.any() and not out["l1"].valid.any()
