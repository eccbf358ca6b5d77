"""``make bench``: measure the hot paths on this machine -> ``outputs/bench/bench.{json,md}``.

python -m sss2bathy.cli.bench                      # full run (< 10 min on a 2-core CPU)
python -m sss2bathy.cli.bench --quick              # short run (< 2 min)
python -m sss2bathy.cli.bench --only finder,siren_step --device cpu

Sections and what each figure means: :mod:`sss2bathy.eval.bench`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sss2bathy.cli._common import git_revision, project_root
from sss2bathy.eval.bench import SECTIONS, run_benchmarks, to_markdown, write_report


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m sss2bathy.cli.bench", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--quick", action="store_true", help="short run (fewer repeats/sizes)")
    parser.add_argument(
        "--out", default=None, help="output folder (default: <project>/outputs/bench)"
    )
    parser.add_argument(
        "--only", default=None, help=f"comma-separated sections among {','.join(SECTIONS)}"
    )
    parser.add_argument("--device", default="auto", help="auto (CUDA if present) | cpu | cuda")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument(
        "--stage-times",
        default=None,
        help="stage_times.json of a make demo (default: outputs/report/stage_times.json)",
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
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    import torch

    if args.threads is not None:
        torch.set_num_threads(args.threads)
    root = project_root()
    out = Path(args.out) if args.out else root / "outputs" / "bench"
    stage_times = args.stage_times or root / "outputs" / "report" / "stage_times.json"
    doc = run_benchmarks(
        only=args.only,
        quick=args.quick,
        device=args.device,
        stage_times=stage_times,
        progress=lambda line: print(line, file=sys.stderr, flush=True),
    )
    doc["machine"]["git"] = git_revision()
    paths = write_report(doc, out)
    print(to_markdown(doc))
    print(f"written: {paths['json']} and {paths['markdown']}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
