"""RunHparams: runs that identify themselves in TensorBoard's HPARAMS, read back through
TensorBoard's own hparams plugin (the columns it would show) and EventAccumulator."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
from pytorch_lightning.loggers import TensorBoardLogger
from tensorboard import context as tb_context
from tensorboard.backend.event_processing import data_provider, plugin_event_multiplexer
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins import base_plugin
from tensorboard.plugins.hparams import backend_context
from tensorboard.plugins.hparams import metadata as hp_meta

from sss2bathy.callbacks import RunHparams

ROOT = Path(__file__).resolve().parents[2]


def hparams_experiment(logdir: Path):
    """What TensorBoard's HPARAMS tab shows for ``logdir``: ``(hparam names, metric tags)``."""
    mux = plugin_event_multiplexer.EventMultiplexer()
    mux.AddRunsFromDirectory(str(logdir))
    mux.Reload()
    provider = data_provider.MultiplexerDataProvider(mux, str(logdir))
    ctx = backend_context.Context(
        base_plugin.TBContext(logdir=str(logdir), multiplexer=mux, data_provider=provider)
    )
    request = tb_context.RequestContext()
    content = ctx.hparams_metadata(request, "")
    exp = ctx.experiment_from_metadata(
        request, "", True, content, ctx.hparams_from_data_provider(request, "", None)
    )
    return {h.name for h in exp.hparam_infos}, {m.name.tag for m in exp.metric_infos}


def session_hparams(run_dir: Path) -> dict:
    """The hparams session start info of one run (plain values)."""
    events = EventAccumulator(str(run_dir)).Reload()
    content = events.PluginTagToContent(hp_meta.PLUGIN_NAME)
    assert hp_meta.EXPERIMENT_TAG not in content, f"{run_dir}: per-run experiment summary"
    start = hp_meta.parse_session_start_info_plugin_data(content[hp_meta.SESSION_START_INFO_TAG])
    return {
        k: v.WhichOneof("kind") and getattr(v, v.WhichOneof("kind"))
        for k, v in start.hparams.items()
    }


class _Module(SimpleNamespace):
    pass


def _run(logdir: Path, name: str, module, step: int, scalars: dict) -> None:
    logger = TensorBoardLogger(str(logdir), name=name, version="", default_hp_metric=False)
    logger.log_metrics(scalars, step=step)
    trainer = SimpleNamespace(is_global_zero=True, loggers=[logger], global_step=step)
    record = RunHparams(run={"experiment": name, "seed": step, "normals": None}, overrides=[])
    record.teardown(trainer, module, "fit")
    record.teardown(trainer, module, "test")  # a test after the fit: one session only
    logger.finalize("success")


def test_two_kinds_of_run_in_one_log_dir_each_keep_their_columns(tmp_path):
    siren = _Module(
        hparams_for_log=lambda: {"w_height": 1.0, "sensor": "NormalSensorModel"},
        final_metrics={"final/mae": 0.3},
    )
    cnn = _Module(hparams={"loss": {"kind": "l1"}}, final_metrics={"test/d1/mae": 0.05})
    _run(tmp_path, "siren", siren, 1, {"val/map_mae_m": 0.4})
    _run(tmp_path, "cnn", cnn, 2, {"val/nlat_mae": 0.06})
    names, tags = hparams_experiment(tmp_path)
    assert {"run/experiment", "run/seed", "w_height", "loss/kind", "run/module"} <= names
    assert {"val/map_mae_m", "final/mae", "val/nlat_mae", "test/d1/mae"} <= tags
    siren_hp, cnn_hp = session_hparams(tmp_path / "siren"), session_hparams(tmp_path / "cnn")
    assert siren_hp["run/seed"] == 1 and cnn_hp["run/seed"] == 2
    assert siren_hp["run/normals"] == "none" and cnn_hp["loss/kind"] == "l1"
    assert EventAccumulator(str(tmp_path / "cnn")).Reload().Scalars("test/d1/mae")[-1].value == (
        pytest.approx(0.05)
    )
    with pytest.raises(ValueError, match="overrides: expected a list"):
        RunHparams(overrides="seed=1")


def _train(root: Path, args: list[str]) -> subprocess.CompletedProcess:
    env = dict(os.environ, SSS2BATHY_ROOT=str(root), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    env.pop("SSS2BATHY_RUN_DIR", None)
    cmd = [sys.executable, "-m", "sss2bathy.cli.train", *args, "scale=tiny", "torch_threads=1"]
    cmd += [f"paths.data_dir={root / 'data'}", "trainer.enable_progress_bar=false"]
    return subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_a_seed_sweep_and_a_cnn_run_tell_themselves_apart(tmp_path):
    """``seed=1,2`` SIREN sweep plus a CNN run in one outputs/ (~100 s on 2 shared cores)."""
    (tmp_path / "conf").symlink_to(ROOT / "conf")
    sweep = _train(tmp_path, ["-m", "experiment=siren_gt_n2d", "seed=1,2"])
    assert sweep.returncode == 0, sweep.stderr[-3000:]
    cnn = _train(tmp_path, ["experiment=cnn", "data.test_surveys=null"])
    assert cnn.returncode == 0, cnn.stderr[-3000:]
    outputs = tmp_path / "outputs"
    runs = sorted(p.parent for p in outputs.rglob("events.out.tfevents.*"))
    runs = sorted(set(runs))
    assert len(runs) == 3, runs
    hp = {run: session_hparams(run) for run in runs}
    siren = [h for h in hp.values() if h["run/experiment"] == "siren_gt_n2d"]
    (cnn_hp,) = [h for h in hp.values() if h["run/experiment"] == "cnn"]
    assert sorted(h["run/seed"] for h in siren) == [1, 2]
    swept = [o for h in siren for o in h["run/overrides"].split() if o.startswith("seed=")]
    assert sorted(swept) == ["seed=1", "seed=2"]  # what the sweep varies
    assert all(h["run/normals"] == "gt" and h["sensor"] == "NormalSensorModel" for h in siren)
    assert cnn_hp["run/module"] == "NormalCNNModule" and cnn_hp["run/scale"] == "tiny"
    assert all(h["run/survey"] == "synthetic_d1_tiny" for h in hp.values())
    _, tags = hparams_experiment(outputs)
    val = {}
    for run in runs:  # every run's own metrics are columns, with values in that run
        scalars = set(EventAccumulator(str(run)).Reload().Tags()["scalars"])
        final = {t for t in scalars if t.startswith(("final/", "test/"))}
        assert final and final <= tags, run
        val[hp[run]["run/experiment"]] = {t for t in scalars if t.startswith("val/")}
    # n_lat metrics and map metrics in metres never share a tag
    assert "val/nlat_mae" in val["cnn"] and "val/map_mae_m" in val["siren_gt_n2d"]
    assert val["cnn"] & val["siren_gt_n2d"] == set()
