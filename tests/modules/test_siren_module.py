"""SirenModule: normals + heights recover a slope; training steps through Hydra compose."""

from __future__ import annotations

import importlib.util
import json
import math
import os
from pathlib import Path

import hydra
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from sss2bathy.geometry import attitude_to_rotation, head_plane_normal_from_gradient
from sss2bathy.losses.siren import height_loss
from sss2bathy.models.arc_fit import arc_geometry
from sss2bathy.models.lambertian import LambertianSensorModel
from sss2bathy.models.normal_sensor import NormalSensorModel
from sss2bathy.models.siren import Siren, TwoScaleSiren
from sss2bathy.modules.schedules import WallClockExponentialLR
from sss2bathy.modules.siren import SirenModule

ROOT = Path(__file__).resolve().parents[2]
TWO_SCALE = "model.siren._target_=sss2bathy.models.siren.TwoScaleSiren"


def _load_tiny_survey_builder():
    spec = importlib.util.spec_from_file_location("_pings_tests", ROOT / "tests/data/test_pings.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.make_tiny_survey


# ------------------------------------------------------------------ pure tensors
SLOPE = (0.1, 0.0)  # dz/dx, dz/dy of the true plane


def _plane(xy: torch.Tensor) -> torch.Tensor:
    return -20.0 + SLOPE[0] * xy[:, 0] + SLOPE[1] * xy[:, 1]


def _one_line_batch(n_pings: int = 40, n_bins: int = 24) -> tuple[dict, torch.Tensor]:
    """One north-bound line at x = 50, 8 m above the plane; targets = the plane's n_lat."""
    y = torch.linspace(0.0, 78.0, n_pings)
    xy = torch.stack([torch.full((n_pings,), 50.0), y], 1)
    position = torch.cat([xy, (_plane(xy) + 8.0).unsqueeze(1)], 1)
    zeros = torch.zeros(n_pings, dtype=torch.float64)
    R = attitude_to_rotation(zeros, zeros, zeros).float()
    side = torch.tensor([0, 1]).expand(n_pings, 2)
    n_lat, _ = head_plane_normal_from_gradient(
        torch.full((n_pings, 2), SLOPE[0]),
        torch.full((n_pings, 2), SLOPE[1]),
        R.unsqueeze(1).expand(-1, 2, -1, -1),
        side,
    )
    batch = {
        "position": position,
        "rotation": R,
        "range_m": torch.linspace(9.0, 30.0, n_bins),
        "n_lat": n_lat.unsqueeze(-1).expand(n_pings, 2, n_bins).contiguous(),
        "mask": torch.zeros(n_pings, 2, n_bins, dtype=torch.uint8),
        "line": torch.zeros(n_pings, dtype=torch.long),
        "index": torch.arange(n_pings),
    }
    altimeter = torch.cat([xy, _plane(xy).unsqueeze(1)], 1)
    return batch, altimeter


def _fit(use_normals: bool, steps: int = 150) -> torch.Tensor:
    """Mean |dz/dx error| over the swath after fitting (heights only, or + normals)."""
    batch, alt = _one_line_batch()
    torch.manual_seed(1)
    siren = Siren(hidden=32, n_layers=3, omega0=3.0, bounds=(20, -30, 80, 108), z_range=(-20, -8))
    opt = torch.optim.Adam(siren.parameters(), lr=3e-3)
    sensor = NormalSensorModel()
    cache = torch.full((40, 2, 24), torch.nan)
    for _ in range(steps):
        loss = height_loss(siren.height(alt[:, :2]), alt[:, 2])
        if use_normals:
            geo, stats = arc_geometry(
                siren, batch, sensor.bin_mask(batch), (0.0, math.radians(60.0)), {}, cache
            )
            loss = loss + sensor.loss(geo, batch["n_lat"][geo.ping, geo.side, geo.bin])[0]
            assert stats["valid_fraction"] > 0.9
        opt.zero_grad()
        loss.backward()
        opt.step()
    if use_normals:
        assert torch.isfinite(cache).float().mean() > 0.9  # warm-start cache filled
    xx, yy = torch.meshgrid(torch.linspace(30, 70, 21), torch.linspace(5, 75, 21), indexing="xy")
    with torch.no_grad():
        _, grad = siren.height_and_gradient(torch.stack([xx.ravel(), yy.ravel()], 1))
    return (grad[:, 0] - SLOPE[0]).abs().mean()


def test_normals_recover_the_cross_track_slope_that_heights_cannot():
    err_heights = _fit(use_normals=False)
    err_normals = _fit(use_normals=True)
    # one line of altimeter points says nothing about the slope across the line
    assert err_heights > 0.05
    assert err_normals < 0.02 and err_normals < 0.25 * err_heights


def test_arc_geometry_normals_are_the_sirens_at_the_crossings():
    batch, _ = _one_line_batch(n_pings=4, n_bins=6)
    siren = Siren(hidden=16, n_layers=3, omega0=3.0, bounds=(20, -30, 80, 108), z_range=(-20, -8))
    use = NormalSensorModel().bin_mask(batch)
    geo, _ = arc_geometry(siren, batch, use, (0.0, math.radians(60.0)), {"tol_m": 1e-4})
    with torch.no_grad():
        z, grad = siren.height_and_gradient(geo.points[:, :2])
    assert torch.allclose(z, geo.points[:, 2], atol=2e-4)  # on the surface
    assert torch.allclose(grad, geo.grad.detach())
    assert geo.grad.requires_grad and geo.n_lat.requires_grad
    r = (geo.points - geo.sonar).norm(dim=-1)
    assert torch.allclose(r, geo.range_m, atol=1e-4)  # on the arc
    with pytest.raises(ValueError, match="finder"):
        arc_geometry(siren, batch, use, (0.0, 1.0), {"solver": "simplex"})


# ------------------------------------------------------------------ Hydra + Lightning
def _compose(tmp: Path, experiment: str, survey: Path, extra: list[str] = ()):
    overrides = [
        f"experiment={experiment}",
        "data/survey=xtf",
        "data.survey.kind=folder",
        f"+data.survey.path={survey}",
        f"paths.data_dir={tmp}",
        f"paths.output_dir={tmp / 'outputs'}",
        "debug=fast",
        "model.siren.hidden=16",
        "model.siren.n_layers=3",
        "data.batch_pings=16",
        "data.altimeter_points=100",
        "model.eval_cell_m=2.0",
        f"model.output_dir={tmp / 'run'}",
        *extra,
    ]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose("train.yaml", overrides=overrides)


@pytest.fixture(scope="module")
def tiny_survey(tmp_path_factory) -> Path:
    return _load_tiny_survey_builder()(tmp_path_factory.mktemp("siren") / "tiny_plane")


def _fit_from_config(cfg):
    dm = hydra.utils.instantiate(cfg.data, _recursive_=False)
    model = hydra.utils.instantiate(cfg.model)
    trainer = hydra.utils.instantiate(cfg.trainer, _convert_="partial")  # as sss2bathy-train
    trainer.fit(model, datamodule=dm)
    return trainer, model, dm


@pytest.mark.parametrize(
    "experiment, extra",
    [
        ("siren_gt_n2d", []),
        ("siren_direct_fit", []),
        ("siren_gt_n2d", ["model.sensor=null"]),
        ("siren_gt_n2d", ["model.line_offset=true"]),
        ("siren_gt_n2d", ["data.bin_fraction=0.25"]),
        ("siren_gt_n2d", ["model.w_shadow=100"]),
        (
            "siren_gt_n2d",
            [
                TWO_SCALE,
                "+model.siren.detail_omega0=40",
                "model.w_detail=1",
                "model.detail_nadir=true",
            ],
        ),
        (
            "siren_gt_n2d",
            [
                TWO_SCALE,
                "model.w_shadow=100",
                "model.shadow_on_detail=true",
                "model.heights_on_base=true",
            ],
        ),
        ("siren_gt_n2d", ["siren_schedule=budget", "scale.siren.budget_s=600"]),
    ],
)
def test_one_training_step_through_hydra(tmp_path, tiny_survey, experiment, extra):
    cfg = _compose(tmp_path, experiment, tiny_survey, extra)
    assert cfg.task_name == experiment
    assert cfg.trainer.max_epochs == cfg.scale.siren.max_epochs
    trainer, model, dm = _fit_from_config(cfg)
    metrics = trainer.callback_metrics
    sched = trainer.lr_scheduler_configs[0]
    if "siren_schedule=budget" in extra:  # the fast decay over 600 s of wall clock
        assert isinstance(sched.scheduler, WallClockExponentialLR) and sched.interval == "step"
        assert sched.scheduler.budget_s == 600.0 and sched.scheduler.decay_epochs == 10
        assert sched.scheduler.gamma == pytest.approx(0.7)
        assert OmegaConf.to_container(cfg.trainer.max_time, resolve=True) == {"seconds": 600}
    else:
        assert isinstance(sched.scheduler, torch.optim.lr_scheduler.ExponentialLR)
        assert sched.interval == "epoch"
    assert torch.isfinite(metrics["train/loss"])
    if TWO_SCALE in extra and "model.w_detail=1" in extra:  # the detail and its penalty
        assert isinstance(model.siren, TwoScaleSiren) and model.siren.detail.omega0 == 40.0
        assert torch.isfinite(metrics["train/loss_detail"])
    elif TWO_SCALE in extra:  # the occlusion term on the detail network alone
        assert isinstance(model.siren, TwoScaleSiren) and model.shadow_on_detail
        assert model.heights_on_base
        assert "train/loss_detail" not in metrics
    else:
        assert "train/loss_detail" not in metrics
    if "model.sensor=null" in extra:  # heights only: no sidescan term
        assert "train/loss_sensor" not in metrics
        assert metrics["train/loss"] == pytest.approx(float(metrics["train/loss_height"]))
    elif experiment == "siren_gt_n2d":
        assert metrics["train/valid_fraction"] > 0.5
        assert 0 < metrics["train/finder_iters"] <= 16
        assert torch.isfinite(model.theta_cache).sum() > 0
        if "model.w_shadow=100" in extra:  # the occlusion term beside the sensor's
            assert torch.isfinite(metrics["train/loss_shadow"])
            assert 0 <= float(metrics["train/shadow/lit_hidden"]) <= 1
        else:
            assert "train/loss_shadow" not in metrics
        if "data.bin_fraction=0.25" in extra:  # a step uses only the batch's drawn bins
            batch = next(iter(dm.train_dataloader()))
            with torch.no_grad():
                geo, _, _ = model.sidescan_geometry(batch)
                assert geo.ping.numel() > 0 and batch["keep"][geo.ping, geo.side, geo.bin].all()
                whole = {k: v for k, v in batch.items() if k != "keep"}
                n_whole = model.sidescan_geometry(whole)[0].ping.numel()
            assert geo.ping.numel() < 0.4 * n_whole
        offsets = model.sensor.offsets()
        if "model.line_offset=true" in extra:  # one learned offset per (line, side)
            assert offsets.shape == (len(dm.line_names), 2)
            assert torch.isfinite(offsets).all() and offsets.abs().sum() > 0
            assert "train/sensor/offset_rms" in metrics
            assert model.hparams_for_log()["sensor/line_offset_weight"] == 1.0
            rows = (tmp_path / "run" / "line_offsets.csv").read_text().splitlines()
            assert rows[0] == "line,side,offset" and len(rows) == 1 + 2 * len(dm.line_names)
            assert rows[1] == f"{dm.line_names[0]},port,{float(offsets[0, 0]):.6f}"
            final = json.loads((tmp_path / "run" / "metrics.json").read_text())
            assert final["final/line_offset_rms"] == pytest.approx(
                float(offsets.pow(2).mean().sqrt()), rel=1e-5
            )
        else:
            assert offsets.numel() == 0 and "train/sensor/offset_rms" not in metrics
            assert "sensor/line_offset_weight" not in model.hparams_for_log()
            assert not (tmp_path / "run" / "line_offsets.csv").exists()
    else:
        assert torch.isfinite(metrics["train/loss_direct"])
    # the SIREN's frame comes from the datamodule (tracks and altimeter), not the grid
    assert model.siren.bounds == pytest.approx(dm.bounds, abs=1e-3)
    assert model.siren.z_range == pytest.approx(dm.z_range, abs=1e-4)
    run = tmp_path / "run"
    final = json.loads((run / "metrics.json").read_text())
    assert final["final/n_cells"] > 100 and np.isfinite(final["final/mae"])
    for name in ("map.tif", "map.npz", "map.png", "gradient_hsv.png", "error.png"):
        assert (run / name).is_file()


def test_line_offsets_only_with_the_normal_sensor():
    lambert = LambertianSensorModel()
    with pytest.raises(ValueError, match="line_offset.*LambertianSensorModel"):
        SirenModule(Siren(hidden=8, n_layers=3), sensor=lambert, line_offset=True)
    with pytest.raises(ValueError, match="line_offset"):
        SirenModule(Siren(hidden=8, n_layers=3), sensor=None, line_offset=True)
    with pytest.raises(ValueError, match="offset_weight"):
        SirenModule(
            Siren(hidden=8, n_layers=3),
            sensor=NormalSensorModel(),
            line_offset=True,
            line_offset_weight=-1.0,
        )
    SirenModule(Siren(hidden=8, n_layers=3), sensor=lambert)  # off: any sensor


def test_the_detail_penalty_needs_a_two_scale_siren():
    with pytest.raises(ValueError, match="w_detail: expected 0 for a one-scale SIREN"):
        SirenModule(Siren(hidden=8, n_layers=3), sensor=None, w_detail=1.0)
    with pytest.raises(ValueError, match="w_detail: expected a weight >= 0"):
        SirenModule(TwoScaleSiren(hidden=8, n_layers=3), sensor=None, w_detail=-1.0)
    with pytest.raises(ValueError, match="shadow_on_detail: expected false for a one-scale"):
        SirenModule(Siren(hidden=8, n_layers=3), sensor=None, shadow_on_detail=True)
    with pytest.raises(ValueError, match="heights_on_base: expected false for a one-scale"):
        SirenModule(Siren(hidden=8, n_layers=3), sensor=None, heights_on_base=True)
    with pytest.raises(ValueError, match="detail_nadir: expected false for a one-scale"):
        SirenModule(Siren(hidden=8, n_layers=3), sensor=None, detail_nadir=True)


def test_heights_on_base_leaves_the_detail_to_the_sidescan():
    """The altimeter's loss reaches the base's parameters, never the detail's."""
    siren = TwoScaleSiren(hidden=16, n_layers=3, bounds=(0, 0, 10, 10), z_range=(-5, 0))
    with torch.no_grad():
        siren.detail.out_layer.weight.normal_()
    module = SirenModule(siren, sensor=None, heights_on_base=True)
    alt = torch.tensor([[2.0, 3.0, -1.0], [7.0, 4.0, -2.5], [5.0, 8.0, -4.0]])
    n = alt.shape[0]
    batch = {"altimeter": alt, "position": torch.zeros(n, 3)}
    module.model_step(batch)["loss"].backward()
    assert all(p.grad is None or not p.grad.any() for p in siren.detail.parameters())
    assert any(
        p.grad is not None and p.grad.abs().sum() > 0 for p in siren.sine_layers.parameters()
    )


def test_the_occlusion_term_needs_a_sidescan_sensor():
    with pytest.raises(ValueError, match="w_shadow: expected 0 without a sidescan sensor"):
        SirenModule(Siren(hidden=8, n_layers=3), sensor=None, w_shadow=1.0)
    with pytest.raises(ValueError, match="w_shadow: expected a weight >= 0"):
        SirenModule(Siren(hidden=8, n_layers=3), sensor=LambertianSensorModel(), w_shadow=-1)
    with pytest.raises(ValueError, match="shadow_min_m: expected a length >= 0"):
        SirenModule(Siren(hidden=8, n_layers=3), sensor=LambertianSensorModel(), shadow_min_m=-1)


def test_cnn_experiment_config(tmp_path, tiny_survey):
    cfg = _compose(tmp_path, "siren_cnn_n2d", tiny_survey)
    assert cfg.data.normals.source == "cnn" and cfg.data.normals.checkpoint == "latest"
    assert cfg.data.normals.runs_dir == os.path.join(str(tmp_path / "outputs"), "runs", "cnn")
    model = hydra.utils.instantiate(cfg.model)
    assert isinstance(model, SirenModule) and model.finder.solver == "secant"
    dm = hydra.utils.instantiate(cfg.data, _recursive_=False)
    with pytest.raises(ValueError, match="data.normals.checkpoint: expected a trained CNN"):
        dm.setup("fit")  # no CNN trained under this output dir


def test_encoding_parameters_get_their_own_learning_rate():
    from functools import partial

    from sss2bathy.models.encoding import FourierFeatures

    enc = FourierFeatures(n_freq=4, sigma=1.0, learnable=True)
    siren = Siren(hidden=8, n_layers=3, omega0=5.0, encoding=enc)
    module = SirenModule(
        siren, sensor=None, optimizer=partial(torch.optim.Adam, lr=1e-3), encoding_lr=1e-2
    )
    groups = module.configure_optimizers()["optimizer"].param_groups
    assert [g["lr"] for g in groups] == [1e-3, 1e-2]
    enc_ids = {id(p) for p in enc.parameters()}
    assert {id(p) for p in groups[1]["params"]} == enc_ids
    assert not enc_ids & {id(p) for p in groups[0]["params"]}
    n_all = sum(p.numel() for p in siren.parameters())
    assert sum(p.numel() for g in groups for p in g["params"]) == n_all
    with pytest.raises(ValueError, match="encoding_lr: expected a positive learning rate"):
        SirenModule(Siren(hidden=8, n_layers=3), sensor=None, encoding_lr=0.0)


def test_holdout_scores_are_logged_beside_the_mbes_ones(tmp_path, tiny_survey):
    """Held-out altimeter points: the map's and the interpolation's MAE at every evaluation
    and in metrics.json, with MBES metrics alongside when there is a grid."""
    cfg = _compose(
        tmp_path, "siren_gt_n2d", tiny_survey, ["model.sensor=null", "data.holdout.block_pings=10"]
    )
    trainer, model, dm = _fit_from_config(cfg)
    split = dm.holdout_split
    assert split is not None and split.n_held > 0
    # the fit never saw the held-out points
    assert dm.altimeter.shape[0] + split.n_held == dm.table.n_pings - 2  # 2 missing readings
    m = trainer.callback_metrics
    assert "val/map_mae_m" in m and np.isfinite(float(m["val/holdout_alt_mae_m"]))
    assert float(m["val/holdout_interp_mae_m"]) == pytest.approx(split.interp_mae, abs=1e-6)
    with torch.no_grad():
        z = model.siren.height(torch.from_numpy(split.held[:, :2].astype(np.float32)))
    expected = np.abs(z.numpy() - split.held[:, 2]).mean()
    assert float(m["val/holdout_alt_mae_m"]) == pytest.approx(expected, rel=1e-4, abs=1e-5)
    final = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert final["final/holdout_alt_mae"] == pytest.approx(expected, rel=1e-4, abs=1e-5)
    assert final["final/holdout_n"] == split.n_held
    assert model.final_metrics["final/holdout_interp_mae"] == pytest.approx(split.interp_mae)


def test_select_best_keeps_the_siren_of_the_lowest_holdout_score():
    """select_best=holdout_alt_mae: the final map is the evaluation with the lowest held-out
    altimeter MAE; a better final evaluation is kept as it is."""
    module = SirenModule(Siren(hidden=8, n_layers=3), sensor=None, select_best="holdout_alt_mae")
    first = {k: v.clone() for k, v in module.siren.state_dict().items()}
    best = module.best
    best.track(module.siren, {"holdout_alt_mae": 0.3}, 0)
    with torch.no_grad():
        for p in module.siren.parameters():
            p.add_(1.0)
    best.track(module.siren, {"holdout_alt_mae": 0.5}, 1)  # worse: not kept
    best.track(module.siren, {"holdout_alt_mae": float("nan")}, 2)  # ignored
    assert best.best["value"] == 0.3
    # the final evaluation is better than every earlier one: nothing is restored
    assert best.restore(module.siren, {"holdout_alt_mae": 0.2}) is None
    assert not torch.equal(module.siren.state_dict()["out_layer.weight"], first["out_layer.weight"])
    # the final evaluation is worse: the best one's SIREN comes back
    assert best.restore(module.siren, {"holdout_alt_mae": 0.4}) == 0
    for k, v in module.siren.state_dict().items():
        assert torch.equal(v, first[k]), k
    with pytest.raises(ValueError, match="select_best: expected one of"):
        SirenModule(Siren(hidden=8, n_layers=3), sensor=None, select_best="val/map_mae_m")


def test_select_best_through_hydra_writes_the_chosen_epoch(tmp_path, tiny_survey):
    cfg = _compose(
        tmp_path,
        "siren_gt_n2d",
        tiny_survey,
        [
            "data.holdout.block_pings=10",
            "model.select_best=holdout_alt_mae",
            "model.eval_every_n_epochs=1",
            "trainer.max_epochs=3",
        ],
    )
    trainer, model, dm = _fit_from_config(cfg)
    final = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert 0 <= final["final/map_epoch"] <= trainer.current_epoch
    assert model.best.best is not None
    # the written map's held-out score is the best one seen
    assert final["final/holdout_alt_mae"] <= model.best.best["value"] + 1e-6


def test_finder_block_of_the_siren_config_is_finder_settings_defaults():
    """conf/model/siren_normals.yaml lists the finder's keys (so they can be overridden on
    the command line) with FinderSettings' defaults, the one source of them."""
    import dataclasses

    from omegaconf import OmegaConf

    from sss2bathy.models.intersection import FinderSettings

    # resolved: a key may default through the scale (neighbour_start: oc.select, false)
    block = OmegaConf.to_container(
        OmegaConf.load(ROOT / "conf/model/siren_normals.yaml").finder, resolve=True
    )
    assert block == dataclasses.asdict(FinderSettings())
    module = SirenModule(Siren(hidden=8, n_layers=3), sensor=None, finder={"solver": "newton"})
    assert module.finder == FinderSettings(solver="newton")
    with pytest.raises(ValueError, match=r"finder\.n_scan: expected"):
        SirenModule(Siren(hidden=8, n_layers=3), sensor=None, finder={"n_scan": 1})


def test_direct_fit_sensor_checks_its_arguments_and_needs_mbes():
    from sss2bathy.models.direct_fit import MBESCellFit

    with pytest.raises(ValueError, match="n_points: expected a positive integer, found 0"):
        MBESCellFit(n_points=0)
    fit = MBESCellFit(n_points=5)
    with pytest.raises(ValueError, match="expected a survey with an MBES grid, found none"):
        fit.set_cells_from_grid(None, None, None, np.ones((2, 2), bool))
    heights = np.array([[-10.0, np.nan], [-11.0, -12.0]])
    fit.set_cells_from_grid(
        np.array([0.0, 1.0]), np.array([5.0, 6.0]), heights, np.ones((2, 2), bool)
    )
    assert fit.cells.tolist() == [[0.0, 5.0, -10.0], [0.0, 6.0, -11.0], [1.0, 6.0, -12.0]]
    siren = Siren(hidden=8, n_layers=3)
    loss, logs = fit.loss(siren)
    with torch.no_grad():
        z = siren.height(fit.cells[:, :2])
    assert float(loss) <= float((z - fit.cells[:, 2]).abs().max()) and "loss_direct" in logs
    with pytest.raises(ValueError, match="no finite cell"):
        fit.set_cells_from_grid(
            np.array([0.0]), np.array([0.0]), heights[:1, 1:], np.ones((1, 1), bool)
        )
