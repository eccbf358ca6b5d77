"""``sss2bathy-map`` over tiles: the ``tile`` settings, the plan on an imported survey, the
blend of tile runs (``sss2bathy-map-blend``) and, end to end (slow), a 2 x 1 plan fitted as a
multirun and blended against the untiled map, on the simulator's tiny lines written as XTF."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
from omegaconf import OmegaConf

from sss2bathy.cli.map import map_survey_config
from sss2bathy.cli.map_blend import blend_tile_runs, read_tile_runs
from sss2bathy.cli.map_tiles import TILE_JSON, plan_tiles, tile_settings, tile_survey_config
from sss2bathy.survey import BathyGrid
from sss2bathy.survey.tiles import footprint_bounds, tile_layout, tile_to_dict
from tests.cli.test_map import _common as map_test_common
from tests.cli.test_map import _run as run_module

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"
ORIGIN = {"crs": "EPSG:32633", "easting": 500000.0, "northing": 6000000.0}


# ------------------------------------------------------------------ fast: settings
@pytest.mark.parametrize(
    ("tile", "match"),
    [
        ({"size_m": 30, "overlap_m": 30}, r"^tile\.overlap_m: expected 0 <= overlap < tile\.size_m \(30 m\), found 30$"),
        ({"size_m": -5}, r"^tile\.size_m: expected a positive"),
        ({"size_m": [10, 20, 30]}, r"^tile\.size_m: expected"),
        ({"size_m": 50, "index": -1}, r"^tile\.index: expected a tile number >= 0"),
        ({"size_m": 50, "margin_m": -1}, r"^tile\.margin_m: expected a distance >= 0"),
        ({"size_m": 50, "min_pings": 1}, r"^tile\.min_pings: expected a count >= 2"),
    ],
)  # fmt: skip
def test_tile_settings_errors_are_one_line_naming_the_key(tile, match):
    with pytest.raises(ValueError, match=match):
        tile_settings({"tile": tile})


def test_tile_settings_off_and_on():
    cfg = OmegaConf.load(CONF / "map.yaml")
    assert tile_settings(cfg) is None  # off by default: the untiled route
    on = tile_settings({"tile": {**cfg.tile, "size_m": [80, 40], "index": 1}})
    assert on == {
        "size_m": [80.0, 40.0],
        "overlap_m": 30.0,
        "index": 1,
        "margin_m": None,
        "min_pings": 20,
    }


# ------------------------------------------------------------------ the survey
def _map_cfg(folder: Path, crs: str, data_dir: Path, **tile) -> dict:
    cfg = OmegaConf.load(CONF / "map.yaml")
    survey = OmegaConf.load(CONF / "data" / "survey" / "xtf.yaml")
    cfg.survey = OmegaConf.merge(survey, cfg.survey)
    cfg.files = str(folder)
    cfg.survey.crs = crs
    cfg.survey.n_bins = None
    cfg.paths = {"data_dir": str(data_dir), "output_dir": str(data_dir.parent / "outputs")}
    cfg.tile = {**cfg.tile, **tile}
    return cfg


def test_plan_covers_the_footprint_and_checks_the_index(tmp_path, tiny_xtf):
    folder, crs = tiny_xtf
    cfg = _map_cfg(folder, crs, tmp_path / "data", size_m=1000.0, index=0)
    tiles, survey, _ = plan_tiles(cfg, map_survey_config(cfg))
    assert len(tiles) == 1 and tiles[0].bounds == footprint_bounds(survey.lines)
    # a plan of one tile is the untiled route: the job fits the whole imported survey
    assert tile_survey_config(cfg, map_survey_config(cfg)) is None
    x0, x1, y0, y1 = footprint_bounds(survey.lines)
    half = (x1 - x0) / 2 + 5.0
    cfg = _map_cfg(folder, crs, tmp_path / "data", size_m=[half + 1, y1 - y0 + 1], overlap_m=10.0)
    tiles, _, _ = plan_tiles(cfg, map_survey_config(cfg))
    assert [t.index for t in tiles] == [(0, 0), (1, 0)]
    cfg.tile.index = 2
    with pytest.raises(ValueError, match=r"^tile\.index: expected 0\.\.1 \(the plan's 2 tiles"):
        plan_tiles(cfg, map_survey_config(cfg))
    cfg.tile.index = 1
    tile_cfg = tile_survey_config(cfg, map_survey_config(cfg))
    from sss2bathy.survey import Survey

    cut = Survey.load(tile_cfg["path"])
    n_all = sum(ln.n_pings for ln in survey.lines)
    n_cut = sum(ln.n_pings for ln in cut.lines)
    assert 0 < n_cut <= n_all and cut.origin == survey.origin
    assert set(cut.splits["test"]) == {ln.name for ln in cut.lines}
    # the tile's SIREN spans the tile's pings: its detail omega0 comes from their extent
    from hydra import initialize_config_dir

    from sss2bathy.cli.map import compose_train_config
    from sss2bathy.cli.map_settings import choose_map_settings, scale_of_survey

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        train = compose_train_config(cfg, tmp_path / "run", {"scale": "tiny"})
    assert train.data.survey.path == tile_cfg["path"]
    tile_scale = scale_of_survey(tile_cfg["path"])
    whole_scale = scale_of_survey(tmp_path / "data" / survey.name)
    whole = choose_map_settings(whole_scale, 1.0, None, None, 16)
    assert max(tile_scale.half_extent_m) < max(whole_scale.half_extent_m)
    chosen = choose_map_settings(tile_scale, 1.0, None, None, 16)
    assert train.model.siren.detail_omega0 == pytest.approx(round(chosen.omega0, 3))
    assert chosen.omega0 < whole.omega0


# ------------------------------------------------------------------ fast: the blend
def _tile_run(folder: Path, index: int, tiles, grid: BathyGrid, method: str = "siren_lambert"):
    from sss2bathy.eval.maps import save_map_outputs
    from sss2bathy.io.export import add_geotiff_tags, provenance_tags

    run = folder / f"tile_{index}"
    save_map_outputs(run, grid, origin=ORIGIN, coverage=np.isfinite(grid.heights))
    add_geotiff_tags(run / "map.tif", provenance_tags(method=method, survey_kind="xtf"))
    record = {"index": index, "tiles": [tile_to_dict(t) for t in tiles], "survey": "s"}
    record.update(origin=ORIGIN, size_m=[60.0, 40.0], overlap_m=tiles[0].overlap_m)
    (run / TILE_JSON).write_text(json.dumps(record))
    return run


def _read(path: Path):
    with rasterio.open(path) as src:
        return src.read(1, masked=True).filled(np.nan), src.transform, src.tags()


def test_one_tile_blends_to_its_own_map(tmp_path):
    tiles = tile_layout((0.0, 40.0, 0.0, 20.0), 100.0, 10.0)
    rng = np.random.default_rng(0)
    z = rng.normal(-20, 1, (41, 81)).astype(np.float32)
    z[:5, :7] = np.nan  # no coverage there
    run = _tile_run(tmp_path, 0, tiles, BathyGrid(z, 0.25, 0.25, 0.5))
    from sss2bathy.io.export import write_geotiff

    sigma = np.where(np.isfinite(z), 0.1 + 0.01 * np.arange(81), np.nan).astype(np.float32)
    write_geotiff(
        BathyGrid(sigma, 0.25, 0.25, 0.5), run / "uncertainty.tif", origin=ORIGIN,
        mask=np.isfinite(sigma),
    )  # fmt: skip
    paths = blend_tile_runs(tmp_path)
    assert {"map_tif", "map_png", "uncertainty_tif", "uncertainty_png"} <= set(paths)
    np.testing.assert_allclose(
        _read(paths["uncertainty_tif"])[0], _read(run / "uncertainty.tif")[0], rtol=1e-6
    )
    got, transform, tags = _read(tmp_path / "map.tif")
    want, want_transform, want_tags = _read(run / "map.tif")
    assert transform == want_transform
    np.testing.assert_array_equal(got, want)  # NaN where the tile has none
    assert tags["SSS2BATHY_METHOD"] == "siren_lambert"
    assert tags["SSS2BATHY_VERTICAL_REFERENCE"] == want_tags["SSS2BATHY_VERTICAL_REFERENCE"]
    assert (
        "1 tiles of at most 60 x 40 m" in tags["SSS2BATHY_TILES"]
        and (tmp_path / "map.png").is_file()
    )


def _two_tiles(tmp_path: Path, offset: float, overlap: float = 20.0):
    """Two tiles over x 0..100 m whose maps are one slope + ``offset`` in the east tile,
    each on its own grid (its tile's bounds + 3 m), one cell lattice."""
    tiles = tile_layout((0.0, 100.0, 0.0, 30.0), (60.0, 40.0), overlap)
    cell = 0.5
    for k, t in enumerate(tiles):
        x0, x1, y0, y1 = t.bounds
        xs = np.arange(max(x0 - 3, 0) + cell / 2, min(x1 + 3, 100), cell)
        ys = np.arange(y0 + cell / 2, y1, cell)
        xx, _ = np.meshgrid(xs, ys)
        z = -20 + 0.05 * xx + (offset if k == 1 else 0.0)
        _tile_run(tmp_path, k, tiles, BathyGrid(z.astype(np.float32), xs[0], ys[0], cell))
    return tiles


def test_two_tiles_blend_without_a_step_over_their_union(tmp_path):
    tiles = _two_tiles(tmp_path, offset=0.4, overlap=20.0)
    blend_tile_runs(tmp_path)
    z, transform, _ = _read(tmp_path / "map.tif")
    assert np.isfinite(z).all()  # the union of the tiles' coverage: x 0..100 m, y 0..30 m
    assert z.shape == (60, 200) and transform.c == ORIGIN["easting"]
    steps = np.abs(np.diff(z, axis=1)) - 0.05 * 0.5  # minus the slope's own step
    # a 0.4 m disagreement spread over the 20 m band: at most 0.4 * pi/2 * 0.5/20 per cell
    assert steps.max() <= 0.4 * np.pi / 2 * 0.5 / 20 + 1e-4
    # at the core border itself (where a hard cut would step 0.4 m) a few cm at most
    border = int(round(tiles[0].core[1] / 0.5))
    assert abs(z[:, border] - z[:, border - 1]).max() < 0.05


def test_blend_errors_name_the_missing_tiles_and_a_mixed_plan(tmp_path, capsys):
    from sss2bathy.cli.map_blend import main

    tiles = tile_layout((0.0, 100.0, 0.0, 60.0), (40.0, 40.0), 10.0)
    grid = BathyGrid(np.zeros((4, 4), np.float32), 0.25, 0.25, 0.5)
    _tile_run(tmp_path, 1, tiles, grid)
    _tile_run(tmp_path, 4, tiles, grid)
    with pytest.raises(SystemExit) as exit_:
        main([str(tmp_path)])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    missing = ", ".join(str(k) for k in range(len(tiles)) if k not in (1, 4))
    assert f"expected the {len(tiles)} tiles of the plan, found tiles {missing} missing" in err
    other = tmp_path / "other"
    _tile_run(other, 0, tile_layout((0.0, 100.0, 0.0, 60.0), (60.0, 60.0), 10.0), grid)
    _tile_run(other, 1, tiles, grid)
    with pytest.raises(ValueError, match="expected the plan of .*found another"):
        read_tile_runs(other)
    with pytest.raises(ValueError, match="found none"):
        read_tile_runs(tmp_path / "nothing")


# ------------------------------------------------------------------ slow: end to end
def _run(args: list[str], tmp: Path, module: str = "sss2bathy.cli.map"):
    return run_module(module, args, tmp, timeout=900)


@pytest.mark.slow
def test_two_tiles_fitted_and_blended_match_the_untiled_coverage(tmp_path, tiny_xtf):
    folder, crs = tiny_xtf
    cfg = _map_cfg(folder, crs, tmp_path / "data", size_m=1000.0)
    _, survey, _ = plan_tiles(cfg, map_survey_config(cfg))
    x0, x1, y0, y1 = footprint_bounds(survey.lines)
    overlap = 10.0
    size = [f"{(x1 - x0) / 2 + overlap / 2 + 1:.1f}", f"{y1 - y0 + 1:.1f}"]
    common = [
        f"files={folder}",
        f"survey.crs={crs}",
        "survey.n_bins=null",
        "holdout.fraction=0",
        "verdict.folds=0",
        "verdict.overlap.enabled=false",
        "mosaic.placement=none",
        "stac=false",
        "report=false",
        *map_test_common(tmp_path),
        'overrides=["callbacks=none","trainer.enable_progress_bar=false"]',
    ]
    tiled = [f"tile.size_m=[{size[0]},{size[1]}]", f"tile.overlap_m={overlap}"]
    plan = _run([*common, *tiled, f"hydra.run.dir={tmp_path / 'plan'}"], tmp_path)
    assert plan.returncode == 0, plan.stderr[-3000:]
    assert "2 tiles" in plan.stdout and "'tile.index=range(0,2)'" in plan.stdout
    out = tmp_path / "tiles"
    jobs = _run(
        ["-m", *common, *tiled, "tile.index=range(0,2)", f"hydra.sweep.dir={out}"], tmp_path
    )
    assert jobs.returncode == 0, jobs.stderr[-3000:]
    assert (out / "tile_0" / "map.tif").is_file() and (out / "tile_1" / "map.tif").is_file()
    blended = _run([str(out)], tmp_path, "sss2bathy.cli.map_blend")
    assert blended.returncode == 0, blended.stderr[-3000:]
    single = _run([*common, f"hydra.run.dir={tmp_path / 'single'}"], tmp_path)
    assert single.returncode == 0, single.stderr[-3000:]

    z, transform, tags = _read(out / "map.tif")
    s, s_transform, s_tags = _read(tmp_path / "single" / "map.tif")
    assert s_transform.a == transform.a
    col = round((s_transform.c - transform.c) / transform.a)
    row = round((transform.f - s_transform.f) / transform.a)
    assert row >= 0 and col >= 0  # the single map's grid lies within the blend's lattice
    on = z[row : row + s.shape[0], col : col + s.shape[1]]
    assert np.isfinite(z).sum() == np.isfinite(on).sum()  # nothing outside the untiled grid
    np.testing.assert_array_equal(np.isfinite(on), np.isfinite(s))  # the same coverage
    assert tags["SSS2BATHY_UNITS"] == "m" and "SSS2BATHY_TILES" in tags
    for key in ("SSS2BATHY_METHOD", "SSS2BATHY_VERTICAL_REFERENCE", "SSS2BATHY_VERSION"):
        assert tags.get(key) == s_tags.get(key), key
    # across the core border the blend steps from cell to cell about as the single fit does
    record = json.loads((out / "tile_0" / TILE_JSON).read_text())
    border_x = record["tiles"][0]["core"][1] + _origin_shift(record)["easting"]

    def border_step(a: np.ndarray, t) -> float:
        j = int(round((border_x - t.c) / t.a))
        both = np.isfinite(a[:, j]) & np.isfinite(a[:, j - 1])
        assert both.sum() >= 10
        return float(np.abs(a[both, j] - a[both, j - 1]).mean())

    step, single_step = border_step(z, transform), border_step(s, s_transform)
    print(f"border step: blend {step:.4f} m, single fit {single_step:.4f} m")
    assert step <= 2 * single_step + 0.01, (step, single_step)


def _origin_shift(record: dict) -> dict:
    return {k: float(record["origin"].get(k) or 0.0) for k in ("easting", "northing")}
