"""Survey data model: save/load round trips and every bad-input case named in its message."""

import math

import numpy as np
import pytest
import yaml

from sss2bathy.geometry import attitude_to_rotation
from sss2bathy.survey import BathyGrid, SensorParams, SidescanLine, Survey, SurveyFormatError


def make_line(name="L0", P=5, B=8, seed=0):
    rng = np.random.default_rng(seed)
    heading = np.full(P, 0.3)
    return SidescanLine(
        name=name,
        time_s=np.arange(P) * 0.1,
        position=np.c_[np.arange(P, dtype=float), np.zeros(P), np.full(P, -2.0)],
        rotation=attitude_to_rotation(heading, np.zeros(P), np.zeros(P)),
        altitude_m=np.full(P, 10.0),
        intensity=rng.random((P, 2, B)),
        range_m=np.linspace(1.0, 30.0, B),
        sensor=SensorParams(),
        extras={"true_n_lat": rng.random((P, 2, B)).astype(np.float32)},
    )


def make_survey(n_lines=2):
    heights = -10.0 - np.arange(12.0)[:, None] * 0.1 + np.zeros((12, 14))
    heights[0, 0] = np.nan
    grid = BathyGrid(heights, x0=-5.0, y0=-3.0, cell_size=0.5, crs="EPSG:32633")
    lines = [make_line(f"L{i}", seed=i) for i in range(n_lines)]
    return Survey(
        name="s",
        lines=lines,
        grid=grid,
        splits={"train": ["L0"], "test": ["L1"]},
        origin={"crs": "EPSG:32633", "easting": 500000.0, "northing": 6500000.0},
        metadata={"config_hash": "abc"},
    )


def test_round_trip_exact(tmp_path):
    s = make_survey()
    s.save(tmp_path / "s")
    t = Survey.load(tmp_path / "s")
    assert t.name == s.name and t.splits == s.splits and t.origin == s.origin
    assert t.metadata == s.metadata
    for a, b in zip(s.lines, t.lines, strict=True):
        for key in ("time_s", "position", "rotation", "altitude_m", "intensity", "range_m"):
            np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
        np.testing.assert_array_equal(a.extras["true_n_lat"], b.extras["true_n_lat"])
        assert a.sensor == b.sensor
    np.testing.assert_array_equal(s.grid.heights, t.grid.heights)
    assert (t.grid.x0, t.grid.y0, t.grid.cell_size) == (s.grid.x0, s.grid.y0, s.grid.cell_size)
    assert "32633" in t.grid.crs


def test_grid_sample_and_gradient():
    g = BathyGrid(2.0 * np.arange(5.0)[None, :] + 0 * np.arange(4.0)[:, None], 0.0, 0.0, 1.0)
    assert float(g.sample(np.array(1.5), np.array(1.0))) == pytest.approx(3.0)
    assert np.isnan(g.sample(np.array(10.0), np.array(1.0)))
    gx, gy = g.sample_gradient(np.array([2.0]), np.array([2.0]))
    assert gx[0] == pytest.approx(2.0) and gy[0] == pytest.approx(0.0)
    mesh = g.to_mesh()
    assert len(mesh.faces) == 2 * 3 * 4


def test_altimeter_points_skip_missing():
    line = make_line()
    line.altitude_m[2] = np.nan
    pts = line.altimeter_points()
    assert pts.shape == (4, 3)
    np.testing.assert_allclose(pts[:, 2], -12.0)


def _damage_line(tmp_path, **changes):
    s = make_survey()
    s.save(tmp_path / "s")
    path = tmp_path / "s" / "lines" / "L1.npz"
    with np.load(path) as d:
        arrays = {k: d[k] for k in d.files}
    arrays.update(changes)
    np.savez_compressed(path, **arrays)
    return tmp_path / "s"


@pytest.mark.parametrize(
    "changes, field, found",
    [
        ({"position": np.full((5, 3), np.nan)}, "position", "NaN at ping 0"),
        ({"position": np.zeros((4, 3))}, "position", "(4, 3)"),
        ({"time_s": np.array([0.0, 0.1, 0.1, 0.3, 0.4])}, "time_s", "non-increasing at ping 2"),
        ({"rotation": np.tile(np.diag([1.0, 2.0, 1.0]), (5, 1, 1))}, "rotation", "ping 0"),
        ({"range_m": -np.linspace(1.0, 30.0, 8)}, "range_m", "positive"),
        ({"intensity": np.zeros((5, 2, 7))}, "intensity", "(5, 2, 7)"),
        ({"altitude_m": np.full(5, -1.0)}, "altitude_m", "negative"),
    ],
)
def test_bad_line_fields_are_named(tmp_path, changes, field, found):
    folder = _damage_line(tmp_path, **changes)
    with pytest.raises(SurveyFormatError) as err:
        Survey.load(folder)
    msg = str(err.value)
    assert "L1.npz" in msg and f"field '{field}'" in msg and found in msg
    assert "\n" not in msg


def test_missing_array_and_missing_files(tmp_path):
    s = make_survey()
    s.save(tmp_path / "s")
    path = tmp_path / "s" / "lines" / "L0.npz"
    with np.load(path) as d:
        arrays = {k: d[k] for k in d.files if k != "altitude_m"}
    np.savez_compressed(path, **arrays)
    with pytest.raises(SurveyFormatError, match=r"L0.npz: field 'altitude_m'.*missing"):
        Survey.load(tmp_path / "s")
    path.unlink()
    with pytest.raises(SurveyFormatError, match=r"L0.npz: field 'file'.*missing file"):
        Survey.load(tmp_path / "s")
    with pytest.raises(SurveyFormatError, match=r"survey.yaml: field 'file'"):
        Survey.load(tmp_path / "nowhere")


def test_truncated_line_file(tmp_path):
    s = make_survey()
    s.save(tmp_path / "s")
    path = tmp_path / "s" / "lines" / "L0.npz"
    path.write_bytes(path.read_bytes()[:50])
    with pytest.raises(SurveyFormatError, match=r"L0.npz: field 'file': expected a readable"):
        Survey.load(tmp_path / "s")


def test_manifest_errors(tmp_path):
    s = make_survey()
    s.save(tmp_path / "s")
    manifest_path = tmp_path / "s" / "survey.yaml"
    manifest = yaml.safe_load(manifest_path.read_text())
    manifest["splits"]["test"] = ["nope"]
    manifest_path.write_text(yaml.safe_dump(manifest))
    with pytest.raises(SurveyFormatError, match=r"field 'splits.test'.*\['nope'\]"):
        Survey.load(tmp_path / "s")
    manifest["splits"]["test"] = ["L1"]
    manifest["sensor"]["beam_width_rad"] = 0.0
    manifest_path.write_text(yaml.safe_dump(manifest))
    with pytest.raises(SurveyFormatError, match=r"field 'sensor'"):
        Survey.load(tmp_path / "s")


def test_sensor_params_validated():
    with pytest.raises(SurveyFormatError, match="beam_width_rad"):
        SensorParams(beam_width_rad=math.pi)
    assert SensorParams(tilt_rad=0.5, beam_width_rad=1.0).beam_limits_rad == (0.0, 1.0)


def test_split_lines_unknown_split():
    s = make_survey()
    assert [ln.name for ln in s.split_lines("all")] == ["L0", "L1"]
    with pytest.raises(ValueError, match="split 'val' does not exist"):
        s.split_lines("val")


def test_duplicate_line_names_rejected():
    with pytest.raises(SurveyFormatError, match="unique line names"):
        Survey(name="x", lines=[make_line("A"), make_line("A")])


def test_grid_geotiff_round_trip_north_up(tmp_path):
    import rasterio

    h = np.arange(12.0).reshape(3, 4)
    g = BathyGrid(h, 100.0, 200.0, 2.0, crs="EPSG:32633")
    g.save_geotiff(tmp_path / "g.tif")
    with rasterio.open(tmp_path / "g.tif") as src:
        top_row = src.read(1)[0]  # north-up file: first row is the northmost
        assert src.transform.c == 99.0 and src.transform.f == 205.0
    np.testing.assert_array_equal(top_row, h[-1])
    back = BathyGrid.load_geotiff(tmp_path / "g.tif")
    np.testing.assert_array_equal(back.heights, h)
    assert (back.x0, back.y0, back.cell_size) == (100.0, 200.0, 2.0)
