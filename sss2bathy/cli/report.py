"""``sss2bathy-report``: gather the latest run of each experiment into ``outputs/report/``
(``index.html``, a self-contained web page, and ``index.md``).

sss2bathy-report                      # outputs/ -> outputs/report/
sss2bathy-report --outputs /scratch/outputs --out /tmp/report
"""

from __future__ import annotations

import argparse
import logging
import textwrap

from sss2bathy.cli._common import project_root, setup_environment


def main(argv: list[str] | None = None) -> None:
    setup_environment()
    parser = argparse.ArgumentParser(
        prog="sss2bathy-report",
        description=textwrap.fill(" ".join(__doc__.split("\n\n")[0].split()).replace("``", "")),
        epilog="examples:\n  sss2bathy-report\n  sss2bathy-report --outputs /scratch/outputs "
        "--out /tmp/report",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--outputs",
        default=str(project_root() / "outputs"),
        help="the outputs folder whose runs are gathered (default: %(default)s)",
    )
    parser.add_argument("--out", default=None, help="report folder (default OUTPUTS/report)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    from sss2bathy.eval.report import build_report

    path = build_report(args.outputs, args.out)
    print(f"report: {path.with_suffix('.html')} (web page) and {path}")


if __name__ == "__main__":
    main()
