"""The thread policy: OpenMP's idle threads sleep instead of spinning, torch's thread count
follows the usable cores (or the run's torch_threads), and what the user set is kept."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from sss2bathy.utils import threads
from sss2bathy.utils.threads import (
    MARK_ENV,
    apply_thread_policy,
    available_cores,
    set_env_defaults,
)

ROOT = Path(__file__).resolve().parents[2]


def test_env_defaults_set_passive_waiting_unless_the_user_chose():
    env: dict[str, str] = {}
    assert set_env_defaults(env) == {"OMP_WAIT_POLICY": "PASSIVE"}
    assert env == {"OMP_WAIT_POLICY": "PASSIVE", MARK_ENV: "OMP_WAIT_POLICY"}
    assert set_env_defaults(env) == {}  # a child process inherits it: nothing more to set
    for users in ({"OMP_WAIT_POLICY": "ACTIVE"}, {"GOMP_SPINCOUNT": "10000"}):
        env = dict(users)
        assert set_env_defaults(env) == {} and env == users
    env = {"SSS2BATHY_THREADS": "off"}
    assert set_env_defaults(env) == {} and "OMP_WAIT_POLICY" not in env


def test_available_cores_is_the_affinity_capped_by_the_cgroup_quota(monkeypatch):
    n = available_cores()
    assert 1 <= n <= (os.cpu_count() or 1)
    if hasattr(os, "sched_getaffinity"):
        assert n <= len(os.sched_getaffinity(0))
    monkeypatch.setattr(threads, "_cgroup_quota", lambda: 0.5)  # half a CPU: one thread
    assert available_cores() == 1


@pytest.fixture
def torch_threads_restored():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_policy_sets_torch_threads_and_says_so_in_one_line(
    monkeypatch, caplog, torch_threads_restored
):
    for key in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OMP_WAIT_POLICY", "GOMP_SPINCOUNT"):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("OMP_WAIT_POLICY", "PASSIVE")
    monkeypatch.setenv(MARK_ENV, "OMP_WAIT_POLICY")  # set by the package (a parent process)
    monkeypatch.setattr(threads, "available_cores", lambda: 1)
    monkeypatch.setitem(threads._state, "late", False)  # whatever this test process did
    with caplog.at_level(logging.INFO, logger="sss2bathy"):
        policy = apply_thread_policy(None)
    assert torch.get_num_threads() == 1 and policy.source == "cores"
    (line,) = [r.getMessage() for r in caplog.records if r.getMessage().startswith("threads:")]
    assert line == (
        "threads: torch 1 (the 1 usable cores), OpenMP waiting OMP_WAIT_POLICY=PASSIVE "
        "(sss2bathy's default; set OMP_WAIT_POLICY to change)"
    )
    # the run's torch_threads wins; the user's OMP_NUM_THREADS is torch's own default
    assert apply_thread_policy(1, announce=False).source == "torch_threads"
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    monkeypatch.delenv(MARK_ENV)
    policy = apply_thread_policy(None, announce=False)
    assert policy.source == "OMP_NUM_THREADS" and policy.wait_source == "user"
    assert "OMP_WAIT_POLICY=ACTIVE (set in the environment)" in policy.line()
    monkeypatch.delenv("OMP_WAIT_POLICY")  # a library caller that never set it
    assert "(OMP_WAIT_POLICY unset: idle threads spin" in apply_thread_policy(1, False).line()
    with pytest.raises(ValueError, match="torch_threads: expected a positive integer"):
        apply_thread_policy(0)


def _torch_libgomp() -> Path | None:
    """torch's GNU OpenMP runtime (``torch/lib/libgomp*.so*``), None for another one."""
    found = sorted((Path(torch.__file__).parent / "lib").glob("libgomp*.so*"))
    return found[0] if found else None


def _openmp_env(env: dict[str, str]) -> str:
    """What torch's OpenMP runtime reports when a process that imported ``sss2bathy.cli``
    loads it (``OMP_DISPLAY_ENV=VERBOSE``; loaded alone, which is what importing torch does
    first, without torch's seconds of start-up)."""
    base = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", MARK_ENV)}
    base.update(OMP_DISPLAY_ENV="VERBOSE", OMP_NUM_THREADS="1", **env)
    code = "import ctypes, sys, sss2bathy.cli; ctypes.CDLL(sys.argv[1])"
    done = subprocess.run(
        [sys.executable, "-c", code, str(_torch_libgomp())], env=base, cwd=ROOT,
        capture_output=True, text=True, timeout=120, check=True,
    )  # fmt: skip
    return done.stderr


def test_entry_points_start_openmp_with_passive_waiting():
    if _torch_libgomp() is None:
        pytest.skip("torch is not built with GNU OpenMP (no torch/lib/libgomp*.so*)")
    # libgomp's default: spin 300000 iterations before sleeping; the policy: sleep at once
    assert "GOMP_SPINCOUNT = '0'" in _openmp_env({})
    assert "GOMP_SPINCOUNT = '300000'" in _openmp_env({"SSS2BATHY_THREADS": "off"})
    # the user's choice is kept
    assert "OMP_WAIT_POLICY = 'ACTIVE'" in _openmp_env({"OMP_WAIT_POLICY": "ACTIVE"})
