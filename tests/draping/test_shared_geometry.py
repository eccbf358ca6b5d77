"""The simulator, draping and the SIREN's intersection finder agree through geometry/.

All three take the side sign, the arc basis (eq. 10) and the head-plane normal (eq. 3)
from :mod:`sss2bathy.geometry`. On a tilted plane seen from a rolled, pitched sonar
every one of them must find the same crossings and the same ``n_lat`` as the closed form.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from sss2bathy.draping import drape_line
from sss2bathy.geometry import arc_point, head_plane_normal_from_gradient
from sss2bathy.models.intersection import find_intersections
from sss2bathy.sim.config import SonarParams
from sss2bathy.sim.sonar import MaterialResponse, RayCaster, range_bins, simulate_pings
from sss2bathy.survey import MASK_VALID

A, B, C = 0.08, -0.05, -20.0  # z = A x + B y + C


class _Plane:
    """The plane as the finder's height field."""

    def height(self, xy: torch.Tensor) -> torch.Tensor:
        return C + A * xy[:, 0] + B * xy[:, 1]

    def height_and_gradient(self, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        grad = torch.tensor([A, B], dtype=xy.dtype).expand(xy.shape[0], 2)
        return self.height(xy), grad


class _OneMaterial:
    """The plane as the simulator's surface: its face normals, one material, no texture."""

    def __init__(self, caster: RayCaster) -> None:
        self.caster = caster

    def normals(self, points: np.ndarray, tri: np.ndarray) -> np.ndarray:
        return self.caster.face_normals(tri)

    def materials(self, points: np.ndarray) -> np.ndarray:
        return np.zeros(len(points), np.int64)

    def texture(self, points: np.ndarray) -> np.ndarray:
        return np.ones(len(points))


def _line(straight_line):
    return straight_line(
        n_pings=6, n_bins=160, max_range=40.0, depth=-8.0, heading_deg=25.0,
        pitch_deg=3.0, roll_deg=5.0, start=(-5.0, 5.0), length=10.0,
    )  # fmt: skip


def _closed_form_n_lat(R: np.ndarray, side: np.ndarray) -> np.ndarray:
    g = np.full(len(side), A), np.full(len(side), B)
    return head_plane_normal_from_gradient(g[0], g[1], R, side)[0]


def test_draping_and_finder_agree_with_the_closed_form(make_plane, make_line):
    plane_grid, line = make_plane, _line(make_line)
    grid = plane_grid(A, B, C, x_range=(-60, 60), y_range=(-40, 70), cell=1.0)
    draped = drape_line(line, grid)
    p, s, b = np.nonzero(draped.mask == MASK_VALID)
    assert len(p) > 500
    R, sonar, r = line.rotation[p], line.position[p], line.range_m[b]
    # draping: hits on the plane, n_lat of eq. 3
    hits = draped.points[p, s, b].astype(np.float64)
    np.testing.assert_allclose(hits[:, 2], C + A * hits[:, 0] + B * hits[:, 1], atol=1e-4)
    np.testing.assert_allclose(draped.n_lat[p, s, b], _closed_form_n_lat(R, s), atol=1e-6)
    # the finder: the same crossings on the same arcs
    t = {k: torch.as_tensor(v) for k, v in dict(sonar=sonar, R=R, r=r, side=s).items()}
    theta, valid, _ = find_intersections(
        _Plane(), t["sonar"], t["R"], t["r"], t["side"], line.sensor.beam_limits_rad, tol_m=1e-6
    )
    assert bool(valid.all())
    found = arc_point(t["sonar"], t["R"], t["r"], theta, t["side"]).numpy()
    np.testing.assert_allclose(found, hits, atol=1e-3)  # float32 draped points


def test_simulator_agrees_with_the_closed_form(make_plane, make_line):
    plane_grid, line = make_plane, _line(make_line)
    mesh = plane_grid(A, B, C, x_range=(-60, 60), y_range=(-40, 70), cell=2.0).to_mesh()
    caster = RayCaster(mesh)
    sonar = SonarParams(
        tilt_rad=math.radians(30.0), beam_width_rad=math.radians(60.0), min_range_m=1.0,
        max_range_m=40.0, n_bins=100, oversampling=2, rays_per_raw_bin=1.0,
    )  # fmt: skip
    echoes = simulate_pings(
        caster, _OneMaterial(caster), line.position, line.rotation, sonar,
        MaterialResponse.single(), np.random.default_rng(0), absorption_db_m=0.1,
    )  # fmt: skip
    hit = np.isfinite(echoes.n_lat)
    p, s, b = np.nonzero(hit)
    assert len(p) > 300
    # one plane: every hit of a bin has the same normal, so the bin's n_lat is eq. 3's
    np.testing.assert_allclose(
        echoes.n_lat[hit], _closed_form_n_lat(line.rotation[p], s), atol=1e-6
    )
    # the energy-weighted hit points lie on the plane, at their bin's slant range, and the
    # in-beam ones on their own head's side of the track
    pts = echoes.points[hit].astype(np.float64)
    np.testing.assert_allclose(pts[:, 2], C + A * pts[:, 0] + B * pts[:, 1], atol=1e-3)
    r_bin, bin_width = range_bins(sonar)[0], (sonar.max_range_m - sonar.min_range_m) / 100
    dist = np.linalg.norm(pts - line.position[p], axis=1)
    assert np.abs(dist - r_bin[b]).max() < bin_width
    valid = echoes.mask[hit] == MASK_VALID
    assert valid.sum() > 300
    u = line.rotation[p][:, :, 1] * np.where(s == 0, 1.0, -1.0)[:, None]
    assert (np.einsum("ij,ij->i", pts - line.position[p], u)[valid] > 0).all()
