"""The process's thread policy: how many threads torch uses and how its idle threads wait.

PyTorch's CPU kernels (and MKL's and oneDNN's inside it) run on the GNU OpenMP runtime
(``libgomp``). At every parallel region's end its threads meet at a barrier, and by default
a thread that arrives first *spins* for ~300000 iterations (a few ms) before it sleeps.
On a machine with something else running, one of the fit's threads is regularly
descheduled for a whole time slice; the others then burn their CPU share spinning at the
barrier instead of yielding it, and a region of tens of microseconds waits milliseconds.
``docs/performance_log.md`` (``python -m benchmarks.thread_policy``) has the measurements.

The policy (:func:`apply_thread_policy`):

* **waiting**: ``OMP_WAIT_POLICY=PASSIVE`` (a waiting thread sleeps at once), set in the
  environment by :func:`set_env_defaults` before torch loads the runtime, which reads it
  once; the entry points do this when the ``sss2bathy.cli`` package is imported, so every
  console script and ``python -m sss2bathy.cli.<x>`` gets it, and so do the processes they
  start (the pipeline's stages, the simulator's workers) through the inherited
  environment. A value the user set (``OMP_WAIT_POLICY``, ``GOMP_SPINCOUNT``) is kept;
  ``SSS2BATHY_THREADS=off`` leaves the runtime's defaults alone;
* **threads**: torch's intra-op threads = the run's ``torch_threads`` when set, else the
  cores this process may use (:func:`available_cores`: its affinity mask and its cgroup's
  CPU quota), unless ``OMP_NUM_THREADS`` / ``MKL_NUM_THREADS`` was set by the user
  (torch's own reading of them is kept). Draping's ``threads: auto`` follows torch's count;
  numba compiles draping's kernels without ``parallel=True``, so numba's own thread pool
  never starts.

The wait policy changes how threads idle, never what they compute: with the same thread
count a seed gives the same bits quiet or loaded. The thread count can change a reduction's
order (the last digits of a loss); a published table is reproduced with its run's
``torch_threads``, which the run's config and the INFO line of :meth:`ThreadPolicy.line`
record.
"""

from __future__ import annotations

import logging
import math
import os
import sys
from collections.abc import MutableMapping
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger("sss2bathy")

#: ``off``: leave the OpenMP runtime's own defaults (no wait policy set)
POLICY_ENV = "SSS2BATHY_THREADS"
#: the environment defaults the policy sets before the OpenMP runtime starts
ENV_DEFAULTS: dict[str, str] = {"OMP_WAIT_POLICY": "PASSIVE"}
#: variables that, when the user set any, mean they chose the wait behaviour themselves
WAIT_KEYS = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")
#: variables that, when the user set any, set torch's default thread count
COUNT_KEYS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS")
#: names of the variables the package set (not the user), so child processes know
MARK_ENV = "SSS2BATHY_ENV_DEFAULTS"

#: ``late``: this process set a variable after torch had loaded the runtime (no effect here)
_state: dict[str, bool] = {"late": False}


def _cgroup_quota() -> float | None:
    """CPUs of this process's cgroup quota (v2 ``cpu.max``, v1 ``cpu.cfs_quota_us``),
    None without one."""
    try:
        text = Path("/sys/fs/cgroup/cpu.max").read_text().split()
        if text and text[0] != "max":
            return float(text[0]) / float(text[1])
    except (OSError, ValueError, IndexError):
        pass
    try:
        quota = float(Path("/sys/fs/cgroup/cpu/cpu.cfs_quota_us").read_text())
        period = float(Path("/sys/fs/cgroup/cpu/cpu.cfs_period_us").read_text())
        if quota > 0 and period > 0:
            return quota / period
    except (OSError, ValueError):
        pass
    return None


def available_cores() -> int:
    """The CPU cores this process may run on: its affinity mask where the OS has one,
    at most its cgroup's CPU quota (rounded up); at least 1."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # no affinity API (macOS, Windows)
        n = os.cpu_count() or 1
    quota = _cgroup_quota()
    if quota is not None:
        n = min(n, math.ceil(quota))
    return max(1, n)


def policy_off(environ: MutableMapping[str, str] | None = None) -> bool:
    """``SSS2BATHY_THREADS=off``: the package sets no thread policy."""
    environ = os.environ if environ is None else environ
    return environ.get(POLICY_ENV, "").strip().lower() == "off"


def _marked(environ: MutableMapping[str, str]) -> set[str]:
    return {k for k in environ.get(MARK_ENV, "").split(",") if k}


def set_env_defaults(environ: MutableMapping[str, str] | None = None) -> dict[str, str]:
    """Put :data:`ENV_DEFAULTS` in the environment where the user set none of
    :data:`WAIT_KEYS` (and not ``SSS2BATHY_THREADS=off``); returns what it set.

    Call before torch is imported: the OpenMP runtime reads its wait policy once, when it
    loads. Where torch is already loaded the variables still reach child processes, and
    :meth:`ThreadPolicy.line` says this process kept the runtime's default."""
    environ = os.environ if environ is None else environ
    if policy_off(environ):
        return {}
    marked = _marked(environ)
    if any(k in environ and k not in marked for k in WAIT_KEYS):
        return {}  # the user's choice
    added = {k: v for k, v in ENV_DEFAULTS.items() if k not in environ}
    environ.update(added)
    if added:
        environ[MARK_ENV] = ",".join(sorted(marked | set(added)))
        if environ is os.environ and "torch" in sys.modules:
            _state["late"] = True
    return added


def _user_set(key: str, environ: MutableMapping[str, str]) -> bool:
    return key in environ and key not in _marked(environ)


@dataclass(frozen=True)
class ThreadPolicy:
    """What :func:`apply_thread_policy` chose (for the log line and run records)."""

    torch_threads: int
    cores: int
    source: str  # "torch_threads", "OMP_NUM_THREADS" (the user's), "cores"
    wait: str  # the OMP_WAIT_POLICY / GOMP_SPINCOUNT in force, "runtime default"
    wait_source: str  # "sss2bathy", "user", "off", "unset", "loaded before the policy"

    def line(self) -> str:
        """The one INFO line: ``threads: torch 2 (the 2 usable cores), OpenMP waiting
        OMP_WAIT_POLICY=PASSIVE (sss2bathy's default; set OMP_WAIT_POLICY to change)``."""
        count = {
            "torch_threads": f"torch {self.torch_threads} (torch_threads; {self.cores} usable "
            "cores)",
            "cores": f"torch {self.torch_threads} (the {self.cores} usable cores)",
        }.get(
            self.source,
            f"torch {self.torch_threads} ({self.source} set; {self.cores} usable cores)",
        )
        how = {
            "sss2bathy": "sss2bathy's default; set OMP_WAIT_POLICY to change",
            "user": "set in the environment",
            "off": f"{POLICY_ENV}=off",
            "loaded before the policy": "torch was loaded before the policy could set it",
            "unset": "OMP_WAIT_POLICY unset: idle threads spin before they sleep",
        }[self.wait_source]
        return f"threads: {count}, OpenMP waiting {self.wait} ({how})"


def _wait_in_force(environ: MutableMapping[str, str]) -> tuple[str, str]:
    set_keys = [k for k in WAIT_KEYS if k in environ]
    if not set_keys:
        return "runtime default", "off" if policy_off(environ) else "unset"
    wait = ", ".join(f"{k}={environ[k]}" for k in set_keys)
    if _state["late"] and not any(_user_set(k, environ) for k in set_keys):
        return "runtime default", "loaded before the policy"
    return wait, "user" if any(_user_set(k, environ) for k in set_keys) else "sss2bathy"


def apply_thread_policy(torch_threads: int | None = None, announce: bool = True) -> ThreadPolicy:
    """Set torch's intra-op threads by the policy (module docstring) and log it in one
    INFO line (``announce``). ``torch_threads``: the run's ``torch_threads`` (None: the
    user's ``OMP_NUM_THREADS``, else the usable cores)."""
    import torch

    environ = os.environ
    cores = available_cores()
    if torch_threads is not None:
        n, source = int(torch_threads), "torch_threads"
        if n < 1:
            raise ValueError(f"torch_threads: expected a positive integer or null, found {n}")
    elif policy_off(environ):
        n, source = torch.get_num_threads(), f"{POLICY_ENV}=off"
    else:
        user = [k for k in COUNT_KEYS if _user_set(k, environ)]
        if user:
            n, source = torch.get_num_threads(), user[0]
        else:
            n, source = cores, "cores"
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    wait, wait_source = _wait_in_force(environ)
    policy = ThreadPolicy(n, cores, source, wait, wait_source)
    if announce:
        log.info("%s", policy.line())
    return policy
