"""Surveys simulated over a real bathymetry grid (issue #19): ``data.survey.terrain.grid``."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from sss2bathy.io.grids import read_grid, spike_mask
from sss2bathy.sim.config import SyntheticSurveyConfig
from sss2bathy.sim.generate import generate_survey
from sss2bathy.sim.plan import (
    SwathOutsideTerrainError,
    footprint_clearance,
    footprint_layout,
    plan_survey,
)
from sss2bathy.sim.sonar import MASK_NO_HIT
from sss2bathy.sim.terrain import fill_holes, grid_terrain, split_holes
from sss2bathy.survey import BathyGrid

CONF = Path(__file__).resolve().parents[2] / "conf"
REALDATA = Path(
    os.environ.get(
        "SSS2BATHY_REALDATA", Path(__file__).resolve().parents[3] / "shared" / "realdata"
    )
)
GGOUTLIER = REALDATA / "ggoutlier_DepthSurface_1m.tif"
needs_realdata = pytest.mark.skipif(not GGOUTLIER.is_file(), reason=f"{GGOUTLIER} not present")
CRS = "EPSG:32633"
E0, N0 = 680000.0, 6580000.0


def _write(tmp: Path, name: str, heights: np.ndarray, cell: float = 0.5) -> str:
    """A north-up GeoTIFF of ``heights`` (row 0 south) with its SW cell centre at E0, N0."""
    path = tmp / name
    BathyGrid(heights.astype(np.float32), E0, N0, cell, CRS).save_geotiff(path)
    return str(path)


def _survey(name: str, scale: str, **overrides) -> dict:
    """Plain ``data.survey`` of a preset at a scale as Hydra composes it, with ``overrides``
    (``a__b=value`` sets ``a.b``; they replace interpolations before resolving)."""
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        composed = compose(
            config_name="prepare", overrides=[f"data/survey={name}", f"scale={scale}"]
        )
    for dotted, value in overrides.items():
        OmegaConf.update(composed.data.survey, dotted.replace("__", "."), value, force_add=True)
    return OmegaConf.to_container(composed.data.survey, resolve=True)


def _tiny(**overrides) -> dict:
    """synthetic_d1 at tiny scale with a level vehicle and no relief (a flat 8 m seabed)."""
    flat = dict(
        terrain__relief_amplitudes_m=[0.0] * 6,
        terrain__regional_slope_deg=0.0,
        terrain__ridges__density_per_ha=0.0,
        terrain__boulders__density_per_ha=0.0,
        plan__motion={"roll_deg": 0.0, "pitch_deg": 0.0, "yaw_deg": 0.0, "period_s": 6.0},
    )
    return _survey("synthetic_d1", "tiny", **{**flat, **overrides})


def _as_grid_config(cfg: dict, path: str, **terrain) -> dict:
    """``cfg`` with its procedural terrain replaced by the grid at ``path``."""
    out = {k: v for k, v in cfg.items() if k != "origin"}
    keep = ("relief_wavelengths_m", "relief_amplitudes_m", "boulders", "texture_cell_m")
    out["terrain"] = {
        "grid": path,
        "mbes_noise_m": cfg["terrain"]["mbes_noise_m"],
        **{k: cfg["terrain"][k] for k in keep},
        **terrain,
    }
    return out


def test_flat_grid_renders_the_procedural_flat_seabed(tmp_path):
    cfg = _tiny()
    nx = round(cfg["terrain"]["size_m"][0] / cfg["terrain"]["cell_m"]) + 1
    ny = round(cfg["terrain"]["size_m"][1] / cfg["terrain"]["cell_m"]) + 1
    depth = cfg["terrain"]["mean_depth_m"]
    path = _write(tmp_path, "flat.tif", np.full((ny, nx), -depth))
    procedural, p_terrain = generate_survey(SyntheticSurveyConfig.from_mapping(cfg))
    real, r_terrain = generate_survey(
        SyntheticSurveyConfig.from_mapping(_as_grid_config(cfg, path))
    )
    assert real.origin == {"crs": CRS, "easting": E0, "northing": N0}
    np.testing.assert_array_equal(r_terrain.heights, p_terrain.heights)
    np.testing.assert_array_equal(r_terrain.materials, p_terrain.materials)
    assert [ln.name for ln in real.lines] == [ln.name for ln in procedural.lines]
    for a, b in zip(real.lines, procedural.lines, strict=True):
        np.testing.assert_array_equal(a.intensity, b.intensity)
        np.testing.assert_array_equal(a.extras["true_mask"], b.extras["true_mask"])
    np.testing.assert_array_equal(real.grid.heights, procedural.grid.heights)  # MBES + noise


def test_tilted_plane_grid_gives_the_expected_n_lat_on_both_heads(tmp_path):
    cfg = _tiny(plan__n_train=2, plan__n_test=2)
    slope = 0.15  # z rises to the East
    nx = round(cfg["terrain"]["size_m"][0] / 0.5) + 1
    ny = round(cfg["terrain"]["size_m"][1] / 0.5) + 1
    x = np.arange(nx) * 0.5
    heights = np.broadcast_to(-10.0 + slope * (x - x.mean()), (ny, nx))
    path = _write(tmp_path, "plane.tif", heights)
    survey, _ = generate_survey(SyntheticSurveyConfig.from_mapping(_as_grid_config(cfg, path)))
    expected = slope / math.sqrt(1 + slope**2)
    seen = set()
    for ln in survey.lines:
        heading = round(math.degrees(float(np.median(_headings(ln))))) % 360
        n_lat, valid = ln.extras["true_n_lat"], ln.extras["true_mask"] == 0
        port, starboard = n_lat[:, 0][valid[:, 0]], n_lat[:, 1][valid[:, 1]]
        # heading North, port looks West, down the slope: tilted away (positive), and the
        # starboard head looks up it (negative); heading South the other way round;
        # East/West lines look along the contours
        sign = {0: 1.0, 180: -1.0, 90: 0.0, 270: 0.0}[heading]
        assert np.median(port) == pytest.approx(sign * expected, abs=0.01)
        assert np.median(starboard) == pytest.approx(-sign * expected, abs=0.01)
        seen.add(heading)
    assert {0, 180} <= seen and seen & {90, 270}


def _headings(line) -> np.ndarray:
    fwd = line.rotation[:, :2, 0]
    return np.arctan2(fwd[:, 0], fwd[:, 1]) % (2 * math.pi)


def test_spike_filter_masks_cells_far_from_their_median():
    h = np.zeros((9, 9))
    h[4, 4], h[1, 7] = 3.0, -1.5
    h[6, 2] = np.nan
    assert np.argwhere(spike_mask(h, 1.0)).tolist() == [[1, 7], [4, 4]]
    assert not spike_mask(h, 4.0).any()
    with pytest.raises(ValueError, match="window_cells"):
        spike_mask(h, 1.0, 4)


def test_small_holes_are_filled_and_large_ones_are_no_seabed():
    valid = np.ones((30, 30), bool)
    valid[5:7, 5:7] = False  # 4 cells = 1 m2 at 0.5 m: small
    valid[12:25, 12:25] = False  # 169 cells = 42 m2: large
    valid[0:3, 20:23] = False  # small but at the edge: outside the survey
    small, large = split_holes(valid, 0.5, 25.0)
    assert small.sum() == 4 and small[5:7, 5:7].all()
    assert large[12:25, 12:25].all() and large[0:3, 20:23].all()
    assert (small | large).sum() == (~valid).sum()
    plane = np.add.outer(np.arange(30) * 0.1, np.arange(30) * -0.05)
    filled = fill_holes(np.where(valid, plane, np.nan), small)
    np.testing.assert_allclose(filled[small], plane[small], atol=1e-3)  # a plane stays a plane
    assert np.isnan(filled[large]).all()  # never silently zero


def _holes_and_spikes_grid(tmp_path: Path) -> tuple[str, np.ndarray]:
    cfg = _tiny()
    nx = round(cfg["terrain"]["size_m"][0] / 0.5) + 1
    ny = round(cfg["terrain"]["size_m"][1] / 0.5) + 1
    heights = np.full((ny, nx), -8.0)
    heights[10, 10] = -4.0  # a spike (4 m above its neighbours)
    heights[40:42, 30:32] = np.nan  # a small hole (1 m2)
    heights[32:48, 40:60] = np.nan  # a large hole (80 m2) between the planned lines
    return _write(tmp_path, "holes.tif", heights), heights


@pytest.mark.parametrize("filter_spikes", [True, False])
def test_holes_and_spikes_are_handled_as_configured(tmp_path, filter_spikes):
    path, heights = _holes_and_spikes_grid(tmp_path)
    spikes = {"enabled": filter_spikes, "threshold_m": 1.0, "window_cells": 5}
    cfg = _as_grid_config(_tiny(), path, spike_filter=spikes, fill_max_area_m2=25.0)
    cfg["plan"] = {**cfg["plan"], "heading_deg": 0.0, "margin_m": 1.0}
    config = SyntheticSurveyConfig.from_mapping(cfg)
    terrain, source = grid_terrain(config.terrain, config.materials, np.random.default_rng(0))
    assert np.isfinite(terrain.heights).all()
    assert terrain.no_seabed[32:48, 40:60].all() and terrain.no_seabed.sum() == 320
    assert source.filled[40:42, 30:32].all()
    assert terrain.heights[40, 30] == pytest.approx(-8.0)  # filled for rendering
    flags = source.flags()
    assert flags[40, 30] == 1 and flags[40, 50] == 3
    if filter_spikes:
        assert source.spikes[10, 10] and source.spikes.sum() == 1 and flags[10, 10] == 2
        assert terrain.heights[10, 10] == pytest.approx(-8.0)
    else:
        assert not source.spikes.any() and terrain.heights[10, 10] == -4.0
    mesh = terrain.to_mesh()
    assert len(mesh.faces) < 2 * (terrain.heights.shape[0] - 1) * (terrain.heights.shape[1] - 1)

    survey, _ = generate_survey(config)
    mbes = survey.grid.heights
    assert np.isnan(mbes[32:48, 40:60]).all() and np.isnan(mbes[40:42, 30:32]).all()
    assert np.isnan(mbes[10, 10]) == filter_spikes  # the truth is the (filtered) grid
    assert np.nanmax(np.abs(mbes + 8.0)) < 0.2 or not filter_spikes
    hits_in_hole = 0
    for ln in survey.lines:
        mask = ln.extras["true_mask"]
        pts = ln.extras["true_points"][mask == 0]
        ix, iy = np.rint(pts[:, 0] / 0.5).astype(int), np.rint(pts[:, 1] / 0.5).astype(int)
        hits_in_hole += int(terrain.no_seabed[iy.clip(0, 80), ix.clip(0, 100)].sum())
    assert hits_in_hole == 0
    if filter_spikes:  # the bins looking into the large hole are no hit, not shadow
        level = np.where(np.isfinite(heights), heights, -8.0)
        level[10, 10] = -8.0
        cfg["terrain"]["grid"] = _write(tmp_path, "level.tif", level)
        cfg["plan"]["heading_deg"] = None  # the whole rectangle: the lawnmower over it
        whole, _ = generate_survey(SyntheticSurveyConfig.from_mapping(cfg))
        no_hit = sum(int((ln.extras["true_mask"] == MASK_NO_HIT).sum()) for ln in survey.lines)
        base = sum(int((ln.extras["true_mask"] == MASK_NO_HIT).sum()) for ln in whole.lines)
        assert no_hit > base + 500


def test_sub_cell_detail_refines_rendering_but_not_the_truth(tmp_path):
    cfg = _tiny()
    nx = round(cfg["terrain"]["size_m"][0] / 0.5) + 1
    ny = round(cfg["terrain"]["size_m"][1] / 0.5) + 1
    path = _write(tmp_path, "flat.tif", np.full((ny, nx), -8.0))
    boulders = {**cfg["terrain"]["boulders"], "density_per_ha": 200.0}
    grid_cfg = _as_grid_config(
        cfg, path, detail=True, detail_cell_m=0.25, boulders=boulders, mbes_noise_m=0.0,
        relief_wavelengths_m=[1.0, 0.5], relief_amplitudes_m=[0.02, 0.01],
    )  # fmt: skip
    config = SyntheticSurveyConfig.from_mapping(grid_cfg)
    terrain, source = grid_terrain(config.terrain, config.materials, np.random.default_rng(0))
    assert terrain.cell_m == 0.25 and terrain.heights.shape == (2 * ny - 1, 2 * nx - 1)
    assert len(terrain.boulders) > 10 and terrain.heights.max() > -7.8
    rock = config.materials.index("rock")
    assert (terrain.materials == rock).any()
    survey, _ = generate_survey(config)
    assert survey.grid.cell_size == 0.5
    np.testing.assert_array_equal(survey.grid.heights, np.full((ny, nx), -8.0, np.float32))


def test_materials_come_from_a_classification_raster(tmp_path):
    cfg = _tiny()
    nx = round(cfg["terrain"]["size_m"][0] / 0.5) + 1
    ny = round(cfg["terrain"]["size_m"][1] / 0.5) + 1
    path = _write(tmp_path, "flat.tif", np.full((ny, nx), -8.0))
    classes = np.zeros((ny, nx))
    classes[:, nx // 2 :] = 2  # mud west, gravel east
    raster = _write(tmp_path, "classes.tif", classes)
    config = SyntheticSurveyConfig.from_mapping(_as_grid_config(cfg, path, materials_raster=raster))
    terrain, _ = grid_terrain(config.terrain, config.materials, np.random.default_rng(0))
    np.testing.assert_array_equal(terrain.materials, classes.astype(np.uint8))
    bad = _write(tmp_path, "bad.tif", classes + 7)
    config = SyntheticSurveyConfig.from_mapping(_as_grid_config(cfg, path, materials_raster=bad))
    with pytest.raises(ValueError, match=r"materials_raster: expected material indices 0\.\.3"):
        grid_terrain(config.terrain, config.materials, np.random.default_rng(0))


def test_grid_config_errors_are_one_line_and_named(tmp_path):
    cfg = _tiny()
    missing = str(tmp_path / "nowhere" / "grid.tif")
    with pytest.raises(ValueError, match=r"data\.survey\.terrain\.grid: expected an existing") as e:
        SyntheticSurveyConfig.from_mapping(_as_grid_config(cfg, missing))
    assert "\n" not in str(e.value) and missing in str(e.value)
    path = _write(tmp_path, "flat.tif", np.full((20, 20), -8.0))
    both = _as_grid_config(cfg, path)
    both["terrain"]["size_m"] = [10.0, 10.0]
    with pytest.raises(ValueError, match=r"the grid gives them"):
        SyntheticSurveyConfig.from_mapping(both)
    with pytest.raises(ValueError, match=r"origin: expected no origin"):
        SyntheticSurveyConfig.from_mapping({**_as_grid_config(cfg, path), "origin": cfg["origin"]})
    with pytest.raises(ValueError, match=r"apply to a grid terrain only"):
        SyntheticSurveyConfig.from_mapping(_survey("synthetic_d1", "tiny", terrain__detail=True))


def _rotated_footprint(angle_deg: float, size=(160, 120), cell=1.0) -> BathyGrid:
    """A level grid whose valid cells form a 100 x 40 m rectangle rotated by ``angle_deg``."""
    ny, nx = size[1], size[0]
    x, y = np.meshgrid(np.arange(nx) * cell, np.arange(ny) * cell)
    a = math.radians(angle_deg)
    u = (x - 80) * math.sin(a) + (y - 60) * math.cos(a)  # along the heading
    v = (x - 80) * math.cos(a) - (y - 60) * math.sin(a)
    inside = (np.abs(u) <= 50) & (np.abs(v) <= 20)
    return BathyGrid(np.where(inside, -30.0, np.nan).astype(np.float32), E0, N0, cell, CRS)


def test_planner_lays_lines_inside_a_rotated_footprint(tmp_path):
    grid = _rotated_footprint(60.0)
    path = tmp_path / "rotated.tif"
    grid.save_geotiff(path)
    cfg = _as_grid_config(_tiny(), str(path))
    cfg["plan"] = {**cfg["plan"], "mount": "auv", "altitude_m": 6.0, "n_train": 3, "n_test": 2}
    cfg["plan"].update(line_spacing_m=6.0, margin_m=2.0, min_line_m=20.0)
    cfg["plan"]["train_cross_fraction"] = 0.0
    config = SyntheticSurveyConfig.from_mapping(cfg)
    terrain, _ = grid_terrain(config.terrain, config.materials, np.random.default_rng(0))
    lines = plan_survey(config.plan, config.sonar, terrain, np.random.default_rng(0))
    main = [ln for ln in lines if ln.line_set == "main"]
    cross = [ln for ln in lines if ln.line_set == "cross"]
    assert len(main) == 4 and len(cross) == 1  # 3 train (all main) + 2 test (1 + 1)
    clear = footprint_clearance(terrain)
    for ln in lines:
        ix, iy = np.rint(ln.position[:, :2].T / terrain.cell_m).astype(int)
        assert (clear[iy, ix] >= 2.0).all()
        assert len(ln.time_s) * config.plan.speed_mps / config.plan.ping_rate_hz >= 20.0
    # the footprint's long axis: 60 deg (or 240, lawnmower); cross lines +90
    assert {round(math.degrees(ln.heading_rad)) for ln in main} == {60, 240}
    assert {round(math.degrees(ln.heading_rad)) % 180 for ln in cross} == {150}
    offsets = sorted(
        float(np.mean(ln.position[:, 0] - 80) * math.cos(math.radians(60)))
        - float(np.mean(ln.position[:, 1] - 60) * math.sin(math.radians(60)))
        for ln in main
    )
    np.testing.assert_allclose(np.diff(offsets), 6.0, atol=0.6)  # line_spacing_m apart
    with pytest.raises(ValueError, match=r"line_spacing_m: expected a spacing that fits 4"):
        footprint_layout(math.radians(60), 4, 15.0, 2.0, 0.75, 20.0, terrain, "main")
    with pytest.raises(SwathOutsideTerrainError, match="margin_m"):
        footprint_layout(math.radians(60), 1, None, 30.0, 0.75, 20.0, terrain, "main")


def _compose(scale: str, overrides: list[str] | None = None, config_name: str = "train"):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(
            config_name=config_name,
            overrides=["data/survey=synthetic_real_1m", f"scale={scale}", *(overrides or [])],
        )


@pytest.mark.parametrize("scale", ["tiny", "demo", "paper"])
def test_real_1m_preset_composes_at_every_scale(scale, monkeypatch):
    monkeypatch.setenv("SSS2BATHY_REALDATA", str(REALDATA))
    composed = _compose(scale)
    plain = OmegaConf.to_container(composed.data.survey, resolve=True)
    assert plain["name"] == f"synthetic_real_1m_{scale}"
    assert Path(plain["terrain"]["grid"]) == GGOUTLIER
    monkeypatch.delenv("SSS2BATHY_REALDATA")
    monkeypatch.setenv("SSS2BATHY_ROOT", "/some/project")
    composed = _compose(scale)
    default = OmegaConf.to_container(composed.data.survey, resolve=True)["terrain"]["grid"]
    assert default == "/some/project/../shared/realdata/ggoutlier_DepthSurface_1m.tif"
    with pytest.raises(ValueError, match=r"^data\.survey\.terrain\.grid: expected an existing"):
        SyntheticSurveyConfig.from_mapping(
            {**plain, "terrain": {**plain["terrain"], "grid": default}}
        )
    if GGOUTLIER.is_file():
        config = SyntheticSurveyConfig.from_mapping(plain)
        sized = "scale.survey.synthetic_real_1m"
        expected = (
            OmegaConf.select(composed, f"{sized}.plan.n_train", default=8),
            OmegaConf.select(composed, f"{sized}.plan.n_test", default=12),
            OmegaConf.select(composed, f"{sized}.sonar.n_bins", default=512),
        )
        assert (config.plan.n_train, config.plan.n_test, config.sonar.n_bins) == expected
        assert scale != "demo" or expected == (4, 6, 256)  # the demo the targets ran at
        assert config.plan.mount == "auv" and config.terrain.grid.spike_threshold_m == 1.0


@needs_realdata
def test_real_1m_grid_reads_and_plans_inside_its_footprint():
    config = SyntheticSurveyConfig.from_mapping(
        _survey("synthetic_real_1m", "demo", terrain__grid=str(GGOUTLIER))
    )
    terrain, source = grid_terrain(config.terrain, config.materials, np.random.default_rng(0))
    assert source.origin == {"crs": "EPSG:32751", "easting": 678572.0, "northing": 8344034.0}
    assert 40 <= source.spikes.sum() <= 55  # the ~48 injected spikes (README)
    z = source.heights[np.isfinite(source.heights)]
    assert z.min() > -48.2 and z.max() < -41.5  # the clean surface: -48.1 ... -41.6 m
    lines = plan_survey(config.plan, config.sonar, terrain, np.random.default_rng(0))
    assert sum(ln.split == "test" for ln in lines) == 6
    assert sum(ln.split == "train" for ln in lines) == 4
    for ln in lines:
        assert 9.0 < float(np.median(ln.altitude_m)) < 13.0
        ix, iy = np.rint(ln.position[:, :2].T).astype(int)
        assert terrain.seabed[iy, ix].all()


@pytest.mark.slow  # ~30-65 s on a shared 2-core CPU
@needs_realdata
def test_tiny_end_to_end_over_a_cropped_real_grid_is_scored_against_it(tmp_path, monkeypatch):
    """prepare + SIREN-GT-N2d at tiny scale over a 90 x 70 m crop of the real grid."""
    from sss2bathy.cli.train import train

    full = read_grid(GGOUTLIER)
    crop = BathyGrid(
        full.heights[30:100, 100:190], full.x0 + 100, full.y0 + 30, full.cell_size, full.crs
    )
    path = tmp_path / "crop.tif"
    crop.save_geotiff(path)
    run = tmp_path / "run"
    cfg = _compose(
        "tiny",
        [
            "experiment=siren_gt_n2d",
            f"data.survey.terrain.grid={path}",
            "data.survey.name=real_crop_tiny",
            f"paths.data_dir={tmp_path / 'data'}",
            f"paths.output_dir={tmp_path / 'outputs'}",
            "logger=none",
            "callbacks=none",
            f"model.output_dir={run}",
            "trainer.enable_progress_bar=false",
        ],
    )
    train(cfg, run_dir=run)
    import json

    metrics = json.loads((run / "metrics.json").read_text())
    assert np.isfinite(metrics["val/map_mae_m"]) and metrics["val/map_mae_m"] < 2.0
    assert np.isfinite(metrics["val/map_grad_cs"])
    from sss2bathy.survey import Survey

    survey = Survey.load(tmp_path / "data" / "real_crop_tiny")
    assert survey.origin["crs"] == "EPSG:32751"
    assert survey.origin["easting"] == pytest.approx(crop.x0)
    truth = np.where(np.isfinite(crop.heights), crop.heights, np.nan)
    both = np.isfinite(truth) & np.isfinite(survey.grid.heights)
    assert both.mean() > 0.5
    assert np.abs(survey.grid.heights[both] - truth[both]).max() < 0.2  # MBES = the grid
    assert (run / "map.tif").is_file()
    mapped = read_grid(run / "map.tif")
    assert mapped.crs == "EPSG:32751"
    assert crop.x0 - 1 <= mapped.x0 <= crop.x0 + 90


def test_xyz_depth_points_give_the_same_terrain_as_the_geotiff(tmp_path):
    cfg = _tiny()
    heights = -8.0 - 0.05 * np.add.outer(np.arange(41), np.arange(61)) * 0.5
    tif = _write(tmp_path, "slope.tif", heights)
    yy, xx = np.meshgrid(np.arange(41) * 0.5 + N0, np.arange(61) * 0.5 + E0, indexing="ij")
    xyz = tmp_path / "slope.xyz"
    np.savetxt(xyz, np.column_stack([xx.ravel(), yy.ravel(), -heights.ravel()]), fmt="%.3f")
    from_tif, _ = grid_terrain(
        *_terrain_params(_as_grid_config(cfg, tif)), np.random.default_rng(0)
    )
    points = _as_grid_config(cfg, str(xyz), grid_cell_m=0.5, grid_crs=CRS, grid_z_positive="down")
    from_xyz, source = grid_terrain(*_terrain_params(points), np.random.default_rng(0))
    assert source.origin["crs"] == CRS
    assert source.origin["easting"] == pytest.approx(E0) and source.origin[
        "northing"
    ] == pytest.approx(N0)
    np.testing.assert_allclose(from_xyz.heights, from_tif.heights, atol=1e-3)
    with pytest.raises(ValueError, match="cell_size"):
        grid_terrain(*_terrain_params(_as_grid_config(cfg, str(xyz))), np.random.default_rng(0))


def _terrain_params(cfg: dict):
    config = SyntheticSurveyConfig.from_mapping(cfg)
    return config.terrain, config.materials


def test_real_figure_draws_hillshade_and_waterfall(tmp_path):
    from studies.real_figure import main, render_real_survey

    path, _ = _holes_and_spikes_grid(tmp_path)
    cfg = _as_grid_config(_tiny(), path)
    cfg["plan"] = {**cfg["plan"], "heading_deg": 0.0, "margin_m": 1.0}
    survey, _ = generate_survey(SyntheticSurveyConfig.from_mapping(cfg))
    out = render_real_survey(survey, tmp_path / "fig" / "real.png")
    assert out.is_file() and out.stat().st_size > 10_000
    with pytest.raises(ValueError, match="line: expected one of"):
        render_real_survey(survey, tmp_path / "bad.png", "line_999")
    assert main([str(tmp_path / "no_survey")]) == 2
