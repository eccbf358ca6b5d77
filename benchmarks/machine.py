"""What the numbers were measured on, and how busy the machine was meanwhile."""

from __future__ import annotations

import os
import platform
import subprocess
import time
from pathlib import Path
from typing import Any

import torch

from sss2bathy.utils.machine import cpu_model


def cpu_clock() -> tuple[float, float, float] | None:
    """(busy CPU seconds of the machine, of this process, wall time); Linux only."""
    try:
        fields = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
    except (OSError, IndexError):
        return None
    ticks = [float(v) for v in fields]
    idle = ticks[3] + (ticks[4] if len(ticks) > 4 else 0.0)  # idle + iowait
    hz = float(os.sysconf("SC_CLK_TCK"))
    t = os.times()
    own = t.user + t.system + t.children_user + t.children_system
    return (sum(ticks) - idle) / hz, own, time.perf_counter()


def other_load(start: tuple | None, end: tuple | None) -> float | None:
    """Cores kept busy by *other* processes between two :func:`cpu_clock` readings."""
    if start is None or end is None or end[2] <= start[2]:
        return None
    return max(0.0, ((end[0] - start[0]) - (end[1] - start[1])) / (end[2] - start[2]))


def machine_info(device: torch.device) -> dict[str, Any]:
    """CPU, core count, torch version and threads, device (and GPU name), Python."""
    info: dict[str, Any] = {
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "device": str(device),
        "python": platform.python_version(),
        "ld_preload": os.environ.get("LD_PRELOAD", ""),
    }
    if device.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
    return info


def git_revision(root: str | Path) -> str | None:
    """The checkout's ``HEAD`` commit (``-dirty`` with uncommitted changes to tracked
    files), or ``None`` outside a git checkout."""

    def git(*args: str) -> str:
        done = subprocess.run(
            ["git", *args], cwd=root, capture_output=True, text=True, check=True, timeout=10
        )
        return done.stdout.strip()

    try:
        head = git("rev-parse", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return None
    return head + ("-dirty" if dirty else "")
