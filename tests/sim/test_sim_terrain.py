"""Terrain generation: determinism, the long-tailed n_lat, coherent materials, texture."""

from __future__ import annotations

import numpy as np
import pytest
from sim_helpers import preset

from sss2bathy.sim.config import SyntheticSurveyConfig
from sss2bathy.sim.terrain import (
    TerrainSurface,
    bilinear,
    gaussian_field,
    generate_terrain,
    nlat_statistics,
    smooth_noise_1d,
)
from sss2bathy.survey import BathyGrid


@pytest.fixture(scope="module")
def d1_demo_terrain():
    cfg = SyntheticSurveyConfig.from_mapping(preset("synthetic_d1", "demo"))
    return cfg, generate_terrain(cfg.terrain, cfg.materials, np.random.default_rng([1, 0]))


def test_gaussian_field_has_unit_variance_at_every_scale():
    rng = np.random.default_rng(0)
    for sigma in (0.5, 2.0, 8.0):
        f = gaussian_field(rng, (400, 400), sigma)
        assert abs(f.std() - 1.0) < 0.15 and abs(f.mean()) < 0.2
    # large scales on a small domain keep their amplitude (normalised by the filter)
    stds = [gaussian_field(np.random.default_rng(s), (40, 40), 60.0).std() for s in range(20)]
    assert np.mean(stds) < 0.5
    with pytest.raises(ValueError, match="sigma_cells"):
        gaussian_field(rng, (10, 10), 0.0)
    n = smooth_noise_1d(rng, 20000, 10.0)
    assert abs(n.std() - 1.0) < 0.1 and abs(np.corrcoef(n[:-1], n[1:])[0, 1]) > 0.95


def test_terrain_is_deterministic():
    cfg = SyntheticSurveyConfig.from_mapping(preset("synthetic_d1", "tiny"))
    a = generate_terrain(cfg.terrain, cfg.materials, np.random.default_rng([1, 0]))
    b = generate_terrain(cfg.terrain, cfg.materials, np.random.default_rng([1, 0]))
    c = generate_terrain(cfg.terrain, cfg.materials, np.random.default_rng([2, 0]))
    np.testing.assert_array_equal(a.heights, b.heights)
    np.testing.assert_array_equal(a.materials, b.materials)
    np.testing.assert_array_equal(a.texture, b.texture)
    assert not np.array_equal(a.heights, c.heights)


def test_d1_n_lat_is_long_tailed(d1_demo_terrain):
    cfg, terrain = d1_demo_terrain
    stats = nlat_statistics(terrain.dzdx, terrain.dzdy)
    assert stats["frac_below_0.2"] > 0.85  # most of the seabed is gentle
    assert stats["frac_above_0.5"] > 1e-3  # boulder flanks and ridges: the tail
    assert stats["max"] > 0.65
    assert stats["q99.9"] > 2.5 * stats["q90"]
    ny, nx = terrain.heights.shape
    assert (nx - 1) * cfg.terrain.cell_m == pytest.approx(cfg.terrain.size_m[0])
    assert (ny - 1) * cfg.terrain.cell_m == pytest.approx(cfg.terrain.size_m[1])
    assert len(terrain.boulders) == round(180 * 1.2)
    d = terrain.boulders[:, 2]
    assert d.min() >= 0.3 and d.max() <= 3.0 and np.median(d) < 0.8  # power law


def test_d2_is_smoother_than_d1(d1_demo_terrain):
    _, d1 = d1_demo_terrain
    cfg = SyntheticSurveyConfig.from_mapping(preset("synthetic_d2", "demo"))
    d2 = generate_terrain(cfg.terrain, cfg.materials, np.random.default_rng([2, 0]))
    s1, s2 = (nlat_statistics(t.dzdx, t.dzdy) for t in (d1, d2))
    assert s2["q90"] < 0.5 * s1["q90"]
    assert s2["frac_above_0.5"] < s1["frac_above_0.5"]
    assert np.mean(d2.materials == 0) > np.mean(d1.materials == 0)  # more mud


def test_materials_are_coherent_and_rock_covers_boulders(d1_demo_terrain):
    cfg, terrain = d1_demo_terrain
    names = terrain.material_names
    assert names == ("mud", "sand", "gravel", "rock")
    fractions = np.bincount(terrain.materials.ravel(), minlength=4) / terrain.materials.size
    target = np.array([c.fraction for c in cfg.materials.classes])
    assert np.all(np.abs(fractions[:3] - target[:3]) < 0.06)
    # spatial coherence: neighbouring cells share their material almost always
    same = np.mean(terrain.materials[:, 1:] == terrain.materials[:, :-1])
    assert same > 0.95
    cell = terrain.cell_m
    centres = np.rint(terrain.boulders[:, :2] / cell).astype(int)
    big = terrain.boulders[:, 2] > 1.0
    on_rock = terrain.materials[centres[big, 1], centres[big, 0]] == names.index("rock")
    assert on_rock.mean() > 0.9
    # texture: mean ~1, per-material contrast (gravel rougher than mud)
    assert abs(float(terrain.texture.mean()) - 1.0) < 0.1
    surf = TerrainSurface(terrain)
    ys, xs = np.nonzero(terrain.materials == 0)
    pts_mud = np.stack([xs * cell, ys * cell, np.zeros(len(xs))], 1)
    ys, xs = np.nonzero(terrain.materials == 2)
    pts_gravel = np.stack([xs * cell, ys * cell, np.zeros(len(xs))], 1)
    assert surf.texture(pts_gravel).std() > 2 * surf.texture(pts_mud).std()
    assert np.all(surf.materials(pts_mud) == 0)


def test_surface_normals_use_the_grid_gradient(d1_demo_terrain):
    _, terrain = d1_demo_terrain
    rng = np.random.default_rng(0)
    x, y = rng.uniform(5, 100, 200), rng.uniform(5, 90, 200)
    n = TerrainSurface(terrain).normals(np.stack([x, y, np.zeros(200)], 1), None)
    gx, gy = terrain.grid().sample_gradient(x, y)
    np.testing.assert_allclose(n[:, 0], -gx, atol=1e-5)
    np.testing.assert_allclose(n[:, 1], -gy, atol=1e-5)
    np.testing.assert_allclose(n[:, 2], 1.0)
    grid = BathyGrid(terrain.heights, 0.0, 0.0, terrain.cell_m)
    np.testing.assert_allclose(bilinear(terrain.heights, terrain.cell_m, x, y), grid.sample(x, y))
