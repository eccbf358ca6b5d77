"""Fine-tuning curve: commands, reader and outputs on synthetic run folders (fast); the
whole curve through the real entry point at tiny scale (slow)."""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path

import pytest

from studies.finetune_curve import (
    RUN_RECORD,
    main,
    parse_counts,
    read_runs,
    run_command,
    write_finetune_curve,
)

ROOT = Path(__file__).resolve().parents[2]
SET = "site_tiny_ft8:test"


def fake_run(folder: Path, start: str, n: int, mae: float, const: float) -> Path:
    folder.mkdir(parents=True)
    metrics = {
        "val/nlat_mae": 0.1,
        f"test/{SET}/nlat_mae": mae,
        f"test/{SET}/constant/nlat_mae": const,
        f"test/{SET}/nlat_rmse": 2 * mae,
    }
    (folder / "metrics.json").write_text(json.dumps(metrics))
    record = {"start": start, "n_lines": n, "run_s": 3.0, "model": "/x/m.safetensors"}
    (folder / RUN_RECORD).write_text(json.dumps(record))
    return folder


def test_counts_are_checked():
    assert parse_counts("8,0, 2,4,2") == [0, 2, 4, 8]
    for bad in ("1,2", "0", "a", "-2,4"):
        with pytest.raises(ValueError, match="--counts"):
            parse_counts(bad)


def test_run_commands_start_from_the_model_or_from_scratch(monkeypatch, tmp_path):
    import studies.finetune_curve as fc

    monkeypatch.setattr(fc, "model_overrides", lambda model: ["++model.net.base_width=2"])
    model = tmp_path / "m.safetensors"
    args = ("site", 8, "tiny", tmp_path / "run", 1)
    zero = run_command("pretrained", 0, model, *args)
    assert f"model.init={model}" in zero and "train=false" in zero
    assert "data.n_train_lines=2" in zero and "data.test_surveys=[]" in zero
    assert "data.survey.plan.n_train=8" in zero and "data.survey.name=site_tiny_ft8" in zero
    four = run_command("pretrained", 4, model, *args, overrides=["trainer.max_epochs=3"])
    assert "data.n_train_lines=4" in four and "train=false" not in four
    assert four[-1] == "trainer.max_epochs=3"
    scratch = run_command("scratch", 4, model, *args)
    assert not any(a.startswith("model.init=") for a in scratch)
    assert "++model.net.base_width=2" in scratch  # the same network, random weights
    for start, n, message in (("scratch", 0, "needs lines"), ("pretrained", 9, "0 or 2..8"),
                              ("other", 2, "start: expected")):  # fmt: skip
        with pytest.raises(ValueError, match=message):
            run_command(start, n, model, *args)


def test_reader_and_outputs_share_one_skill_denominator(tmp_path):
    runs = [
        fake_run(tmp_path / "runs" / "pretrained_00", "pretrained", 0, 0.06, 0.11),
        fake_run(tmp_path / "runs" / "pretrained_02", "pretrained", 2, 0.05, 0.09),
        fake_run(tmp_path / "runs" / "pretrained_08", "pretrained", 8, 0.04, 0.085),
        fake_run(tmp_path / "runs" / "scratch_02", "scratch", 2, 0.09, 0.09),
        fake_run(tmp_path / "runs" / "scratch_08", "scratch", 8, 0.05, 0.08),
    ]
    rows = read_runs(runs)
    assert [(r["start"], r["n_lines"]) for r in rows] == [
        ("pretrained", 0), ("pretrained", 2), ("pretrained", 8), ("scratch", 2), ("scratch", 8),
    ]  # fmt: skip
    assert {r["constant_mae"] for r in rows} == {0.08}  # scratch at 8 lines: the most lines
    assert rows[0]["skill"] == pytest.approx(0.75) and rows[-1]["skill"] == pytest.approx(0.625)
    md, csv_path, png = write_finetune_curve(rows, tmp_path)
    text = md.read_text()
    assert "starting from the trained CNN `m.safetensors`" in text
    assert "| 0 | 0.0600 / 0.75 |  |" in text and "| 8 | 0.0400 / 0.50 | 0.0500 / 0.62 |" in text
    table = list(csv.DictReader(io.StringIO(csv_path.read_text())))
    assert len(table) == 5 and float(table[3]["skill"]) == pytest.approx(0.09 / 0.08)
    assert png.stat().st_size > 1000
    # read-only mode reads the same folders
    assert main(["--read-only", "--out", str(tmp_path)]).read_text() == text
    # a run twice, or two test sets, is refused
    fake_run(tmp_path / "again" / "x", "scratch", 8, 0.05, 0.08)
    with pytest.raises(ValueError, match="was already read"):
        read_runs([*runs, tmp_path / "again" / "x"])
    other = fake_run(tmp_path / "other", "scratch", 4, 0.05, 0.08)
    metrics = json.loads((other / "metrics.json").read_text())
    metrics["test/b:test/nlat_mae"] = 0.1
    (other / "metrics.json").write_text(json.dumps(metrics))
    with pytest.raises(ValueError, match="expected the site's test lines as the one test set"):
        read_runs([other])


@pytest.mark.slow
def test_the_curve_through_the_entry_point_at_tiny_scale(tmp_path, monkeypatch):
    """A tiny CNN exported, then fine-tuned on 2 lines of site2 and trained from scratch."""
    import subprocess
    import sys

    env = dict(os.environ, SSS2BATHY_ROOT=str(ROOT), OMP_NUM_THREADS="1")
    common = [f"paths.data_dir={tmp_path / 'data'}", f"paths.output_dir={tmp_path / 'out'}"]
    cnn = tmp_path / "cnn"
    subprocess.run(
        [sys.executable, "-m", "sss2bathy.cli.train", "experiment=cnn", "scale=tiny",
         "logger=none", "trainer.enable_progress_bar=false", "data.test_surveys=[]",
         "torch_threads=1", f"hydra.run.dir={cnn}", *common],
        env=env, check=True, cwd=tmp_path, capture_output=True,
    )  # fmt: skip
    from sss2bathy.pretrained import export_checkpoint

    weights, _ = export_checkpoint(cnn / "checkpoints" / "last.ckpt", tmp_path / "m", "m")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("SSS2BATHY_ROOT", str(ROOT))
    md = main(["--model", str(weights), "--scale", "tiny", "--counts", "0,2",
               "--out", str(tmp_path / "ft"), *common])  # fmt: skip
    rows = read_runs(sorted((tmp_path / "ft" / "runs").glob("*")))
    assert [(r["start"], r["n_lines"]) for r in rows] == [
        ("pretrained", 0),
        ("pretrained", 2),
        ("scratch", 2),
    ]
    assert all(r["mae"] > 0 and r["skill"] > 0 for r in rows)
    assert rows[0]["test_set"].startswith("synthetic_d1_site2_tiny_ft2")
    assert "from the trained CNN" in md.read_text()
