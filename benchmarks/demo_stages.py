"""Section ``demo_stages``: the stage wall times of the last ``make demo``, read, not re-run.

The demo writes them to ``outputs/report/stage_times.json`` (``{"scale", "seconds":
{stage: s}}``).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from datetime import datetime, timezone
from pathlib import Path

from benchmarks.timing import figure

TITLE = "make demo stages"


def demo_stage_times(path: str | Path) -> dict:
    """The stage wall times of the last ``make demo`` (``stage_times.json``), as figures."""
    path = Path(path)
    if not path.is_file():
        return {
            "title": TITLE,
            "params": {"file": str(path)},
            "figures": [],
            "info": {"missing": True},
            "notes": f"{path} not found: run `make demo` first (not re-run here).",
        }
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(
            f"{path}: expected JSON stage times, found unreadable text ({err})"
        ) from err
    seconds = data.get("seconds") if isinstance(data, Mapping) else None
    if not isinstance(seconds, Mapping):
        raise ValueError(f"{path}: expected a 'seconds' mapping of stage times, found {data!r}")
    figures = [figure(str(stage), "s", float(t), "one run") for stage, t in seconds.items()]
    stamp = datetime.fromtimestamp(path.stat().st_mtime, timezone.utc).isoformat(timespec="seconds")
    return {
        "title": TITLE,
        "params": {"file": str(path), "scale": data.get("scale"), "written": stamp},
        "figures": figures,
        "info": {},
        "notes": f"wall times of each stage of the last `make demo` ({stamp}), read from {path}.",
    }
