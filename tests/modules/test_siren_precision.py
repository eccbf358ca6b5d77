"""Training precision of the SIREN fit: a bf16 fit's map against the fp32 fit's, and the
geometry of a step under an enclosing autocast (Lightning's ``precision="bf16-mixed"``)."""

from __future__ import annotations

import math

import pytest
import torch

from sss2bathy.geometry import arc_point, attitude_to_rotation, head_plane_normal_from_gradient
from sss2bathy.losses.siren import height_loss
from sss2bathy.models.arc_fit import arc_geometry
from sss2bathy.models.intersection import find_intersections
from sss2bathy.models.normal_sensor import NormalSensorModel
from sss2bathy.models.siren import Siren

BEAM = (math.radians(5.0), math.radians(65.0))
BOUNDS = (0.0, -20.0, 100.0, 100.0)
N_PINGS, N_BINS = 20, 16
# the stated tolerance: a bf16 fit's map MAE within 5 % or 1 cm of the fp32 fit's
REL_TOL, ABS_TOL_M = 0.05, 0.01


class _Seabed:
    """A tilted plane with a 0.3 m swell: ``z = -20 + 0.08 (x - 50) + bump`` (m)."""

    def height(self, xy: torch.Tensor) -> torch.Tensor:
        x, y = xy[:, 0], xy[:, 1]
        bump = torch.sin(2 * math.pi * y / 50) * torch.cos(2 * math.pi * x / 70)
        return -20.0 + 0.08 * (x - 50) + 0.3 * bump

    def height_and_gradient(self, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.enable_grad():
            xy = xy.detach().requires_grad_(True)
            z = self.height(xy)
            (grad,) = torch.autograd.grad(z.sum(), xy)
        return z.detach(), grad


SEABED = _Seabed()


def _two_lines() -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Two north-bound lines 30 m apart, 8 m above the seabed; n_lat targets from the truth."""
    y = torch.linspace(0.0, 78.0, N_PINGS)
    xy = torch.cat([torch.stack([torch.full_like(y, x0), y], 1) for x0 in (35.0, 65.0)])
    position = torch.cat([xy, (SEABED.height(xy) + 8.0).unsqueeze(1)], 1)
    n = position.shape[0]
    zeros = torch.zeros(n, dtype=torch.float64)
    rotation = attitude_to_rotation(zeros, zeros, zeros).float()
    range_m = torch.linspace(9.0, 30.0, N_BINS)
    p, s, b = (
        i.reshape(-1)
        for i in torch.meshgrid(
            torch.arange(n), torch.arange(2), torch.arange(N_BINS), indexing="ij"
        )
    )
    theta, valid, _ = find_intersections(
        SEABED, position[p], rotation[p], range_m[b], s, BEAM, tol_m=1e-5
    )
    points = arc_point(position[p], rotation[p], range_m[b], torch.nan_to_num(theta), s)
    _, grad = SEABED.height_and_gradient(points[:, :2])
    n_lat, _ = head_plane_normal_from_gradient(grad[:, 0], grad[:, 1], rotation[p], s)
    batch = {
        "position": position,
        "rotation": rotation,
        "range_m": range_m,
        "n_lat": n_lat.reshape(n, 2, N_BINS).float(),
        "mask": (~valid).to(torch.uint8).reshape(n, 2, N_BINS),
        "line": (torch.arange(n) >= N_PINGS).long(),
        "index": torch.arange(n),
    }
    altimeter = torch.cat([xy, SEABED.height(xy).unsqueeze(1)], 1)
    return batch, altimeter


def _map_mae(precision: str, steps: int = 300, seed: int = 1) -> float:
    """Fit normals + altimeter heights; mean |error| (m) of the map over the swaths."""
    batch, alt = _two_lines()
    torch.manual_seed(seed)
    siren = Siren(32, 4, 3.0, BOUNDS, (-25.0, -15.0), precision=precision)
    opt = torch.optim.Adam(siren.parameters(), lr=3e-3)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, 0.99)
    sensor = NormalSensorModel()
    cache = torch.full((2 * N_PINGS, 2, N_BINS), torch.nan)
    for _ in range(steps):
        geo, stats = arc_geometry(siren, batch, sensor.bin_mask(batch), BEAM, {}, cache)
        target = batch["n_lat"][geo.ping, geo.side, geo.bin]
        loss = height_loss(siren.height(alt[:, :2]), alt[:, 2]) + sensor.loss(geo, target)[0]
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    assert stats["valid_fraction"] > 0.95
    xx, yy = torch.meshgrid(torch.linspace(15, 85, 36), torch.linspace(5, 73, 35), indexing="xy")
    grid = torch.stack([xx.ravel(), yy.ravel()], 1)
    with torch.no_grad():
        return float((siren.height(grid) - SEABED.height(grid)).abs().mean())


def test_bf16_fit_map_mae_matches_fp32_within_tolerance():
    mae32, mae16 = _map_mae("fp32"), _map_mae("bf16")
    assert mae32 < 0.10  # the fit works: 0.3 m swell and a 4 m tilt over the swaths
    assert abs(mae16 - mae32) <= max(REL_TOL * mae32, ABS_TOL_M), (mae32, mae16)


def test_step_geometry_stays_fp32_under_autocast():
    batch, _ = _two_lines()
    torch.manual_seed(0)
    siren = Siren(32, 4, 3.0, BOUNDS, (-25.0, -15.0))
    low = Siren(32, 4, 3.0, BOUNDS, (-25.0, -15.0), precision="bf16")
    low.load_state_dict(siren.state_dict())
    use = NormalSensorModel().bin_mask(batch)
    ref, _ = arc_geometry(siren, batch, use, BEAM, {})
    with torch.autocast("cpu", dtype=torch.bfloat16):
        auto, _ = arc_geometry(siren, batch, use, BEAM, {})
    bf16, _ = arc_geometry(low, batch, use, BEAM, {})
    # crossings (finder + arc geometry) exactly as in fp32; gradients as precision="bf16"
    assert torch.equal(auto.points, ref.points) and torch.equal(auto.theta, ref.theta)
    assert auto.points.dtype == torch.float32
    assert torch.equal(auto.grad, bf16.grad) and torch.equal(auto.n_lat, bf16.n_lat)
    assert not torch.equal(auto.grad, ref.grad)
    torch.testing.assert_close(auto.n_lat, ref.n_lat, rtol=0, atol=5e-3)


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_hydra_config_selects_the_precision(precision):
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from sss2bathy.config_validation import ConfigError, instantiate_group, validate_config

    conf = Path(__file__).resolve().parents[2] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose(
            "train.yaml",
            overrides=["experiment=siren_gt_n2d", f"model.siren.precision={precision}"],
        )
        bad = compose("train.yaml", overrides=["experiment=siren_gt_n2d", "model.siren.chunk=0"])
    validate_config(cfg)
    model = instantiate(cfg.model)
    assert model.siren.precision == precision and model.siren.chunk is None
    validate_config(bad)  # no table rule: the Siren constructor checks chunk at start-up
    with pytest.raises(ConfigError, match="model.siren.chunk"):
        instantiate_group(
            "model", lambda: instantiate(bad.model, _recursive_=True, _convert_="partial"), bad
        )
