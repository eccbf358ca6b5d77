"""The benchmark results document as ``bench.json`` and a Markdown table ``bench.md``."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sss2bathy.utils.atomic import atomic_write_text


def _fmt(value: float) -> str:
    if not math.isfinite(value):
        return str(value)
    a = abs(value)
    if a >= 1e6:
        return f"{value / 1e6:.3g} M"
    if a >= 1e4:
        return f"{value / 1e3:.3g} k"
    if a >= 100:
        return f"{value:.0f}"
    return f"{value:.3g}"


def to_markdown(doc: Mapping[str, Any]) -> str:
    """The results document as a Markdown table with a header and per-section notes."""
    m = doc["machine"]
    device = m.get("gpu") or f"{m['device']} ({m['torch_threads']} threads)"
    load0 = ", ".join(f"{v:.2f}" for v in doc["load_avg_start"])
    load1 = ", ".join(f"{v:.2f}" for v in doc.get("load_avg_end", doc["load_avg_start"]))
    lines = [
        "# sss2bathy benchmarks",
        "",
        f"{doc['created']} · mode `{doc['mode']}` · {m['cpu']} ({m['cpu_count']} cores) · "
        f"torch {m['torch']} · device {device} · load average {load0} -> {load1} · "
        f"{doc.get('seconds', 0):.0f} s",
        "",
        "Median of repeated runs after warm-up; spread = min - max and inter-quartile range.",
        "",
    ]
    others = doc.get("other_load_cores")
    if others is not None:
        lines[2] += f" · other processes used {others:.2f} cores meanwhile"
        if others > 0.25:
            lines += [
                f"**Warning:** other processes kept {others:.2f} of {m['cpu_count']} cores "
                "busy during the run: CPU timings are pessimistic and noisy.",
                "",
            ]
    lines += [
        "| Benchmark | Figure | Median | Unit | Min - max | IQR | n | Note |",
        "|---|---|---:|---|---|---|---:|---|",
    ]
    for section in doc["sections"].values():
        for f in section["figures"]:
            single = f["n"] == 1
            spread = "" if single else f"{_fmt(f['min'])} - {_fmt(f['max'])}"
            iqr = "" if single else f"{_fmt(f['q1'])} - {_fmt(f['q3'])}"
            lines.append(
                f"| {section['title']} | {f['name']} | {_fmt(f['median'])} | {f['unit']} | "
                f"{spread} | {iqr} | {f['n']} | {f['note']} |"
            )
    lines += ["", "Notes:", ""]
    for section in doc["sections"].values():
        lines.append(f"- **{section['title']}** ({section['seconds']:.0f} s): {section['notes']}")
    return "\n".join(lines) + "\n"


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, torch.Tensor | np.generic):
        return obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def write_report(doc: Mapping[str, Any], out_dir: str | Path) -> dict[str, Path]:
    """Write ``bench.json`` and ``bench.md`` under ``out_dir`` (atomically)."""
    out = Path(out_dir)
    paths = {"json": out / "bench.json", "markdown": out / "bench.md"}
    atomic_write_text(paths["json"], json.dumps(_jsonable(doc), indent=2) + "\n")
    atomic_write_text(paths["markdown"], to_markdown(doc))
    return paths
