"""The callbacks package: map images logged once per evaluation, metric rows only for the
current epoch's evaluation, the map export folder; models/ knows neither Lightning nor
matplotlib."""

from __future__ import annotations

import ast
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from pytorch_lightning.loggers import TensorBoardLogger
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from sss2bathy.callbacks import MetricCurve, SirenMapExport, SirenMapImages
from sss2bathy.callbacks.curve import evaluation_metrics
from sss2bathy.modules.siren_parts import MapEvaluation
from sss2bathy.survey import BathyGrid

ROOT = Path(__file__).resolve().parents[2]


def _evaluation(epoch: int, with_truth: bool = True) -> MapEvaluation:
    yy, xx = np.mgrid[0:6, 0:8].astype(np.float32)
    pred = BathyGrid(heights=-10.0 + 0.1 * xx + 0.05 * yy, x0=0.0, y0=0.0, cell_size=1.0)
    truth = BathyGrid(heights=pred.heights + 0.2, x0=0.0, y0=0.0, cell_size=1.0)
    region = np.ones(pred.heights.shape, bool)
    return MapEvaluation(pred, {"mae": 0.2}, epoch, truth if with_truth else None, region)


def _trainer(loggers, epoch=0, step=3):
    return SimpleNamespace(
        loggers=loggers, sanity_checking=False, is_global_zero=True, current_epoch=epoch,
        global_step=step,
    )  # fmt: skip


def test_map_images_are_logged_once_per_evaluation(tmp_path):
    tb = TensorBoardLogger(str(tmp_path), name="tb", version="")
    module = SimpleNamespace(latest_evaluation=None)
    images = SirenMapImages()
    images.on_validation_epoch_end(_trainer([tb]), module)  # nothing evaluated yet
    module.latest_evaluation = _evaluation(0)
    images.on_validation_epoch_end(_trainer([tb], step=3), module)
    images.on_validation_epoch_end(_trainer([tb], step=4), module)  # the same evaluation
    module.latest_evaluation = _evaluation(1, with_truth=False)
    images.on_validation_epoch_end(_trainer([tb], step=5), module)
    tb.experiment.flush()
    events = EventAccumulator(str(tmp_path / "tb")).Reload()
    assert [e.step for e in events.Images("map/bathymetry")] == [3, 5]
    assert [e.step for e in events.Images("map/signed_error")] == [3]  # no truth at step 5
    images.on_validation_epoch_end(_trainer([]), module)  # no TensorBoard: nothing, no error


def test_metric_rows_come_from_the_current_epochs_evaluation_only():
    module = SimpleNamespace(latest_evaluation=None)
    assert evaluation_metrics(_trainer([], epoch=0), module) == {}
    module.latest_evaluation = _evaluation(2)
    assert evaluation_metrics(_trainer([], epoch=3), module) == {}
    assert evaluation_metrics(_trainer([], epoch=2), module) == {"val/map_mae_m": 0.2}
    # modules without map evaluations: the trainer's val/* metrics
    trainer = SimpleNamespace(callback_metrics={"val/err": 0.5, "train/loss": 1.0})
    assert evaluation_metrics(trainer, SimpleNamespace()) == {"val/err": 0.5}
    assert isinstance(MetricCurve(), MetricCurve)


def test_map_export_folder_order(tmp_path):
    with_logger = SimpleNamespace(logger=SimpleNamespace(save_dir=str(tmp_path / "log")))
    bare = SimpleNamespace(logger=None, default_root_dir=str(tmp_path / "root"))
    assert SirenMapExport(tmp_path / "given").folder(with_logger) == tmp_path / "given"
    assert SirenMapExport().folder(with_logger) == tmp_path / "log"
    assert SirenMapExport(None).folder(bare) == tmp_path / "root"


@pytest.mark.parametrize("banned", ["pytorch_lightning", "lightning", "matplotlib"])
def test_models_import_neither_lightning_nor_matplotlib(banned):
    """Every import in sss2bathy/models/ (inside functions too) stays clear of ``banned``."""
    found = []
    for path in sorted((ROOT / "sss2bathy" / "models").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            found += [f"{path.name}: {n}" for n in names if n.split(".")[0] == banned]
    assert found == []


def test_test_metrics_table_keeps_full_names():
    from sss2bathy.callbacks import metrics_table

    metrics = {
        "test/synthetic_d1_tiny:test/mae": 0.05,
        "test/synthetic_d1_tiny:test/constant/mae": 0.08,
        "test/synthetic_d2_tiny/mae": 0.07,
        "val/map_mae_m": 1.0,
    }
    lines = metrics_table(metrics).splitlines()
    assert lines[0].split() == ["test", "set", "mae"]
    rows = {line.split()[0]: line.split()[1:] for line in lines[1:]}
    assert rows == {
        "synthetic_d1_tiny:test": ["0.0500"],
        "synthetic_d1_tiny:test/constant": ["0.0800"],
        "synthetic_d2_tiny": ["0.0700"],
    }
    assert metrics_table({"val/map_mae_m": 1.0}) == ""


def test_siren_inputs_come_from_the_accessor_or_the_attributes():
    from sss2bathy.data.siren_inputs import SirenInputs

    with pytest.raises(ValueError, match="expected a set-up PingAltimeterDataModule.*found none"):
        SirenInputs.of(None)
    with pytest.raises(ValueError, match=r"one without \['bounds'"):
        SirenInputs.of(SimpleNamespace(bounds=None))
    inputs = SirenInputs(
        (0.0, 0.0, 1.0, 1.0), (-2.0, -1.0), None, np.zeros(3), 4, None, np.zeros((1, 2)), 5.0
    )
    assert SirenInputs.of(SimpleNamespace(siren_inputs=lambda: inputs)) is inputs
    with pytest.raises(ValueError, match="siren_inputs\\(\\): expected a SirenInputs"):
        SirenInputs.of(SimpleNamespace(siren_inputs=lambda: {}))
