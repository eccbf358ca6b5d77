"""sss2bathy-eval and sss2bathy-predict on tiny runs: the CLIs reproduce what the stages wrote."""

import json
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from sss2bathy.cli.evaluate import evaluate
from sss2bathy.cli.predict import predict
from sss2bathy.cli.train import train

CONF = Path(__file__).resolve().parents[2] / "conf"


def _cfg(config_name, tmp, overrides):
    common = [
        "scale=tiny",
        f"paths.data_dir={tmp / 'data'}",
        f"paths.output_dir={tmp / 'outputs'}",
    ]
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose(config_name, overrides=common + overrides)


@pytest.fixture(scope="module")
def tmp(tmp_path_factory):
    return tmp_path_factory.mktemp("cli")


def test_eval_reproduces_the_fit_metrics_from_checkpoint_and_map(tmp):
    run = tmp / "siren"
    cfg = _cfg(
        "train",
        tmp,
        [
            "experiment=siren_gt_n2d",
            "logger=none",
            "callbacks=none",
            "+callbacks.last._target_=pytorch_lightning.callbacks.ModelCheckpoint",
            f"+callbacks.last.dirpath={run / 'checkpoints'}",
            "+callbacks.last.save_last=true",
            "+callbacks.last.save_top_k=0",
            f"model.output_dir={run}",
            "trainer.enable_progress_bar=false",
        ],
    )
    train(cfg, run_dir=run)
    fitted = json.loads((run / "metrics.json").read_text())
    # the checkpoint's map is scored on the fit's own region and reproduces its metrics
    out = tmp / "eval_ckpt_path"
    metrics = evaluate(_cfg("eval", tmp, [f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}"]), out)
    assert metrics["mae"] == pytest.approx(fitted["val/map_mae_m"], rel=1e-4)
    assert metrics["grad_cs"] == pytest.approx(fitted["val/map_grad_cs"], rel=1e-4)
    assert metrics["n_cells"] == fitted["final/n_cells"]
    assert (out / "map.tif").is_file() and (out / "error.png").is_file()
    # the written map.tif holds data only where the sonar imaged or an altimeter point lies:
    # scored from it, the same heights on the cells it holds
    out_map = tmp / "eval_map_path"
    from_map = evaluate(_cfg("eval", tmp, [f"map_path={run / 'map.tif'}"]), out_map)
    assert 0 < from_map["n_cells"] < metrics["n_cells"]
    import rasterio

    with rasterio.open(out / "map.tif") as a, rasterio.open(out_map / "map.tif") as b:
        za, zb = a.read(1, masked=True), b.read(1, masked=True)
    both = ~np.ma.getmaskarray(za) & ~np.ma.getmaskarray(zb)
    assert both.sum() >= from_map["n_cells"]
    np.testing.assert_allclose(zb.data[both], za.data[both], atol=1e-4)
    assert (out_map / "error.png").is_file()
    with pytest.raises(ValueError, match="exactly one"):
        evaluate(_cfg("eval", tmp, []), tmp / "eval_none")


def test_predict_writes_masked_normals_for_a_split(tmp):
    cnn = _cfg(
        "train",
        tmp,
        [
            "experiment=cnn",
            "logger=none",
            "~callbacks.lr_monitor",
            "trainer.enable_progress_bar=false",
            "test=false",
        ],
    )
    run = tmp / "outputs" / "runs" / "cnn" / "r0"
    cnn.callbacks.epoch_checkpoint.dirpath = str(run / "checkpoints")
    cnn.callbacks.model_checkpoint.dirpath = str(run / "checkpoints")
    cnn.callbacks.step_checkpoint.dirpath = str(run / "checkpoints")
    cnn.callbacks.cnn_table.out_dir = str(run)
    train(cnn, run_dir=run)
    preds = predict(_cfg("predict", tmp, ["ckpt_path=latest", "split=test", "render=false"]))
    assert len(preds) == 2  # the tiny survey's two test lines
    for n_lat, mask in preds.values():
        valid = mask == 0
        assert valid.any()
        assert np.isfinite(n_lat[valid]).all() and np.isnan(n_lat[~valid]).all()
        assert np.abs(n_lat[valid]).max() <= 1.0
