"""``make bench``: measure the hot paths on this machine -> ``outputs/bench/bench.{json,md}``.

python -m benchmarks                      # full run (every section)
python -m benchmarks --quick              # short run (fewer repeats, smaller sizes)
python -m benchmarks --only finder,siren_step --device cpu
python -m benchmarks --root /path/to/checkout --out /tmp/bench

The project root (``conf/`` for the presets, ``outputs/`` for the demo's stage times and
the default output folder) is ``--root``, else ``$SSS2BATHY_ROOT``, else the current
directory. Sections and what each figure means: the modules of :mod:`benchmarks`.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch

from benchmarks import (
    cnn,
    demo_stages,
    draping,
    finder,
    projection,
    simulator,
    siren_step,
    windows,
)
from benchmarks.config import project_root
from benchmarks.machine import cpu_clock, git_revision, machine_info, other_load
from benchmarks.report import to_markdown, write_report
from benchmarks.timing import resolve_device

SECTIONS = ("siren_step", "finder", "cnn", "windows", "sim", "drape", "demo_stages")
SECTION_TITLES = {
    "siren_step": siren_step.TITLE,
    "finder": finder.TITLE,
    "cnn": cnn.TITLE,
    "windows": windows.TITLE,
    "sim": simulator.TITLE,
    "drape": draping.TITLE,
    "demo_stages": demo_stages.TITLE,
    "gpu_projection": projection.TITLE,
}
QUICK: dict[str, dict[str, Any]] = {
    "siren_step": {"warmup": 1, "repeats": 3, "mm_repeats": 2, "n_batches": 2},
    "finder": {"n_pings": 16, "warmup": 1, "repeats": 3, "gd_repeats": 2},
    "cnn": {"warmup": 1, "repeats": 3},
    "windows": {"n_lines": 4, "n_batches": 4, "warmup": 1, "repeats": 3},
    "sim": {"n_pings": 24, "warmup": 1, "repeats": 3},
    "drape": {"n_pings": 200, "warmup": 1, "repeats": 3},
}
FULL: dict[str, dict[str, Any]] = {
    "siren_step": {"warmup": 2, "repeats": 15, "mm_repeats": 5, "n_batches": 4},
    "finder": {"n_pings": 64, "warmup": 1, "repeats": 7, "gd_repeats": 3},
    "cnn": {"warmup": 1, "repeats": 5},
    "windows": {"warmup": 1, "repeats": 5},
    "sim": {"n_pings": 96, "warmup": 1, "repeats": 5},
    "drape": {"n_pings": 1000, "warmup": 1, "repeats": 5},
}
# CNN batch cap on a CPU (windows/s from a smaller batch than the paper's 64)
CPU_CNN_MAX_BATCH = {"quick": 2, "full": 4}


def _section_runner(
    name: str, device: torch.device, root: Path, mode: str, stage_times: Path
) -> Callable[..., dict]:
    """The function measuring section ``name``, called with the section's keyword args."""
    if name == "siren_step":
        return lambda **kw: siren_step.bench_siren_step(device=device, **kw)
    if name == "finder":
        return lambda **kw: finder.bench_finder(device=device, **kw)
    if name == "cnn":
        cap = {"max_batch": CPU_CNN_MAX_BATCH[mode]} if device.type == "cpu" else {}
        return lambda **kw: cnn.bench_cnn(device=device, root=root, **{**cap, **kw})
    if name == "windows":
        return lambda **kw: windows.bench_windows(device=device, **kw)
    if name == "sim":
        return lambda **kw: simulator.bench_sim(root=root, **kw)
    if name == "drape":
        return draping.bench_drape
    return lambda path=stage_times: demo_stages.demo_stage_times(path)


def run_benchmarks(
    only: Sequence[str] | None = None,
    quick: bool = False,
    device: str | torch.device | None = None,
    root: str | Path | None = None,
    stage_times: str | Path | None = None,
    overrides: Mapping[str, Mapping[str, Any]] | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict:
    """Run the chosen sections (default all) and return the results document.

    Args:
        only: section names among :data:`SECTIONS`; ``None`` = all.
        quick: the short sizes of :data:`QUICK` (else :data:`FULL`).
        device: ``"auto"``/``None`` (CUDA if present), ``"cpu"``, ``"cuda"``.
        root: the project root (:func:`benchmarks.config.project_root`).
        stage_times: the demo's ``stage_times.json`` (default
            ``<root>/outputs/report/stage_times.json``).
        overrides: per-section keyword arguments replacing the preset's.
        progress: called with a line per finished section.
    """
    names = list(SECTIONS) if only is None else list(only)
    unknown = sorted(set(names) - set(SECTIONS))
    if unknown or not names:
        raise ValueError(f"only: expected names among {SECTIONS}, found {names}")
    dev = resolve_device(device)
    mode = "quick" if quick else "full"
    preset = QUICK if quick else FULL
    overrides = overrides or {}
    base = project_root(root)
    stage_file = Path(stage_times) if stage_times else base / "outputs/report/stage_times.json"
    doc: dict[str, Any] = {
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "mode": mode,
        "machine": machine_info(dev),
        "load_avg_start": list(os.getloadavg()),
        "sections": {},
    }
    t_all = time.perf_counter()
    clock0 = cpu_clock()
    for name in names:
        kwargs = {**preset.get(name, {}), **overrides.get(name, {})}
        t0 = time.perf_counter()
        result = _section_runner(name, dev, base, mode, stage_file)(**kwargs)
        result["seconds"] = round(time.perf_counter() - t0, 2)
        doc["sections"][name] = result
        if progress is not None:
            progress(f"{name}: {result['seconds']:.1f} s")
    if "siren_step" in doc["sections"]:
        # derived, not measured: the paper-scale fit from the measured step
        proj = projection.projection_section(doc["sections"]["siren_step"])
        proj["seconds"] = 0.0
        doc["sections"]["gpu_projection"] = proj
    doc["seconds"] = round(time.perf_counter() - t_all, 2)
    doc["load_avg_end"] = list(os.getloadavg())
    doc["other_load_cores"] = other_load(clock0, cpu_clock())
    return doc


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--quick", action="store_true", help="short run (fewer repeats/sizes)")
    parser.add_argument(
        "--root",
        default=None,
        help="project root with conf/ (default: $SSS2BATHY_ROOT, else the current directory)",
    )
    parser.add_argument("--out", default=None, help="output folder (default: <root>/outputs/bench)")
    parser.add_argument(
        "--only", default=None, help=f"comma-separated sections among {','.join(SECTIONS)}"
    )
    parser.add_argument("--device", default="auto", help="auto (CUDA if present) | cpu | cuda")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument(
        "--stage-times",
        default=None,
        help="stage_times.json of a make demo (default: <root>/outputs/report/stage_times.json)",
    )
    args = parser.parse_args(argv)
    if args.only is not None:
        names = [n.strip() for n in args.only.split(",") if n.strip()]
        unknown = sorted(set(names) - set(SECTIONS))
        if unknown or not names:
            parser.error(f"--only: expected names among {','.join(SECTIONS)}, found {args.only!r}")
        args.only = names
    if args.threads is not None and args.threads < 1:
        parser.error(f"--threads: expected >= 1, found {args.threads}")
    try:
        args.root = project_root(args.root)
    except ValueError as err:
        parser.error(f"--{err}")
    return args


def main(argv: list[str] | None = None) -> int:
    """Run the benchmarks and write the report; a bad input (a ``ValueError`` naming it)
    ends with one ``error:`` line on stderr and exit status 2 (``HYDRA_FULL_ERROR=1``: the
    traceback, as the entry points do)."""
    args = parse_args(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    out = Path(args.out) if args.out else args.root / "outputs" / "bench"
    try:
        doc = run_benchmarks(
            only=args.only,
            quick=args.quick,
            device=args.device,
            root=args.root,
            stage_times=args.stage_times,
            progress=lambda line: print(line, file=sys.stderr, flush=True),
        )
    except ValueError as err:
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        print("error: " + " ".join(str(err).split()), file=sys.stderr, flush=True)
        return 2
    doc["machine"]["git"] = git_revision(args.root)
    paths = write_report(doc, out)
    print(to_markdown(doc))
    print(f"written: {paths['json']} and {paths['markdown']}", file=sys.stderr)
    return 0
