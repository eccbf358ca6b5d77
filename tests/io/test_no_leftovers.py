"""Failed imports and drapings leave nothing behind; the grid/lines message says what happened."""

from __future__ import annotations

import numpy as np
import pytest

from sss2bathy.draping import drape_survey
from sss2bathy.io.grids import footprint_coverage
from sss2bathy.io.xtf import write_xtf
from sss2bathy.io.xtf_survey import prepare_xtf_survey
from sss2bathy.survey import BathyGrid, Survey, SurveyFormatError


def tree(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*")) if folder.exists() else []


def _survey(make_line, heights, x0, y0, crs="EPSG:32633"):
    line = make_line("L0", n_pings=30, n_bins=64)
    grid = BathyGrid(heights, x0, y0, 1.0, crs)
    return Survey("s", [line], grid=grid, origin={"crs": crs, "easting": 0.0, "northing": 0.0})


def test_failed_xtf_import_leaves_data_unchanged(tmp_path, make_line, origin, xtf_patch):
    raw = tmp_path / "raw"
    for i in range(2):
        write_xtf(make_line(f"L{i}", n_pings=30, n_bins=32, seed=i), raw / f"L{i}.xtf", origin)
    _, _, offsets = xtf_patch
    bad = raw / "L1.xtf"
    with open(bad, "r+b") as f:  # corrupt the magic number of pings 6-29: most of the file
        for ping in range(6, 30):
            f.seek(offsets(bad)[ping])
            f.write(b"\x00\x00")
    data = tmp_path / "data"
    (data / "other").mkdir(parents=True)
    (data / "other" / "keep.txt").write_text("x")
    before = tree(data)
    cfg = {"kind": "xtf", "name": "imp", "files": str(raw), "n_bins": 32}
    with pytest.raises(SurveyFormatError, match=r"L1\.xtf") as err:
        prepare_xtf_survey(cfg, data)
    assert "\n" not in str(err.value)
    assert tree(data) == before  # no survey folder, no temporary folder


def test_draping_without_any_hit_raises_before_writing_a_cache(tmp_path, make_line):
    far = _survey(make_line, np.full((50, 50), -25.0), 5000.0, 5000.0)
    folder = far.save(tmp_path / "far")
    with pytest.raises(ValueError, match="do not overlap.*outside its extent.*CRS"):
        drape_survey(far, folder)
    assert not (folder / "draped").exists()


def test_holes_are_not_reported_as_no_overlap(tmp_path, make_line):
    # A grid under the lines with 70 % of its cells NaN (in blocks under the track).
    probe = _survey(make_line, np.full((400, 400), -25.0), -100.0, -200.0)
    cov = footprint_coverage(probe.grid, probe.lines)
    assert cov["inside"] == 1.0 and cov["holes"] == 0.0
    heights = np.full((400, 400), np.nan)
    rng = np.random.default_rng(0)
    heights[rng.random((400, 400)) < 0.3] = -25.0
    holed = _survey(make_line, heights, -100.0, -200.0)
    cov = footprint_coverage(holed.grid, holed.lines)
    assert cov["inside"] == 1.0 and 0.5 < cov["holes"]
    assert cov["grid_nan"] == pytest.approx(0.7, abs=0.01)
    corner = np.full((400, 400), np.nan)
    corner[350:, :50] = -25.0  # valid only in the NW corner, far from the lines
    none = _survey(make_line, corner, -100.0, -200.0)
    folder = none.save(tmp_path / "holes")
    with pytest.raises(ValueError, match=r"100% of the lines' footprint lies inside.*holes") as err:
        drape_survey(none, folder)
    assert "do not overlap" not in str(err.value)
    assert not (folder / "draped").exists()
