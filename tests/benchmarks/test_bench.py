"""Benchmark suite: every section at tiny sizes, the report's structure, the FLOP accounting,
the draping benchmark's ray recording, the runner's command line."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from benchmarks import runner
from benchmarks.demo_stages import demo_stage_times
from benchmarks.matmul import siren_matmul_flops
from benchmarks.report import write_report
from benchmarks.timing import summarize, time_in_turns, time_runs

ROOT = Path(__file__).resolve().parents[2]
TINY_SIREN = {"hidden": 16, "n_layers": 3, "omega0": 30.0, "n_bins": 48, "max_range_m": 40.0}
TINY = {
    "siren_step": {
        **TINY_SIREN,
        "n_pings": 4,
        "altimeter_points": 50,
        "n_batches": 2,
        "warmup": 1,
        "repeats": 2,
        "mm_repeats": 2,
    },
    "finder": {
        **TINY_SIREN,
        "n_pings": 4,
        "warmup": 0,
        "repeats": 2,
        "gd_repeats": 1,
        "gd_max_iter": 600,
    },
    "cnn": {
        "configs": {"tiny": {"base_width": 2, "n_blocks": 1, "batch_size": 2}},
        "window": (16, 64),
        "max_batch": 1,
        "warmup": 1,
        "repeats": 2,
    },
    "windows": {
        "n_lines": 2,
        "n_pings": 40,
        "n_bins": 64,
        "window": (16, 32),
        "batch": 4,
        "n_batches": 2,
        "warmup": 0,
        "repeats": 2,
    },
    "sim": {"scale": "tiny", "n_pings": 4, "warmup": 0, "repeats": 2},
    "drape": {"n_pings": 12, "n_bins": 32, "cell_m": 4.0, "warmup": 0, "repeats": 2},
}
STATS = ("median", "min", "max", "q1", "q3")


@pytest.fixture(scope="module")
def doc(tmp_path_factory):
    stage_file = tmp_path_factory.mktemp("report") / "stage_times.json"
    stage_file.write_text(json.dumps({"scale": "demo", "seconds": {"cnn": 95.2, "total": 612.0}}))
    return runner.run_benchmarks(
        quick=True, device="cpu", root=ROOT, stage_times=stage_file, overrides=TINY
    )


def test_every_section_reports_positive_finite_figures(doc):
    assert list(doc["sections"]) == [*runner.SECTIONS, "gpu_projection"]
    for name, section in doc["sections"].items():
        assert section["figures"], name
        for f in section["figures"]:
            for key in STATS:
                assert math.isfinite(f[key]) and f[key] > 0, (name, f["name"], key, f[key])
            assert f["min"] <= f["q1"] <= f["median"] <= f["q3"] <= f["max"], f
            assert f["n"] >= 1
    timed = [
        f for s in ("siren_step", "cnn", "sim", "drape") for f in doc["sections"][s]["figures"]
    ]
    assert all(f["n"] >= 2 for f in timed if f["unit"] in ("s", "1/s", "windows/s", "rays/s"))


def test_siren_step_counts_every_matmul(doc):
    sec = doc["sections"]["siren_step"]
    info = sec["info"]
    pts = info["points"]
    # the finder (no graph), the gradient pass of the valid bins and the altimeter heights
    finder_pts = pts.get("height", 0) + pts.get("gradient", 0)
    assert finder_pts > 0 and pts["gradient_grad"] > 0 and pts["height_grad"] == 50
    # analytic count from layer shapes x points == every mm/addmm dispatched (fwd + bwd)
    assert info["recorded_siren_flops"] == info["analytic_flops"]["total"]
    assert info["analytic_flops"]["backward"] > info["analytic_flops"]["forward"] / 10
    assert info["recorded_flops"] >= info["recorded_siren_flops"]  # + tiny arc/normal bmm
    figs = {f["name"]: f for f in sec["figures"]}
    assert 0 < figs["valid bins per step"]["max"] <= 4 * 2 * 48
    assert figs["matmul bound"]["median"] < figs["step time"]["median"]
    ratio = figs["matmul bound / step time"]["median"] / 100
    assert ratio == pytest.approx(info["bound_fraction"], rel=0.5)
    # sines: one per hidden unit and point of every pass, a cosine too in gradient passes
    # (2 sine layers of 16 here); the arc geometry's sin/cos of the angles come on top
    per_point = 2 * 16
    heights = pts.get("height", 0) + pts["height_grad"]
    gradients = pts.get("gradient", 0) + pts["gradient_grad"]
    siren_sines = per_point * (heights + 2 * gradients)
    assert siren_sines <= info["sine_elements"] <= 1.25 * siren_sines
    assert 0 < figs["sine bound"]["median"] < figs["step time"]["median"]
    ceiling = figs["ceiling: matmul / (matmul + sine bound)"]["median"] / 100
    assert ceiling == pytest.approx(info["matmul_fraction_ceiling"])
    assert info["bound_fraction"] < ceiling < 1


def test_siren_matmul_flops_by_hand():
    # 3 layers, width 4: sine 2->4, 4->4, out 4->1; reverse 4x4 and 4x2
    f = siren_matmul_flops(4, 3, {"height": 1})
    assert f == {"forward": 2 * (8 + 16 + 4), "backward": 0, "total": 56}
    g = siren_matmul_flops(4, 3, {"gradient_grad": 2})
    fwd = 2 * 2 * (8 + 16 + 4 + 16 + 8)
    bwd = 2 * (2 * 2 * (8 + 16 + 16 + 8) - 2 * 8)
    assert g == {"forward": fwd, "backward": bwd, "total": fwd + bwd}


def test_finder_solvers_agree_and_newton_is_faster(doc):
    sec = doc["sections"]["finder"]
    solvers = sec["info"]["solvers"]
    for key in ("gd", "newton", "gd_warm", "newton_warm"):
        s = solvers[key]
        assert s["valid"] > 0
        assert s["max_residual_mm"] <= 1.0 + 1e-3  # every solver at the same accuracy
        assert s["found_of_reference"] > 0.9, (key, s)
    # a warm start converges in about two Newton evaluations (the check + one step)
    assert solvers["newton_warm"]["iters_mean"] <= 2.5
    assert solvers["newton_warm"]["max_point_diff_mm"] < 5.0
    assert solvers["gd"]["iters_mean"] > 5 * solvers["newton"]["iters_mean"]
    assert all(v > 0 for v in sec["info"]["speedups"].values())
    assert 0 < sec["info"]["warm_start_height_change_rms_m"] < 0.5


def test_cnn_batch_cap_and_demo_stage_times(doc):
    (windows, step) = doc["sections"]["cnn"]["figures"]
    assert "capped" in windows["note"] and windows["unit"] == "windows/s"
    assert windows["max"] == pytest.approx(1 / step["min"], rel=1e-6)  # batch 1
    stages = {f["name"]: f["median"] for f in doc["sections"]["demo_stages"]["figures"]}
    assert stages == {"cnn": 95.2, "total": 612.0}


def test_window_batches_report_their_rate(doc):
    sec = doc["sections"]["windows"]
    (rate,) = sec["figures"]
    assert rate["unit"] == "batches/s" and rate["n"] == 2
    assert sec["params"]["windows"] > 0 and sec["params"]["batch"] == 4


def test_report_files(doc, tmp_path):
    paths = write_report(doc, tmp_path / "bench")
    data = json.loads(paths["json"].read_text())
    assert set(data["sections"]) == {*runner.SECTIONS, "gpu_projection"}
    assert data["machine"]["device"] == "cpu" and data["mode"] == "quick"
    assert data["other_load_cores"] is None or 0 <= data["other_load_cores"] <= 64
    md = paths["markdown"].read_text()
    rows = [ln for ln in md.splitlines() if ln.startswith("| ") and not ln.startswith("| Bench")]
    n_figures = sum(len(s["figures"]) for s in doc["sections"].values())
    assert len(rows) == n_figures
    assert all(ln.count("|") == 9 for ln in rows)
    assert "| SIREN training step | steps/s |" in md


def test_summarize_and_bad_inputs(tmp_path):
    s = summarize([4.0, 1.0, 3.0, 2.0, 5.0])
    assert (s["median"], s["min"], s["max"], s["q1"], s["q3"], s["n"]) == (3, 1, 5, 2, 4, 5)
    with pytest.raises(ValueError, match="only"):
        runner.run_benchmarks(only=["nope"], root=ROOT)
    with pytest.raises(ValueError, match="repeats"):
        time_runs(lambda: None, 0, 0)
    with pytest.raises(SystemExit):
        runner.parse_args(["--only", "finder,nope"])
    missing = demo_stage_times(tmp_path / "none.json")
    assert missing["figures"] == [] and missing["info"]["missing"]


def test_time_in_turns_runs_round_robin_after_warmup():
    calls = []
    fns = {"a": lambda: calls.append("a"), "b": lambda: calls.append("b")}
    wall, cpu = time_in_turns(fns, {"a": 3, "b": 1}, warmup=1)
    assert calls == ["a", "b", "a", "b", "a", "a"]  # warm-up, then rounds while repeats last
    assert [len(wall["a"]), len(wall["b"]), len(cpu["a"])] == [3, 1, 3]
    with pytest.raises(ValueError, match="repeats: expected a count for every function"):
        time_in_turns(fns, {"a": 1}, warmup=0)


def test_presets_come_from_the_composed_configs():
    from benchmarks.config import cnn_preset, project_root, survey_preset

    paper = cnn_preset(ROOT, "paper")
    assert (paper["base_width"], paper["n_blocks"], paper["batch_size"]) == (64, 7, 64)
    # the paper's architecture (two down-sampling stages) and loss (eq. 4-5) at scale=paper;
    # the demo's own choices (README "CNN") through the same keys
    assert paper["n_down"] == 2 and paper["loss"]["kind"] == "normal_aware"
    demo = cnn_preset(ROOT, "demo")
    assert demo["n_down"] == 3 and demo["loss"]["kind"] == "l1"
    survey = survey_preset(ROOT, "synthetic_d1", "tiny")
    assert survey["sonar"]["n_bins"] > 0 and "terrain" in survey
    with pytest.raises(ValueError, match="root: expected the project checkout"):
        project_root(ROOT / "benchmarks")


def test_cli_writes_report(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    stage_file = tmp_path / "stage_times.json"
    stage_file.write_text(json.dumps({"scale": "demo", "seconds": {"prepare_d1": 12.5}}))
    out = tmp_path / "out"
    rc = runner.main(
        ["--only", "demo_stages", "--stage-times", str(stage_file), "--out", str(out)]
        + ["--root", str(ROOT)]
    )
    assert rc == 0
    data = json.loads((out / "bench.json").read_text())
    assert data["sections"]["demo_stages"]["figures"]
    assert data["machine"]["git"] is None or len(data["machine"]["git"]) >= 40
    assert "| make demo stages | prepare_d1 | 12.5 | s |" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        runner.parse_args(["--root", str(tmp_path)])  # no conf/ there
    capsys.readouterr()
    stage_file.write_text("{not json")
    rc = runner.main(["--only", "demo_stages", "--stage-times", str(stage_file), "--out", str(out)])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {stage_file}: expected JSON stage times")


def test_cnn_inference_variants_and_projection():
    """Every variant of the CNN inference benchmark runs at a tiny size; the projection is
    the survey's windows over the measured rate; the pipeline's rate is compared with the
    bare pass of what it runs (the bfloat16 copy for bf16)."""
    from benchmarks import cnn_inference

    out = cnn_inference.bench(
        base_width=2, n_blocks=1, batch=2, window=(16, 64), repeats=1, e2e_pings=40,
        e2e_batch=4,
    )  # fmt: skip
    assert set(out["windows_per_s"]) == set(cnn_inference.VARIANTS)
    assert all(r > 0 and math.isfinite(r) for r in out["windows_per_s"].values())
    n = out["survey_windows_12_lines_by_overlap"]
    assert n["overlap_0.5"] < n["overlap_0.75"]
    rate = out["windows_per_s"]["bf16_net"]
    assert out["projected_min_12_lines"]["bf16_net_overlap_0.5"] == pytest.approx(
        n["overlap_0.5"] / rate / 60
    )
    assert {"fp32_ratio_to_forward", "bf16_ratio_to_forward"} <= set(out["e2e"])
    with pytest.raises(ValueError, match="variants: expected some of"):
        cnn_inference.bench(base_width=2, n_blocks=1, variants=["fp16"])
