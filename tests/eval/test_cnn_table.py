"""CNN table with constant-prediction rows and skill; bias files; CNNTableWriter end to end
on a small in-memory datamodule (the constant comes from the training lines only)."""

import csv
import io
import math
from dataclasses import dataclass
from functools import partial

import numpy as np
import pytest
import pytorch_lightning as pl
import torch
from torch.utils.data import DataLoader, Dataset

from sss2bathy.callbacks import CNNTableWriter
from sss2bathy.eval.cnn_table import (
    cnn_table_csv,
    cnn_table_markdown,
    constant_metric_keys,
    constant_rows_from_metrics,
    table_rows_from_metrics,
    write_cnn_bias,
    write_cnn_table,
)
from sss2bathy.losses import NormalLoss
from sss2bathy.models.normal_cnn import NormalResNet
from sss2bathy.modules.normal_cnn import NormalCNNModule

ROW = {"mae": 0.05, "rel": 0.051, "rmse": 0.07, "delta1": 80.0, "delta2": 93.0, "delta3": 97.0}
CONST = {"mae": 0.08, "rel": 0.081, "rmse": 0.1, "delta1": 60.0, "delta2": 85.0, "delta3": 95.0}


def test_constant_rows_and_skill_in_markdown_and_csv(tmp_path):
    rows = {"d1:test": ROW, "d2:all": {**ROW, "mae": 0.1}}
    const = {"d1:test": {**CONST, "value": 0.0123}}
    md = cnn_table_markdown(rows, const)
    cnn_line = next(ln for ln in md.splitlines() if "| d1:test | CNN |" in ln)
    assert cnn_line.endswith("| 0.62 |")  # 0.05 / 0.08
    const_line = next(ln for ln in md.splitlines() if "constant +0.0123" in ln)
    assert "0.0800" in const_line and const_line.endswith("| 1.00 |")
    d2_line = next(ln for ln in md.splitlines() if "| d2:all | CNN |" in ln)
    assert d2_line.endswith("| n/a |")  # no constant row for d2
    table = list(csv.DictReader(io.StringIO(cnn_table_csv(rows, const))))
    assert [(r["dataset"], r["predictor"]) for r in table[:3]] == [
        ("d1:test", "CNN"), ("d1:test", "constant"), ("d2:all", "CNN"),
    ]  # fmt: skip
    assert float(table[0]["skill"]) == pytest.approx(0.625)
    assert float(table[1]["constant_value"]) == pytest.approx(0.0123)
    assert table[2]["skill"] == "" and table[-1]["source"].startswith("paper")
    md_path, csv_path = write_cnn_table(rows, tmp_path, const)
    assert md_path.read_text() == md and csv_path.is_file()


def test_table_rows_from_metrics_groups_complete_rows_only():
    metrics = {f"test/d1/{k}": v for k, v in ROW.items()}
    metrics.update({f"test/{k}": v for k, v in ROW.items()})
    metrics.update({"test/d2/nlat_mae": 0.1, "val/nlat_mae": 0.2, "test/d1/constant/nlat_mae": 0.3})
    rows = table_rows_from_metrics(metrics)
    assert rows == {"d1": pytest.approx(ROW), "test": pytest.approx(ROW)}


def test_constant_rows_round_trip_through_metrics_and_errors():
    row = {**CONST, "value": -0.01}
    metrics = {"test/d1:test/nlat_mae": 0.05, **constant_metric_keys("d1:test", row)}
    assert constant_rows_from_metrics(metrics) == {"d1:test": pytest.approx(row)}
    del metrics["test/d1:test/constant/nlat_delta3"]
    assert constant_rows_from_metrics(metrics) == {}
    with pytest.raises(ValueError, match=r"constant_rows\['d9'\].*CNN rows"):
        cnn_table_markdown({"d1": ROW}, {"d9": row})
    with pytest.raises(ValueError, match=r"constant_rows\['d1'\]\['value'\]"):
        cnn_table_markdown({"d1": ROW}, {"d1": CONST})


def test_write_cnn_bias_files_and_errors(tmp_path):
    lines = [
        {"dataset": "d1", "line": "line_001", "side": s, "count": 10.0, "mean_truth": 0.01,
         "mean_pred": 0.03, "bias": 0.02}
        for s in ("port", "starboard")
    ]  # fmt: skip
    ranged = [
        {"dataset": "d1", "side": "port", "range_bin": j, "bin_lo": 4 * j, "bin_hi": 4 * j + 4,
         "count": 5.0, "mean_truth": 0.0, "mean_pred": 0.01 * j, "bias": 0.01 * j}
        for j in range(3)
    ]  # fmt: skip
    paths = write_cnn_bias(lines, ranged, tmp_path)
    got = list(csv.DictReader(io.StringIO(paths[0].read_text())))
    assert [r["side"] for r in got] == ["port", "starboard"]
    assert float(got[0]["bias"]) == pytest.approx(0.02)
    assert len(paths[1].read_text().splitlines()) == 4
    assert paths[2].read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(ValueError, match=r"line_rows\[0\].*missing \['bias'\]"):
        write_cnn_bias([{k: v for k, v in lines[0].items() if k != "bias"}], ranged, tmp_path)
    with pytest.raises(ValueError, match="side in"):
        write_cnn_bias([{**lines[0], "side": 0}], ranged, tmp_path)


# ------------------------------------------------------------------ end to end
H, W = 8, 16


@dataclass
class Line:
    name: str
    n_lat: np.ndarray
    valid: np.ndarray


class Windows(Dataset):
    """Windows of lines of shape (2*H, 2, W): two windows per side, at pings 0 and H."""

    def __init__(self, lines):
        self.lines, self.line_names = lines, [ln.name for ln in lines]
        self.items = [(li, s, p0) for li in range(len(lines)) for s in (0, 1) for p0 in (0, H)]

    def __len__(self):
        return len(self.items)

    def __getitem__(self, i):
        li, s, p0 = self.items[i]
        ln = self.lines[li]
        n_lat = torch.tensor(ln.n_lat[p0 : p0 + H, s][None], dtype=torch.float32)
        intensity = 1.0 - n_lat
        return {
            "intensity": intensity, "inputs": intensity, "n_lat": n_lat,
            "mask": torch.tensor(ln.valid[p0 : p0 + H, s][None]),
            "line": torch.tensor(li), "side": torch.tensor(s), "ping_start": torch.tensor(p0),
            "bin_start": torch.tensor(0), "flipped": torch.tensor(False),
        }  # fmt: skip


def _line(name, rng, offset):
    n_lat = (offset + 0.05 * rng.standard_normal((2 * H, 2, W))).astype(np.float32)
    return Line(name, n_lat, rng.random((2 * H, 2, W)) > 0.2)


class LinesModule(pl.LightningDataModule):
    def __init__(self):
        super().__init__()
        rng = np.random.default_rng(0)
        self.train_set = Windows([_line(f"tr{i}", rng, 0.2) for i in range(2)])
        self.val_set = Windows([_line("va", rng, 0.2)])
        # test data far from the training mean: a constant taken from it would be ~ -0.3
        self.test_sets = [Windows([_line("te0", rng, -0.3), _line("te1", rng, -0.3)])]
        self.test_set_names = ["d1:test"]
        self.train_lines, self.val_lines = ["tr0", "tr1"], ["va"]

    def train_dataloader(self):
        return DataLoader(self.train_set, batch_size=4)

    def val_dataloader(self):
        return DataLoader(self.val_set, batch_size=4)

    def test_dataloader(self):
        return [DataLoader(ds, batch_size=3) for ds in self.test_sets]


def test_writer_scores_training_mean_and_writes_bias(tmp_path):
    torch.manual_seed(0)
    model = NormalCNNModule(
        net=NormalResNet(base_width=4, n_blocks=1),
        loss=NormalLoss("normal_aware", tv_across_track=0.0, tv_along_track=0.0),
        optimizer=partial(torch.optim.Adam, lr=1e-3),
        image_every_n_epochs=0,
    )
    writer = CNNTableWriter(tmp_path, n_range_bins=4)
    trainer = pl.Trainer(
        max_epochs=1, accelerator="cpu", logger=False, callbacks=[writer],
        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
        num_sanity_val_steps=0,
    )  # fmt: skip
    dm = LinesModule()
    trainer.fit(model, datamodule=dm)
    trainer.test(model, datamodule=dm)
    train = dm.train_set.lines
    expect = np.concatenate([ln.n_lat[ln.valid] for ln in train]).astype(np.float64).mean()
    assert writer.constant == pytest.approx(expect, abs=1e-6) and writer.constant > 0.15
    # the constant's MAE over the test windows' valid pixels
    err = [np.abs(writer.constant - ln.n_lat[ln.valid]) for ln in dm.test_sets[0].lines]
    const_mae = np.concatenate(err).mean()
    fm = model.final_metrics
    assert fm["test/d1:test/constant/nlat_mae"] == pytest.approx(const_mae, rel=1e-5)
    assert fm["test/d1:test/constant/value"] == pytest.approx(expect, abs=1e-6)
    assert fm["data/n_train_lines"] == 2 and fm["data/n_val_lines"] == 1
    md = writer.paths[0].read_text()
    skill = fm["test/d1:test/nlat_mae"] / const_mae
    assert f"| {skill:.2f} |" in md and f"constant {writer.constant:+.4f}" in md
    bias = list(csv.DictReader(io.StringIO((tmp_path / "cnn_bias.csv").read_text())))
    assert [(r["line"], r["side"]) for r in bias] == [
        ("te0", "port"), ("te0", "starboard"), ("te1", "port"), ("te1", "starboard"),
    ]  # fmt: skip
    ln = dm.test_sets[0].lines[0]
    assert float(bias[0]["mean_truth"]) == pytest.approx(ln.n_lat[:, 0][ln.valid[:, 0]].mean())
    assert float(bias[0]["count"]) == ln.valid[:, 0].sum()
    for r in bias:
        assert math.isclose(
            float(r["bias"]), float(r["mean_pred"]) - float(r["mean_truth"]), abs_tol=1e-12
        )
    assert (tmp_path / "cnn_bias.png").is_file() and (tmp_path / "cnn_bias_range.csv").is_file()
