"""Learning-curve harness: reader and plots on synthetic run folders (fast); two tiny runs
through the real entry point on one survey with fixed test lines (slow)."""

import csv
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from sss2bathy.data.windows import SidescanWindowDataModule
from studies.learning_curve import (
    RUN_RECORD,
    main,
    parse_counts,
    read_runs,
    run_command,
    write_learning_curve,
)

ROOT = Path(__file__).resolve().parents[2]
SETS = ("d1_lc:test", "d2:all")


def fake_run(folder: Path, n_train: int, mae: dict, const: dict, train_s: float) -> Path:
    folder.mkdir(parents=True)
    metrics = {"val/nlat_mae": 0.1, "data/n_train_lines": n_train - 1.0, "data/n_val_lines": 1.0}
    for name in mae:
        metrics[f"test/{name}/nlat_mae"] = mae[name]
        metrics[f"test/{name}/nlat_rmse"] = 2 * mae[name]
        metrics[f"test/{name}/constant/nlat_mae"] = const[name]
    (folder / "metrics.json").write_text(json.dumps(metrics))
    (folder / "metric_curve.csv").write_text(
        f"epoch,step,wall_s,train_s,lr,val/nlat_mae\n0,5,1.0,0.5,0.001,0.2\n1,10,"
        f"{train_s + 1},{train_s},0.001,0.1\n"
    )
    (folder / RUN_RECORD).write_text(json.dumps({"n_train": n_train, "run_s": train_s + 9}))
    return folder


def test_reader_and_writer_on_synthetic_runs(tmp_path):
    runs = [
        fake_run(tmp_path / "runs" / "b", 16, dict(zip(SETS, (0.06, 0.09), strict=True)),
                 dict(zip(SETS, (0.085, 0.03), strict=True)), 40.0),
        fake_run(tmp_path / "runs" / "a", 8, dict(zip(SETS, (0.07, 0.12), strict=True)),
                 dict(zip(SETS, (0.09, 0.031), strict=True)), 20.0),
    ]  # fmt: skip
    rows = read_runs(runs)
    assert [(r["n_train"], r["dataset"]) for r in rows] == [
        (8, SETS[0]), (8, SETS[1]), (16, SETS[0]), (16, SETS[1]),
    ]  # fmt: skip
    assert rows[0]["skill"] == pytest.approx(0.07 / 0.09)
    assert rows[2]["train_s"] == 40.0 and rows[2]["fit_wall_s"] == 41.0
    assert rows[2]["n_fit_lines"] == 15 and rows[2]["run_s"] == 49.0
    md, table, png = write_learning_curve(rows, tmp_path / "lc")
    got = list(csv.DictReader(io.StringIO(table.read_text())))
    assert float(got[3]["mae"]) == 0.09 and float(got[3]["constant_mae"]) == 0.03
    assert "| 16 | 15 | 40.0 | 0.0600 / 0.0850 = 0.71 | 0.0900 / 0.0300 = 3.00 |" in md.read_text()
    assert png.read_bytes()[:4] == b"\x89PNG"
    # --read-only: the same outputs from <out>/runs
    assert main(["--read-only", "--out", str(tmp_path)]).read_text() == md.read_text()


def test_reader_names_what_is_missing(tmp_path):
    run = fake_run(tmp_path / "r", 8, {SETS[0]: 0.07}, {SETS[0]: 0.09}, 1.0)
    other = fake_run(tmp_path / "s", 16, {SETS[1]: 0.07}, {SETS[1]: 0.09}, 1.0)
    with pytest.raises(ValueError, match="expected the test sets"):
        read_runs([run, other])
    dup = fake_run(tmp_path / "t", 8, {SETS[0]: 0.07}, {SETS[0]: 0.09}, 1.0)
    with pytest.raises(ValueError, match="n_train=8 was already read"):
        read_runs([run, dup])
    metrics = json.loads((run / "metrics.json").read_text())
    del metrics[f"test/{SETS[0]}/constant/nlat_mae"]
    (run / "metrics.json").write_text(json.dumps(metrics))
    with pytest.raises(ValueError, match="constant/nlat_mae"):
        read_runs([run])
    (run / "metric_curve.csv").unlink()
    with pytest.raises(ValueError, match="metric_curve.csv: expected"):
        read_runs([run])


def test_counts_and_command():
    assert parse_counts("16, 8,32,8") == [8, 16, 32]
    for bad in ("8,x", "1,8", ""):
        with pytest.raises(ValueError, match="--n-train"):
            parse_counts(bad)
    cmd = run_command(8, 32, "syn_lc32", "demo", Path("/o/r"), 1, ["seed=3"])
    # every run: the same survey (32 training lines, one name), its own subset of them
    assert "data.survey.plan.n_train=32" in cmd and "data.survey.name=syn_lc32" in cmd
    assert "data.n_train_lines=8" in cmd and "torch_threads=1" in cmd and cmd[-1] == "seed=3"
    with pytest.raises(ValueError, match="n_train"):
        run_command(33, 32, "s", "demo", Path("/o"), 1)


@pytest.mark.slow
def test_two_tiny_runs_share_their_test_lines(tmp_path):
    env = dict(os.environ, SSS2BATHY_ROOT=str(ROOT), OMP_NUM_THREADS="1")
    cmd = [
        sys.executable, "-m", "studies.learning_curve", "--n-train", "3,4",
        "--scale", "tiny", "--out", str(tmp_path / "lc"), f"paths.data_dir={tmp_path / 'data'}",
        f"paths.output_dir={tmp_path / 'outputs'}", "logger=none",
    ]  # fmt: skip
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    rows = list(csv.DictReader(io.StringIO((tmp_path / "lc" / "learning_curve.csv").read_text())))
    assert sorted({int(r["n_train"]) for r in rows}) == [3, 4]
    assert {int(r["n_fit_lines"]) for r in rows} == {2, 3}
    assert all(float(r["constant_mae"]) > 0 and float(r["train_s"]) > 0 for r in rows)
    assert (tmp_path / "lc" / "learning_curve.png").is_file()
    # the d1 test lines are the same lines with the same truth in both runs
    truth = []
    for n in (3, 4):
        bias = (tmp_path / "lc" / "runs" / f"n_train_{n:03d}" / "cnn_bias.csv").read_text()
        d1 = [r for r in csv.DictReader(io.StringIO(bias)) if r["dataset"].endswith(":test")]
        truth.append([(r["line"], r["side"], r["count"], r["mean_truth"]) for r in d1])
    assert truth[0] and truth[0] == truth[1]


def test_n_train_lines_is_validated():
    survey = {"kind": "synthetic", "name": "x"}
    for bad in (1, 2.5, True):
        with pytest.raises(ValueError, match="data.n_train_lines: expected null or an integer"):
            SidescanWindowDataModule(survey, "/tmp", n_train_lines=bad)
