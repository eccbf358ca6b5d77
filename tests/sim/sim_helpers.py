"""Shared helpers for the simulator tests: preset configs and analytic scenes."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
from omegaconf import OmegaConf

from sss2bathy.geometry import attitude_to_rotation
from sss2bathy.sim.config import SonarParams
from sss2bathy.sim.sonar import MaterialResponse, RayCaster
from sss2bathy.survey import BathyGrid
from sss2bathy.utils.config import survey_preset

CONF = Path(__file__).resolve().parents[2] / "conf"


def preset(survey: str, scale: str, **overrides) -> dict:
    """Plain ``data.survey`` dict of a preset at a scale (as Hydra composes it)."""
    root = OmegaConf.create({"data": {"survey": survey_preset(survey, scale, CONF)}})
    for dotted, value in overrides.items():
        OmegaConf.update(root.data.survey, dotted.replace("__", "."), value, force_add=True)
    return OmegaConf.to_container(root.data.survey, resolve=True)


def grid_mesh(heights_fn, half: float = 45.0, cell: float = 1.0) -> trimesh.Trimesh:
    """Mesh of ``z = heights_fn(x, y)`` on ``[-half, half]^2``."""
    x = np.arange(-half, half + cell / 2, cell)
    X, Y = np.meshgrid(x, x)
    return BathyGrid(heights_fn(X, Y), float(x[0]), float(x[0]), cell).to_mesh()


class MeshSurface:
    """A mesh of one material without texture; normals are the faces' normals."""

    def __init__(self, caster: RayCaster, material: int = 0) -> None:
        self.caster, self.material = caster, int(material)

    def normals(self, points: np.ndarray, tri: np.ndarray) -> np.ndarray:
        return self.caster.face_normals(tri)

    def materials(self, points: np.ndarray) -> np.ndarray:
        return np.full(len(points), self.material, dtype=np.int64)

    def texture(self, points: np.ndarray) -> np.ndarray:
        return np.ones(len(points))


def scene(mesh: trimesh.Trimesh) -> tuple[RayCaster, MeshSurface]:
    caster = RayCaster(mesh)
    return caster, MeshSurface(caster)


def north_pings(n: int = 24, z: float = 0.0, spacing: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """``n`` level pings heading North through the origin at height ``z``."""
    y = (np.arange(n) - (n - 1) / 2) * spacing
    pos = np.stack([np.zeros(n), y, np.full(n, z)], axis=1)
    R = attitude_to_rotation(np.zeros(n), np.zeros(n), np.zeros(n))
    return pos, R


@pytest.fixture
def sonar() -> SonarParams:
    """30 m range, 0.25 m bins, beam 0-60 deg, seawater-like absorption."""
    return SonarParams(
        tilt_rad=math.radians(30.0),
        beam_width_rad=math.radians(60.0),
        min_range_m=1.0,
        max_range_m=30.0,
        n_bins=116,
        oversampling=4,
        rays_per_raw_bin=2.0,
        speckle_looks=1.0,
        snr_db=20.0,
    )


@pytest.fixture
def response() -> MaterialResponse:
    return MaterialResponse.single(mu=1.0, exponent=1.8, specular=1.0)
