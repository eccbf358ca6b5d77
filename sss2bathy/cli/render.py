"""``sss2bathy-render``: pictures of a survey folder.

    sss2bathy-render waterfall --survey data/synthetic_d1_demo --line line_002 --out wf.png
    sss2bathy-render terrain --survey data/synthetic_d1_demo --out terrain.png

Each subcommand is one entry of :data:`SUBCOMMANDS` (its arguments and its action), so a
new picture is one function pair away.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from pathlib import Path


def _load(folder: str):
    from sss2bathy.survey import Survey

    return Survey.load(Path(folder))


def _waterfall_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--survey", required=True, help="survey folder (holds survey.yaml)")
    p.add_argument("--line", required=True, help="line name (see survey.yaml)")
    p.add_argument("--out", required=True, help="output PNG")
    p.add_argument("--pings", nargs=2, type=int, metavar=("START", "STOP"), help="ping interval")
    p.add_argument("--no-truth", action="store_true", help="intensity only, no ground truth")
    p.add_argument("--clip-percentile", type=float, default=99.5)


def _waterfall(args: argparse.Namespace) -> Path:
    from sss2bathy.sim.render import render_waterfall

    survey = _load(args.survey)
    try:
        line = survey.line(args.line)
    except KeyError:
        names = ", ".join(ln.name for ln in survey.lines)
        raise SystemExit(f"--line: expected one of {names}, found {args.line!r}") from None
    return render_waterfall(
        line,
        args.out,
        truth=not args.no_truth,
        clip_percentile=args.clip_percentile,
        pings=tuple(args.pings) if args.pings else None,
    )


def _terrain_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--survey", required=True, help="survey folder (holds survey.yaml)")
    p.add_argument("--out", required=True, help="output PNG")


def _terrain(args: argparse.Namespace) -> Path:
    from sss2bathy.sim.render import render_terrain

    return render_terrain(_load(args.survey), args.out)


#: name -> (help, add its arguments, run it and return the written file)
SUBCOMMANDS: dict[
    str, tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], Path]]
] = {
    "waterfall": (
        "a line's waterfall (port mirrored left of starboard)",
        _waterfall_args,
        _waterfall,
    ),
    "terrain": ("the MBES grid, hillshaded, with the survey lines", _terrain_args, _terrain),
}


EXAMPLES = """examples:
  sss2bathy-render waterfall --survey data/synthetic_d1_demo --line line_002 --out wf.png
  sss2bathy-render terrain --survey data/synthetic_d1_demo --out terrain.png"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sss2bathy-render",
        description=__doc__.split("\n")[0].replace("``", ""),
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name, (help_text, add_args, run) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        add_args(p)
        p.set_defaults(run=run)
    return parser


def main(argv: Sequence[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    path = args.run(args)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
