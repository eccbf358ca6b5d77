"""Run folders and loggers: every run writes into its own folder whatever the logger
(``paths.run_dir``), and each ``logger=`` option (TensorBoard, CSV, MLflow, W&B offline,
several at once) instantiates and writes there."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from sss2bathy.cli.instantiate import instantiate_loggers

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"
LOGGER_OPTIONS = sorted(p.stem for p in (CONF / "logger").glob("*.yaml"))


def _compose(overrides: list[str]):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("train", overrides=["experiment=siren_gt_n2d", *overrides])


def test_run_dir_is_the_hydra_jobs_folder(monkeypatch, tmp_path):
    cfg = _compose([f"paths.output_dir={tmp_path / 'outputs'}"])
    # outside a Hydra run (compose API) the outputs folder stands in ...
    monkeypatch.delenv("SSS2BATHY_RUN_DIR", raising=False)
    assert cfg.paths.run_dir == str(tmp_path / "outputs")
    # ... inside one, Hydra hands the job its folder (hydra.job.env_set)
    monkeypatch.setenv("SSS2BATHY_RUN_DIR", str(tmp_path / "run"))
    assert cfg.paths.run_dir == str(tmp_path / "run")
    env_set = OmegaConf.to_container(_compose_hydra().job.env_set, resolve=False)
    assert env_set["SSS2BATHY_RUN_DIR"] == "${hydra:runtime.output_dir}"


def _compose_hydra():
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=[], return_hydra_config=True)
    return cfg.hydra


def test_every_logger_option_is_tested():
    assert set(LOGGER_OPTIONS) == {"none", "tensorboard", "csv", "mlflow", "wandb", "many"}


def _log_and_close(loggers: list) -> None:
    for lg in loggers:
        lg.log_hyperparams({"w_height": 1.0, "seed": 42})
        lg.log_metrics({"val/mae_m": 0.5}, step=1)
        lg.finalize("success")


def _instantiate(choice: str, tmp_path: Path, monkeypatch) -> list:
    monkeypatch.setenv("SSS2BATHY_RUN_DIR", str(tmp_path / "run"))
    cfg = _compose([f"logger={choice}", f"paths.output_dir={tmp_path / 'outputs'}"])
    return instantiate_loggers(cfg.logger)


def test_logger_none_is_no_logger(tmp_path, monkeypatch):
    assert _instantiate("none", tmp_path, monkeypatch) == []


def test_tensorboard_and_csv_write_into_the_run_folder(tmp_path, monkeypatch):
    loggers = _instantiate("[tensorboard,csv]", tmp_path, monkeypatch)
    assert [type(lg).__name__ for lg in loggers] == ["TensorBoardLogger", "CSVLogger"]
    _log_and_close(loggers)
    run = tmp_path / "run"
    assert list((run / "tensorboard").glob("events.out.tfevents.*"))
    rows = (run / "csv" / "metrics.csv").read_text().splitlines()
    assert rows[0].split(",") == ["step", "val/mae_m"] and rows[1].split(",") == ["1", "0.5"]
    assert "w_height: 1.0" in (run / "csv" / "hparams.yaml").read_text()
    assert not (tmp_path / "outputs").exists()


def test_mlflow_logs_to_a_local_store_without_a_server(tmp_path, monkeypatch):
    pytest.importorskip("mlflow", reason="logger=mlflow needs mlflow-skinny ('.[tracking]')")
    loggers = _instantiate("mlflow", tmp_path, monkeypatch)
    assert [type(lg).__name__ for lg in loggers] == ["MLFlowLogger"]
    _log_and_close(loggers)
    store = tmp_path / "outputs" / "mlflow.db"
    assert store.is_file()
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=f"sqlite:///{store}")
    experiment = client.get_experiment_by_name("siren_gt_n2d")  # the task name
    (run,) = client.search_runs([experiment.experiment_id])
    assert run.data.metrics["val/mae_m"] == 0.5
    assert run.data.params["w_height"] == "1.0"
    assert run.data.tags["run_dir"] == str(tmp_path / "run")  # which run folder it is
    assert run.info.status == "FINISHED"


def test_wandb_logs_offline_into_the_run_folder(tmp_path, monkeypatch):
    pytest.importorskip("wandb", reason="logger=wandb needs the wandb package ('.[tracking]')")
    monkeypatch.setenv("WANDB_SILENT", "true")
    monkeypatch.setenv("WANDB_MODE", "offline")
    loggers = _instantiate("wandb", tmp_path, monkeypatch)
    assert [type(lg).__name__ for lg in loggers] == ["WandbLogger"]
    _log_and_close(loggers)
    import wandb

    wandb.finish()
    (offline,) = (tmp_path / "run" / "wandb").glob("offline-run-*")
    assert list(offline.glob("run-*.wandb"))


def test_many_composes_tensorboard_csv_and_mlflow(tmp_path, monkeypatch):
    pytest.importorskip("mlflow", reason="logger=many includes mlflow")
    loggers = _instantiate("many", tmp_path, monkeypatch)
    # TensorBoard first: the SIREN's map files follow the first logger's folder
    assert [type(lg).__name__ for lg in loggers] == [
        "TensorBoardLogger",
        "CSVLogger",
        "MLFlowLogger",
    ]
    _log_and_close(loggers)
    assert (tmp_path / "run" / "csv" / "metrics.csv").is_file()
    assert (tmp_path / "outputs" / "mlflow.db").is_file()


# ------------------------------------------------------------------ tiny runs, end to end
@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory) -> Path:
    """The tiny synthetic survey's folder, generated by the first run and shared."""
    return tmp_path_factory.mktemp("data")


@pytest.fixture
def tiny_root(tmp_path) -> Path:
    """A project root of its own (conf/ linked in): its outputs/ starts empty."""
    (tmp_path / "conf").symlink_to(CONF)
    return tmp_path


def _train(root: Path, data: Path, args: list[str]) -> subprocess.CompletedProcess:
    env = dict(os.environ, SSS2BATHY_ROOT=str(root), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    env.pop("SSS2BATHY_RUN_DIR", None)
    env["WANDB_SILENT"] = "true"
    if not any(a.startswith("experiment=") for a in args):
        args = ["experiment=siren_gt_n2d", *args]
    cmd = [sys.executable, "-m", "sss2bathy.cli.train", "scale=tiny"]
    cmd += [f"paths.data_dir={data}", "torch_threads=1", "trainer.enable_progress_bar=false"]
    cmd += ["callbacks=none", *args]
    return subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True, timeout=300)


def _only_run_folder(root: Path) -> Path:
    """The one run folder below outputs/runs/; outputs/ holds nothing else but stores."""
    outputs = root / "outputs"
    (run,) = (outputs / "runs" / "siren_gt_n2d").iterdir()
    strays = sorted(p.name for p in outputs.iterdir() if p.name not in ("runs", "mlflow.db"))
    assert strays == [], f"written into outputs/ itself: {strays}"
    return run


def test_a_run_without_logger_writes_into_its_own_run_folder(tiny_root, tiny_data):
    proc = _train(tiny_root, tiny_data, ["logger=none"])
    assert proc.returncode == 0, proc.stderr[-3000:]
    run = _only_run_folder(tiny_root)
    for name in ("map.tif", "map.npz", "map.png", "metrics.json", "run_info.json"):
        assert (run / name).is_file(), name
    assert "final/mae" in json.loads((run / "metrics.json").read_text())


@pytest.mark.slow
def test_a_run_with_many_loggers_writes_each_and_keeps_the_map_in_its_folder(tiny_root, tiny_data):
    pytest.importorskip("mlflow", reason="logger=many includes mlflow")
    proc = _train(tiny_root, tiny_data, ["logger=many"])
    assert proc.returncode == 0, proc.stderr[-3000:]
    run = _only_run_folder(tiny_root)
    assert (run / "map.tif").is_file() and (run / "metrics.json").is_file()
    assert "val/map_mae_m" in (run / "csv" / "metrics.csv").read_text().splitlines()[0]
    assert list((run / "tensorboard").glob("events.out.tfevents.*"))
    assert (tiny_root / "outputs" / "mlflow.db").is_file()


def test_a_run_that_fails_in_setup_leaves_no_empty_tensorboard_run(tiny_root, tiny_data):
    proc = _train(
        tiny_root,
        tiny_data,
        ["experiment=siren_cnn_n2d", "logger=tensorboard", "data.normals.checkpoint=/no/such.ckpt"],
    )
    assert proc.returncode != 0 and "/no/such.ckpt" in proc.stderr
    # a run that failed before writing anything leaves no run folder, so TensorBoard shows
    # no empty run
    runs = tiny_root / "outputs" / "runs" / "siren_cnn_n2d"
    assert not runs.exists()
