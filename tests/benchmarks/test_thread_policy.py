"""benchmarks.thread_policy: each policy's environment, the summary table and its ratios."""

from __future__ import annotations

import pytest

from benchmarks.thread_policy import policy_env, summarize, to_markdown


def test_policy_environments(monkeypatch):
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")  # the caller's own: never inherited
    n, env = policy_env("t2_passive", 2)
    assert n == 2 and env["OMP_WAIT_POLICY"] == "PASSIVE" and env["OMP_NUM_THREADS"] == "2"
    assert env["SSS2BATHY_THREADS"] == "off"  # the runtime's own behaviour is measured
    n, env = policy_env("t2_spin", 4)
    assert n == 4 and "OMP_WAIT_POLICY" not in env
    n, env = policy_env("t1", 4)
    assert n == 1 and env["MKL_NUM_THREADS"] == "1"
    with pytest.raises(ValueError, match="policies: expected names among"):
        policy_env("t3", 2)


def _run(policy, load, step, loss=0.5):
    return {"workload": "cnn", "policy": policy, "load": load, "step_median_s": step,
            "last_loss": loss}  # fmt: skip


def test_summary_ratios_and_table():
    runs = [
        _run("t2_spin", "quiet", 0.10), _run("t2_spin", "busy", 0.80),
        _run("t2_spin", "quiet", 0.12), _run("t2_spin", "busy", 0.60),
        _run("t2_passive", "quiet", 0.10), _run("t2_passive", "busy", 0.14),
        _run("t1", "quiet", 0.16, 0.51), _run("t1", "busy", 0.17, 0.51),
    ]  # fmt: skip
    rows = {r["policy"]: r for r in summarize(runs)}
    spin, passive, one = rows["t2_spin"], rows["t2_passive"], rows["t1"]
    assert spin["quiet_s"] == pytest.approx(0.11) and spin["busy_s"] == pytest.approx(0.70)
    assert spin["busy_over_quiet"] == pytest.approx(0.70 / 0.11)
    assert passive["busy_vs_reference_quiet"] == pytest.approx(0.14 / 0.11)
    assert one["quiet_vs_reference"] == pytest.approx(0.16 / 0.11)
    assert {r["reference"] for r in rows.values()} == {"t2_spin"}
    # without t2_spin the first policy run is the reference
    (first, *_) = summarize([r for r in runs if r["policy"] != "t2_spin"])
    assert first["reference"] == "t2_passive" and first["quiet_vs_reference"] == 1.0
    assert all(r["same_loss_in_every_run"] for r in rows.values())
    runs.append(_run("t1", "busy", 0.17, 0.52))  # another loss: not reproducible
    assert not {r["policy"]: r for r in summarize(runs)}["t1"]["same_loss_in_every_run"]
    params = {"cores": 2, "competitor": "new-session", "repeats": 2, "load_before": "0.1",
              "load_after": "1.0"}  # fmt: skip
    text = to_markdown({"command": "python -m benchmarks.thread_policy", "params": params,
                        "rows": summarize(runs)})  # fmt: skip
    assert "| cnn | t2_passive | 100.0 | 140.0 | 1.40 | 0.91 | 1.27 | yes |" in text
    assert "| quiet vs t2_spin quiet |" in text
