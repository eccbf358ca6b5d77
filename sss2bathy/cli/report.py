"""``sss2bathy-report``: gather the latest run of each experiment into ``outputs/report/``
(``index.html``, a self-contained web page, and ``index.md``).

sss2bathy-report                      # outputs/ -> outputs/report/
sss2bathy-report --outputs /scratch/outputs --out /tmp/report
sss2bathy-report --publish            # also docs/results.md and the README's results
sss2bathy-report outputs/runs/map/RUN  # one sss2bathy-map run -> RUN/report.html
"""

from __future__ import annotations

import argparse
import logging
import sys
import textwrap

from sss2bathy.cli._common import config_dir, project_root, setup_environment


def main(argv: list[str] | None = None) -> None:
    setup_environment()
    parser = argparse.ArgumentParser(
        prog="sss2bathy-report",
        description=textwrap.fill(" ".join(__doc__.split("\n\n")[0].split()).replace("``", "")),
        epilog="examples:\n  sss2bathy-report\n  sss2bathy-report --outputs /scratch/outputs "
        "--out /tmp/report\n  sss2bathy-report --publish",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--outputs",
        default=str(project_root() / "outputs"),
        help="the outputs folder whose runs are gathered (default: %(default)s)",
    )
    parser.add_argument("--out", default=None, help="report folder (default OUTPUTS/report)")
    parser.add_argument(
        "--publish",
        action="store_true",
        help="then write the results into docs/ (results.json, results.md, figures) and the "
        "README's results block (make results)",
    )
    parser.add_argument(
        "run",
        nargs="?",
        default=None,
        help="a sss2bathy-map run folder: its report.html (map, mosaic, uncertainty, verdict, "
        "import warnings, settings) instead of the experiments' report",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    if args.run is not None:
        from sss2bathy.eval.map_report import write_map_report

        try:
            page = write_map_report(args.run)
        except ValueError as err:
            print(f"sss2bathy-report: {err}", file=sys.stderr)
            raise SystemExit(2) from None
        print(f"report: {page} (web page)")
        return
    from sss2bathy.eval.report import build_report

    path = build_report(args.outputs, args.out, config_dir())
    print(f"report: {path.with_suffix('.html')} (web page) and {path}")
    if args.publish:
        from sss2bathy.eval.results import publish

        root = project_root()
        try:
            written = publish(path.parent, root / "docs", root / "README.md")
        except (OSError, ValueError) as err:
            print(f"sss2bathy-report: {err}", file=sys.stderr)
            raise SystemExit(2) from None
        print("published: " + ", ".join(str(p.relative_to(root)) for p in written))


if __name__ == "__main__":
    main()
