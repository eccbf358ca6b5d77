"""PingAltimeterDataModule on a tiny survey built here (a tilted plane, two crossing lines)."""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import pytest
import pytorch_lightning as pl
import torch

from sss2bathy.data.pings import PingAltimeterDataModule, build_ping_table
from sss2bathy.geometry import attitude_to_rotation, head_plane_normal_from_gradient
from sss2bathy.losses.normal import NormalLoss
from sss2bathy.models.normal_cnn import NormalResNet
from sss2bathy.modules.normal_cnn import NormalCNNModule
from sss2bathy.survey import (
    MASK_OUT_OF_BEAM,
    MASK_WATER_COLUMN,
    BathyGrid,
    SensorParams,
    SidescanLine,
    Survey,
)

PLANE = (-20.0, 0.05, 0.02)  # z = a + b x + c y
ALTITUDE = 8.0


def plane_z(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return PLANE[0] + PLANE[1] * x + PLANE[2] * y


def make_tiny_survey(folder: Path, n_pings: int = 40, n_bins: int = 32) -> Path:
    """A tilted-plane MBES grid and two lines (north-bound, east-bound) flown 8 m above it."""
    cell = 0.5
    xs = np.arange(0.0, 120.0 + cell, cell)
    xx, yy = np.meshgrid(xs, xs)
    grid = BathyGrid(plane_z(xx, yy), 0.0, 0.0, cell)
    sensor = SensorParams(math.radians(30.0), math.radians(60.0))
    rng = np.random.default_rng(0)
    lines = []
    for name, heading, start, step in (
        ("north", 0.0, (60.0, 40.0), (0.0, 1.0)),
        ("east", math.pi / 2, (40.0, 60.0), (1.0, 0.0)),
    ):
        k = np.arange(n_pings)
        x, y = start[0] + step[0] * k, start[1] + step[1] * k
        altitude = np.full(n_pings, ALTITUDE)
        altitude[3] = np.nan  # a missing altimeter reading
        position = np.stack([x, y, plane_z(x, y) + ALTITUDE], 1)
        rotation = attitude_to_rotation(
            np.full(n_pings, heading), np.zeros(n_pings), np.zeros(n_pings)
        )
        lines.append(
            SidescanLine(
                name=name,
                time_s=k.astype(float),
                position=position,
                rotation=rotation,
                altitude_m=altitude,
                intensity=rng.uniform(0.5, 2.0, (n_pings, 2, n_bins)),
                range_m=np.linspace(2.0, 30.0, n_bins),
                sensor=sensor,
            )
        )
    survey = Survey("tiny_plane", lines, grid, splits={"test": ["north", "east"], "train": []})
    return survey.save(folder)


@pytest.fixture(scope="module")
def tiny_survey(tmp_path_factory) -> Path:
    return make_tiny_survey(tmp_path_factory.mktemp("tiny") / "tiny_plane")


def _cnn(**kw) -> dict:
    """``data.normals`` of a CNN source (``latest`` under a runs folder unless given)."""
    return {"source": "cnn", "checkpoint": "latest", "runs_dir": "runs", **kw}


def _dm(folder: Path, **kw) -> PingAltimeterDataModule:
    cfg = {"kind": "folder", "path": str(folder)}
    kw.setdefault("batch_pings", 16)
    kw.setdefault("altimeter_points", 50)
    return PingAltimeterDataModule(cfg, str(folder.parent), **kw)


def test_batches_shapes_and_epoch_coverage(tiny_survey):
    dm = _dm(tiny_survey, normals="gt", need_intensity=True)
    dm.prepare_data()
    dm.setup("fit")
    loader = dm.train_dataloader()
    batches = list(loader)
    assert len(batches) == math.ceil(80 / 16)
    b = batches[0]
    assert b["position"].shape == (16, 3) and b["rotation"].shape == (16, 3, 3)
    assert b["range_m"].shape == (32,)
    for key in ("n_lat", "intensity", "mask"):
        assert b[key].shape == (16, 2, 32)
    assert b["mask"].dtype == torch.uint8
    assert b["altimeter"].shape == (50, 3)
    assert {"line", "ping", "index"} <= set(b)
    # an epoch visits every ping exactly once
    seen = torch.cat([bb["index"] for bb in batches]).sort().values
    assert torch.equal(seen, torch.arange(80))
    # the gathered rows are the table's rows
    i = b["index"]
    assert torch.equal(b["line"], dm.table.line[i]) and torch.equal(b["ping"], dm.table.ping[i])
    # altimeter points lie on the plane (sonar minus altitude)
    alt = b["altimeter"].double().numpy()
    assert np.allclose(alt[:, 2], plane_z(alt[:, 0], alt[:, 1]), atol=1e-4)


def test_gt_normals_match_the_plane_and_frame_ignores_the_grid(tiny_survey):
    dm = _dm(tiny_survey, normals="gt")
    dm.setup("fit")
    t = dm.table
    valid = t.mask == 0
    assert valid.float().mean() > 0.3
    assert torch.isnan(t.n_lat[~valid]).all() and torch.isfinite(t.n_lat[valid]).all()
    # analytic head-plane normal of the plane for every ping and side
    side = torch.tensor([0, 1]).view(1, 2).expand(t.n_pings, 2)
    n_lat, _ = head_plane_normal_from_gradient(
        torch.full((t.n_pings, 2), PLANE[1]),
        torch.full((t.n_pings, 2), PLANE[2]),
        t.rotation.unsqueeze(1).expand(-1, 2, -1, -1),
        side,
    )
    expected = n_lat.unsqueeze(-1).expand_as(t.n_lat)
    assert torch.allclose(t.n_lat[valid], expected[valid], atol=2e-3)
    # frame: bounds = tracks +- max range, z from altimeter points (not the grid's 241 x 241)
    assert dm.bounds == pytest.approx((10.0, 10.0, 109.0, 109.0), abs=1e-3)
    zmin, zmax = dm.z_range
    alt_z = plane_z(np.array([60.0, 60.0, 40.0, 79.0]), np.array([40.0, 79.0, 60.0, 60.0]))
    margin = max(0.25 * (alt_z.max() - alt_z.min()), 2.0)
    assert (zmin, zmax) == pytest.approx((alt_z.min() - margin, alt_z.max() + margin), abs=1e-3)
    assert dm.swath_half_width_m == pytest.approx(math.sqrt(30.0**2 - 8.0**2), rel=1e-6)


def test_sidescan_only_masks_without_normals(tiny_survey):
    dm = _dm(tiny_survey, normals="none")
    dm.setup("fit")
    t = dm.table
    assert torch.isnan(t.n_lat).all()
    water = t.range_m < ALTITUDE
    # beam 0..60 deg below horizontal: on the flat seabed 8 m down, bins nearer than
    # 8 / sin(60 deg) are out of beam
    out_of_beam = ~water & (t.range_m < ALTITUDE / math.sin(math.radians(60.0)))
    # every ping with an altitude: water column exactly where the slant range < altitude
    ping_ok = torch.ones(t.n_pings, dtype=torch.bool)
    ping_ok[[3, 43]] = False  # the pings without altimeter reading
    m = t.mask[ping_ok]
    assert ((m & MASK_WATER_COLUMN) > 0).equal(water.expand_as(m))
    assert ((m & MASK_OUT_OF_BEAM) > 0).equal(out_of_beam.expand_as(m))
    assert (m[:, :, ~water & ~out_of_beam] == 0).all()  # intensities 0.5..2: no shadow
    assert (t.mask[~ping_ok] != 0).all()
    # the mask parameters come from data.sonar_mask
    wide = _dm(tiny_survey, normals="none", sonar_mask={"beam_limits": False})
    wide.setup("fit")
    assert not (wide.table.mask & MASK_OUT_OF_BEAM).any()
    with pytest.raises(ValueError, match="sonar_mask.shadow_threshold"):
        _dm(tiny_survey, normals="none", sonar_mask={"shadow_threshold": -1})


def test_steps_per_epoch_and_validation(tiny_survey):
    with pytest.raises(ValueError, match="data.normals.source: expected one of"):
        _dm(tiny_survey, normals="mbes")
    with pytest.raises(ValueError, match="data.normals.checkpoint: expected a checkpoint path"):
        _dm(tiny_survey, normals="cnn")
    with pytest.raises(ValueError, match="data.normals.precision: expected no CNN setting"):
        _dm(tiny_survey, normals={"source": "gt", "precision": "bf16"})
    with pytest.raises(ValueError, match="data.normals.chekpoint: expected one of"):
        _dm(tiny_survey, normals={"source": "cnn", "chekpoint": "x.ckpt"})
    dm = _dm(tiny_survey, normals="none", steps_per_epoch=7, batch_pings=32)
    dm.setup("fit")
    batches = list(dm.train_dataloader())
    assert len(batches) == 7 and all(b["index"].numel() == 32 for b in batches)
    assert len(list(dm.val_dataloader())) == 1


def test_bin_fraction_draws_reproducible_bins_per_batch(tiny_survey):
    whole = _dm(tiny_survey, normals="gt", steps_per_epoch=4, batch_pings=32)
    whole.setup("fit")
    assert all("keep" not in b for b in whole.train_dataloader())
    dm = _dm(tiny_survey, normals="gt", steps_per_epoch=4, batch_pings=32, bin_fraction=0.25)
    dm.setup("fit")
    first = list(dm.train_dataloader())
    kept = torch.stack([b["keep"] for b in first])
    assert kept.dtype == torch.bool and kept.shape == (4, 32, 2, 32)
    assert 0.2 < kept.float().mean() < 0.3  # 8192 draws at p = 0.25
    assert not kept[0].equal(kept[1])  # a new draw every batch
    # the same keys give the same bins (a resumed run sees what the uninterrupted one saw)
    again = _dm(tiny_survey, normals="gt", steps_per_epoch=4, batch_pings=32, bin_fraction=0.25)
    again.setup("fit")
    for a, b in zip(first, again.train_dataloader(), strict=True):
        assert a["keep"].equal(b["keep"]) and a["index"].equal(b["index"])


@pytest.mark.parametrize(
    "kw, message",
    [
        ({"bin_fraction": 0.0}, "bin_fraction: expected a fraction in (0, 1], found 0.0"),
        ({"bin_fraction": 1.5}, "bin_fraction: expected a fraction in (0, 1], found 1.5"),
        ({"batch_pings": 0}, "batch_pings: expected a positive integer, found 0"),
        ({"altimeter_points": 2.5}, "altimeter_points: expected a positive integer, found 2.5"),
        ({"need_intensity": 3}, "need_intensity: expected true or false, found 3"),
        ({"z_margin": -0.5}, "z_margin: expected a fraction >= 0, found -0.5"),
        ({"z_margin_m": "x"}, "z_margin_m: expected a number >= 0 (m), found 'x'"),
        (
            {"normals": _cnn(window={"window_pings": 0})},
            "data.normals.window.window_pings: expected a positive integer",
        ),
        (
            {"normals": _cnn(window={"window_bins": -8})},
            "data.normals.window.window_bins: expected a positive integer",
        ),
        (
            {"normals": _cnn(window={"overlap": 1.0})},
            "data.normals.window.overlap: expected a fraction in [0, 1), found 1.0",
        ),
        (
            {"normals": _cnn(precision="fp16")},
            "data.normals.precision: expected one of ['fp32', 'bf16'], found 'fp16'",
        ),
        (
            {"normals": _cnn(overlap=1.0)},
            "data.normals.overlap: expected null (the training overlap) or a fraction",
        ),
    ],
)
def test_constructor_names_the_bad_argument(tiny_survey, kw, message):
    # "<argument>: expected ..., found ...": start-up turns it into the key data.<argument>
    with pytest.raises(ValueError) as err:
        _dm(tiny_survey, **kw)
    assert str(err.value).startswith(message)
    dm = _dm(tiny_survey, normals=_cnn(window={"window_pings": 8, "overlap": 0.5}))
    assert dm.normals.window == {"window_pings": 8, "overlap": 0.5}


def test_build_ping_table_rejects_mixed_ranges(tiny_survey):
    survey = Survey.load(tiny_survey)
    survey.lines[1].range_m = survey.lines[1].range_m * 1.1
    with pytest.raises(ValueError, match="slant ranges"):
        build_ping_table(survey, tiny_survey, ["north", "east"], normals="none")


def _tiny_checkpoint(folder: Path, channels: tuple[str, ...] = ("intensity",)) -> Path:
    torch.manual_seed(0)
    module = NormalCNNModule(
        net=functools.partial(NormalResNet, base_width=2, n_blocks=1),
        loss=NormalLoss(),
        optimizer=functools.partial(torch.optim.Adam, lr=1e-3),
        image_every_n_epochs=0,
        input_channels=list(channels),
    )
    trainer = pl.Trainer(accelerator="cpu", logger=False, enable_checkpointing=False, max_epochs=0)
    trainer.strategy.connect(module)
    ckpt = folder / "runs" / "cnn" / "2024-01-01_10-00-00" / "checkpoints" / "last.ckpt"
    ckpt.parent.mkdir(parents=True)
    trainer.save_checkpoint(ckpt)
    return ckpt


WINDOW = {"window_pings": 16, "window_bins": None, "overlap": 0.5}


def test_cnn_normals_from_the_latest_checkpoint(tiny_survey, tmp_path):
    """normals=cnn: predictions of a (tiny, untrained) CNN on the sonar-only valid bins,
    masked exactly like normals=none (the Lambertian fit)."""
    _tiny_checkpoint(tmp_path)
    dm = _dm(
        tiny_survey,
        normals=_cnn(runs_dir=str(tmp_path / "runs" / "cnn"), window=WINDOW),
    )
    dm.setup("fit")
    lambert = _dm(tiny_survey, normals="none", need_intensity=True)
    lambert.setup("fit")
    gt = _dm(tiny_survey, normals="gt")
    gt.setup("fit")
    t = dm.table
    assert torch.equal(t.mask, lambert.table.mask)  # one sonar-only mask for both variants
    assert not torch.equal(t.mask, gt.table.mask)  # not the draped (MBES) mask
    valid = t.mask == 0
    assert torch.isfinite(t.n_lat[valid]).all() and torch.isnan(t.n_lat[~valid]).all()
    assert t.n_lat[valid].abs().max() <= 1.0


@pytest.mark.parametrize(
    "channels",
    [
        ("intensity",),
        ("intensity", "grazing", "range"),
        ("relative", "grazing"),
        ("intensity", "opposite"),
    ],
)
def test_removing_the_grid_changes_no_cnn_input(tiny_survey, tmp_path, channels):
    """SIREN-CNN-N2d's inputs (n_lat, mask, intensity) are the same with and without MBES."""
    ckpt = _tiny_checkpoint(tmp_path, channels)
    with_grid = Survey.load(tiny_survey)
    assert with_grid.grid is not None
    bare = Survey.load(tiny_survey)
    bare.grid = None
    names = ["north", "east"]
    kw = {"normals": _cnn(checkpoint=str(ckpt), window=WINDOW), "need_intensity": True}
    a = build_ping_table(with_grid, tmp_path / "with_grid", names, **kw)
    b = build_ping_table(bare, tmp_path / "bare", names, **kw)
    assert torch.equal(a.mask, b.mask)
    assert torch.equal(a.intensity, b.intensity)
    torch.testing.assert_close(a.n_lat, b.n_lat, rtol=0, atol=0, equal_nan=True)
    assert (a.mask == 0).float().mean() > 0.3 and torch.isfinite(a.n_lat[a.mask == 0]).all()
    # and no draping happened for either (no MBES touched)
    assert not list((tmp_path / "with_grid").glob("draped/*"))


def test_cnn_probe_scores_the_prediction_siren_cnn_n2d_uses(tiny_survey, tmp_path, capsys):
    """``studies.cnn_probe``: the MAE and bias of the very prediction SIREN-CNN-N2d gets, against
    the draped truth, beside the constant; one line for a folder that is not a survey."""
    from sss2bathy.data.cnn_normals import predict_normals
    from sss2bathy.draping import DrapeConfig, drape_survey
    from studies.cnn_probe import main, probe_survey

    ckpt = _tiny_checkpoint(tmp_path)
    rows = probe_survey(ckpt, tiny_survey, None, constant=0.05, window_cfg=WINDOW)
    row = rows["all"]
    survey = Survey.load(tiny_survey)
    names = [ln.name for ln in survey.lines]
    draped = drape_survey(survey, tiny_survey, DrapeConfig(), lines=names)
    assert row["n"] > 100 and abs(row["bias"]) <= row["mae"]
    truth = np.concatenate([draped[n].n_lat[draped[n].valid] for n in names])
    assert row["constant_mae"] == pytest.approx(np.abs(0.05 - truth).mean(), rel=0.1)
    # the same numbers from the prediction and the truth directly, bin for bin
    pred = predict_normals(ckpt, survey, tiny_survey, names, window_cfg=WINDOW)
    err = np.concatenate(
        [
            (pred[n][0] - draped[n].n_lat)[
                draped[n].valid & np.isfinite(draped[n].n_lat) & np.isfinite(pred[n][0])
            ]
            for n in names
        ]
    )
    assert row["n"] == err.size
    assert row["mae"] == pytest.approx(np.abs(err).mean(), rel=1e-6)
    assert row["bias"] == pytest.approx(err.mean(), rel=1e-6, abs=1e-9)
    assert row["skill"] == pytest.approx(row["mae"] / row["constant_mae"])
    with pytest.raises(ValueError, match="expected a split of"):
        probe_survey(ckpt, tiny_survey, "nope", constant=0.0, window_cfg=WINDOW)
    assert main([str(ckpt), str(tmp_path / "nowhere")]) == 2
    assert "expected a survey folder" in capsys.readouterr().err
