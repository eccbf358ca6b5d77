"""Every config composes, every experiment resolves, and validation names the bad key."""

import copy
import tempfile
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf, open_dict

from sss2bathy.cli.train import instantiate_run
from sss2bathy.config_validation import ConfigError, validate_config
from sss2bathy.eval.results import REPORT_TABLES, SIREN_TABLES
from sss2bathy.utils.experiments import pipeline_experiments
from tests.conftest import skip_unless_survey_files

CONF = Path(__file__).resolve().parents[2] / "conf"
EXPERIMENTS = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
SCALES = ("tiny", "demo", "paper")


def _compose(config_name="train", overrides=()):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose(config_name, overrides=list(overrides), return_hydra_config=False)


def _resolve(cfg):
    # hydra:runtime.* interpolations only exist inside a Hydra run
    c = OmegaConf.to_container(cfg, resolve=False)
    for group in ("logger", "callbacks"):
        c.pop(group, None)
    return OmegaConf.to_container(OmegaConf.create(c), resolve=True)


# one composed config per experiment; each case sets one bad value (yaml-parsed) on a copy
_COMPOSED: dict[tuple[str, ...], object] = {}
_RUN_DIR = tempfile.mkdtemp(prefix="sss2bathy_compose_")


def _composed(*overrides: str):
    if overrides not in _COMPOSED:
        with initialize_config_dir(str(CONF), version_base="1.3"):
            cfg = compose(
                "train",
                overrides=["scale=tiny", "logger=none", f"paths.output_dir={_RUN_DIR}", *overrides],
                return_hydra_config=True,
            )
        with open_dict(cfg):
            cfg.hydra.runtime.output_dir = _RUN_DIR
        _COMPOSED[overrides] = cfg
    return _COMPOSED[overrides]


def _startup(cfg) -> None:
    """What sss2bathy-train checks before any data is made: the cross-key table, then every
    constructor's own checks (datamodule, model, callbacks, loggers, trainer)."""
    validate_config(cfg)
    HydraConfig.instance().set_config(cfg)
    instantiate_run(cfg)


def test_paper_experiments_exist():
    """The one list of experiments (the pipeline stages, :mod:`sss2bathy.utils.experiments`)
    names experiment files composed below, gives every report table a stage and every row
    the paper reports (its Tables 3 and 4) an experiment with that table and label."""
    stages = pipeline_experiments(CONF)
    assert {e.name for e in stages} <= set(EXPERIMENTS)
    assert {e.table for e in stages} == set(REPORT_TABLES)
    rows = {(e.table, e.label) for e in stages}
    for table, (_title, paper, _zoom) in SIREN_TABLES.items():
        missing = sorted(set(paper) - {label for t, label in rows if t == table})
        assert not missing, f"table {table}: the paper's rows {missing} have no experiment"


@pytest.mark.parametrize("scale", SCALES)
@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_experiment_composes_and_validates(experiment, scale):
    cfg = _compose(overrides=[f"experiment={experiment}", f"scale={scale}"])
    resolved = _resolve(cfg)
    assert resolved["task_name"] == experiment
    assert "_target_" in resolved["data"] and "_target_" in resolved["model"]
    assert resolved["trainer"]["max_epochs"] >= 1
    skip_unless_survey_files(cfg)
    validate_config(cfg)


@pytest.mark.parametrize(
    ("experiment", "sensor"),
    [
        ("siren_gt_n2d", "gt_n2d"),
        ("siren_cnn_n2d", "cnn_n2d"),
        ("siren_cnn_n2d_pretrained", "cnn_n2d_pretrained"),
        ("d2_siren_cnn_n2d", "cnn_n2d"),
        ("d3_siren_cnn_n2d_pretrained", "cnn_n2d_pretrained"),
        ("siren_lambert", "lambert"),
        ("siren_lambert_all", "lambert"),
        ("siren_heights_only", None),
    ],
)
def test_each_sensor_takes_the_altimeter_weight_its_scale_chose(experiment, sensor):
    """The altimeter weight (w_H) is chosen per sensor on the validation site at demo scale
    (conf/scale/demo.yaml siren.w_height); the paper scale keeps model.w_height's 1, and
    heights-only (no sensor term) keeps 1 everywhere."""
    demo = _resolve(_compose(overrides=[f"experiment={experiment}", "scale=demo"]))
    chosen = demo["scale"]["siren"]["w_height"]
    assert set(chosen) == {"gt_n2d", "cnn_n2d", "cnn_n2d_pretrained", "lambert"}
    expected = 1.0 if sensor is None else chosen[sensor]
    assert demo["model"]["w_height"] == pytest.approx(expected)
    paper = _resolve(_compose(overrides=[f"experiment={experiment}", "scale=paper"]))
    assert paper["model"]["w_height"] == pytest.approx(1.0)


@pytest.mark.parametrize("scale", SCALES)
def test_cnn_experiment_instantiates_at_every_scale(scale):
    """The CNN's test surveys are interpolations to survey presets whose keys fall back to
    list literals at scale=paper; instantiating the run failed there until the data and
    callback nodes were resolved into plain containers first (sss2bathy/cli/train.py)."""
    cfg = copy.deepcopy(_composed("experiment=cnn", f"scale={scale}"))
    _startup(cfg)
    names = [s.name for s in cfg.data.test_surveys]
    assert names == [
        f"synthetic_d2_{scale}",
        f"synthetic_d3_{scale}",
        f"synthetic_d1_site2_{scale}",
    ]


@pytest.mark.parametrize("config_name", ["prepare", "eval", "predict"])
def test_other_entry_configs_compose(config_name):
    cfg = _compose(config_name, ["scale=tiny"])
    assert _resolve(cfg)["data"]["survey"]["kind"] == "synthetic"


@pytest.mark.parametrize(
    "override, key",
    [
        ("model.w_height=-1", "model.w_height"),
        ("data.survey.sonar.beam_width_deg=0", "data.survey.sonar.beam_width_deg"),
        ("data.survey.sonar.beam_width_deg=180", "data.survey.sonar.beam_width_deg"),
        ("data.survey.terrain.cell_m=0", "data.survey.terrain.cell_m"),
        ("data.batch_pings=0", "data.batch_pings"),
        ("trainer.max_epochs=0", "trainer.max_epochs"),
        ("seed=-3", "seed"),
    ],
)
def test_validation_names_key_and_value(override, key):
    cfg = copy.deepcopy(_composed("experiment=siren_gt_n2d"))
    OmegaConf.update(cfg, key, yaml.safe_load(override.split("=")[1]))
    with pytest.raises(ConfigError) as err:
        _startup(cfg)
    assert f"'{key}'" in str(err.value)
    assert override.split("=")[1] in str(err.value)


def test_window_larger_than_waterfall_rejected():
    cfg = _compose(overrides=["experiment=cnn", "scale=tiny", "data.window_bins=4096"])
    with pytest.raises(ConfigError, match="data.window_bins"):
        validate_config(cfg)


XTF = ("experiment=cnn", "data/survey=xtf", "data.survey.files=/none", "data.test_surveys=null")

BAD_VALUES = [
    # run control
    (("experiment=siren_gt_n2d",), "deterministic", "maybe"),
    (("experiment=siren_gt_n2d",), "guard.max_consecutive_nonfinite", "0"),
    (("experiment=siren_gt_n2d",), "callbacks.epoch_checkpoint.every_n_epochs", "-1"),
    (("experiment=siren_gt_n2d",), "callbacks.step_checkpoint.every_n_train_steps", "-5"),
    (("experiment=siren_gt_n2d",), "callbacks.nonfinite_guard.max_consecutive", "0"),
    (("experiment=siren_gt_n2d",), "trainer.min_epochs", "-1"),
    (("experiment=siren_gt_n2d",), "trainer.check_val_every_n_epoch", "0"),
    (("experiment=siren_gt_n2d",), "trainer.log_every_n_steps", "0"),
    (("experiment=siren_gt_n2d",), "trainer.accumulate_grad_batches", "0"),
    (("experiment=siren_gt_n2d",), "trainer.gradient_clip_val", "-1.5"),
    # data modules
    (("experiment=siren_gt_n2d",), "data.normals.source", "mbes"),
    (("experiment=siren_gt_n2d",), "data.need_intensity", "3"),
    (("experiment=siren_gt_n2d",), "data.steps_per_epoch", "0"),
    (("experiment=siren_gt_n2d",), "data.bin_fraction", "0"),
    (("experiment=siren_gt_n2d", "siren_schedule=budget"), "scale.siren.budget_s", "0"),
    (("experiment=siren_gt_n2d", "siren_schedule=budget"), "scale.siren.bin_fraction", "1.5"),
    (("experiment=siren_gt_n2d", "siren_schedule=budget"), "scale.siren.neighbour_start", "2"),
    (("experiment=siren_gt_n2d",), "data.z_margin", "-0.5"),
    (("experiment=siren_gt_n2d",), "data.z_margin_m", "-1.0"),
    (("experiment=siren_cnn_n2d",), "data.normals.window.window_pings", "0"),
    (("experiment=siren_cnn_n2d",), "data.normals.window.window_bins", "-8"),
    (("experiment=siren_cnn_n2d",), "data.normals.window.overlap", "1.5"),
    (("experiment=siren_cnn_n2d",), "data.normals.precision", "fp16"),
    (("experiment=siren_cnn_n2d",), "data.normals.overlap", "0.9x"),
    (("experiment=siren_gt_n2d",), "data.normals.checkpoint", "x.ckpt"),
    (("experiment=cnn",), "data.flip_augment", "1"),
    (("experiment=cnn",), "data.window_pings", "0"),
    (("experiment=cnn",), "data.overlap", "1.0"),
    (("experiment=cnn",), "data.min_valid_fraction", "1.5"),
    (("experiment=cnn",), "data.val_fraction", "0.0x"),
    (("experiment=cnn",), "data.num_workers", "-1"),
    (("experiment=cnn",), "data.batch_size", "0"),
    (("experiment=cnn",), "data.drape.rays_per_bin", "0"),
    (("experiment=cnn",), "data.drape.engine", "optix"),
    # the synthetic surveys (all keys: SyntheticSurveyConfig), test surveys included
    (("experiment=siren_gt_n2d",), "data.survey.terrain.mean_depth_m", "-3.0"),
    (("experiment=siren_gt_n2d",), "data.survey.plan.n_train", "-1"),
    (("experiment=siren_gt_n2d",), "data.survey.sonar.min_range_m", "-1.0"),
    (("experiment=siren_gt_n2d",), "data.survey.sonar.max_range_m", "0"),
    (("experiment=siren_gt_n2d",), "data.survey.sonar.frequency_khz", "-850.0"),
    (("experiment=siren_gt_n2d",), "data.survey.plan.speed_mps", "0"),
    (("experiment=siren_gt_n2d",), "data.survey.seed", "-2"),
    (("experiment=cnn",), "data.test_surveys[0].sonar.n_bins", "0"),
    # a real (xtf) survey
    (XTF, "data.survey.n_bins", "1"),
    (XTF, "data.survey.frequency_hz", "-400000.0"),
    (XTF, "data.survey.sound_speed_mps", "0"),
    (XTF, "data.survey.mbes_z_positive", "sideways"),
    (XTF, "data.survey.mbes_statistic", "mode"),
    (XTF, "data.survey.mbes_crs_mismatch", "ignore"),
    (XTF, "data.survey.missing_attitude", "zero"),
    (XTF, "data.survey.channel_pair", "-1"),
    (XTF, "data.survey.max_jump_m", "0"),
    (XTF, "data.survey.max_speed_mps", "0"),
    (XTF, "data.survey.max_nav_gap_s", "-1.0"),
    (XTF, "data.survey.min_first_return_m", "-0.5"),
    # the normal CNN and its loss
    (("experiment=cnn",), "model.net.in_channels", "0"),
    (("experiment=cnn",), "model.net.base_width", "0"),
    (("experiment=cnn",), "model.net.n_blocks", "-1"),
    (("experiment=cnn",), "model.net.outer_kernel", "4"),
    (("experiment=cnn",), "model.image_every_n_epochs", "-1"),
    (("experiment=cnn",), "model.n_images", "-2"),
    (("experiment=cnn",), "model.compile", "yes please"),
    (("experiment=cnn",), "model.loss.kind", "l3"),
    (("experiment=cnn",), "model.loss.base", "huber"),
    (("experiment=cnn",), "model.loss.beta", "0"),
    (("experiment=cnn",), "model.loss.tv_across_track", "-0.001"),
    (("experiment=cnn",), "model.loss.tv_along_track", "-0.001"),
    (("experiment=cnn",), "model.optimizer.lr", "0"),
    # the SIREN fits
    (("experiment=siren_gt_n2d",), "model.siren.hidden", "0"),
    (("experiment=siren_gt_n2d",), "model.siren.n_layers", "1"),
    (("experiment=siren_gt_n2d",), "model.siren.omega0", "0"),
    (("experiment=siren_gt_n2d",), "model.finder.solver", "brent"),
    (("experiment=siren_gt_n2d",), "model.finder.scan_max_slope", "-1"),
    (("experiment=siren_gt_n2d",), "model.finder.max_iter", "0"),
    (("experiment=siren_gt_n2d",), "model.finder.tol_m", "0"),
    (("experiment=siren_gt_n2d",), "model.finder.gd_step", "-0.01"),
    (("experiment=siren_gt_n2d",), "model.finder.n_scan", "0"),
    (("experiment=siren_gt_n2d",), "model.finder.warm_bracket_deg", "0"),
    (("experiment=siren_gt_n2d",), "model.finder.chunk", "0"),
    (("experiment=siren_gt_n2d",), "model.finder.warm_start", "2"),
    (("experiment=siren_gt_n2d",), "model.eval_cell_m", "0"),
    (("experiment=siren_gt_n2d",), "model.eval_every_n_epochs", "0"),
    (("experiment=siren_gt_n2d",), "model.region_radius_m", "-5.0"),
    (("experiment=siren_gt_n2d",), "model.sensor_lr", "0"),
    (("experiment=siren_gt_n2d",), "model.scheduler.gamma", "1.5"),
    (("experiment=siren_lambert",), "model.sensor.n_beam_knots", "1"),
    (("experiment=siren_lambert",), "model.sensor.n_gain_knots", "1"),
    (("experiment=siren_lambert",), "model.sensor.reflectivity", "map"),
    (("experiment=siren_lambert",), "model.sensor.tilt_deg", "95.0"),
    (("experiment=siren_lambert",), "model.sensor.beam_width_deg", "0"),
    (("experiment=siren_lambert",), "model.sensor.near_range_cut_m", "-1.0"),
    (("experiment=siren_lambert",), "model.sensor.init_scale", "0"),
    (("experiment=siren_lambert",), "model.sensor.q", "0.5"),
    (("experiment=siren_lambert",), "model.sensor.shadow_threshold", "-0.1"),
]


@pytest.mark.parametrize("base, key, bad", BAD_VALUES, ids=[f"{k}={v}" for _, k, v in BAD_VALUES])
def test_every_validated_key_rejects_a_bad_value(base, key, bad):
    cfg = copy.deepcopy(_composed(*base))
    _startup(cfg)  # the composed config itself is valid
    if key.startswith("data.test_surveys[0]."):
        OmegaConf.update(cfg.data.test_surveys[0], key.split("].", 1)[1], yaml.safe_load(bad))
    else:
        OmegaConf.update(cfg, key, yaml.safe_load(bad), force_add=True)
    with pytest.raises(ConfigError) as err:
        _startup(cfg)
    assert f"'{key}'" in str(err.value)
    assert bad in str(err.value)


@pytest.mark.parametrize(
    "base, overrides, key",
    [
        (XTF, {"data.window_bins": 64, "data.survey.n_bins": 32}, "data.window_bins"),
        (("experiment=siren_gt_n2d",), {"trainer.min_epochs": 99}, "trainer.min_epochs"),
    ],
)
def test_cross_key_limits(base, overrides, key):
    cfg = copy.deepcopy(_composed(*base))
    for k, v in overrides.items():
        OmegaConf.update(cfg, k, v)
    with pytest.raises(ConfigError, match=key):
        validate_config(cfg)


def test_optuna_search_targets_existing_keys():
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper")
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose(
            "train",
            overrides=["experiment=cnn", "hparams_search=cnn_optuna", "scale=tiny"],
            return_hydra_config=True,
        )
    sweeper = cfg.hydra.sweeper
    assert sweeper._target_.endswith("OptunaSweeper") and sweeper.direction == "minimize"
    assert cfg.optimized_metric == "val/nlat_mae"
    for key in sweeper.params:
        assert OmegaConf.select(cfg, key) is not None, f"searched key {key} is not in the config"


def test_constructor_errors_name_the_config_key():
    from sss2bathy.config_validation import constructor_error

    cfg = OmegaConf.create({"model": {"w_height": 1.0, "siren": {"hidden": 8}}, "data": {}})

    def named(node, message):
        return str(constructor_error(node, ValueError(message), cfg))

    assert named("model", "w_height: expected >= 0, found -1") == (
        "config key 'model.w_height': expected >= 0, found -1"
    )
    # built by the module from its model.siren factory
    assert named("model", "hidden: expected a positive width, found 0").startswith(
        "config key 'model.siren.hidden':"
    )
    assert named("data", "drape.engine: expected one of [...], found 'x'").startswith(
        "config key 'data.drape.engine':"
    )
    assert named("data", "data.survey.plan.n_test: expected >= 1, found 0").startswith(
        "config key 'data.survey.plan.n_test':"
    )
    assert named("model", "something else went wrong") == (
        "config node 'model': something else went wrong"
    )
