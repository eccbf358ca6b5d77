"""Overlap study: does the off-track overlap score agree with the MBES where the nadir verdict cannot?

    .venv/bin/python -m studies.overlap_study --scale tiny --seeds 1 2 3
    .venv/bin/python -m studies.overlap_study --scale demo --seeds 1 2 3 --out outputs/verdict_study_demo

Per seed, on the verdict study's generated overlapping AUV survey
(:func:`studies.xtf_study.make_survey`, no MBES given to the fit):

1. the verdict study's runs (:func:`studies.xtf_study.run_verdict_study`, reused from
   ``--out`` when finished): ``sss2bathy-map`` with ``verdict.folds=K`` (the nadir K-fold
   verdict on held-out altimeter blocks) and a heights-only map, both final maps scored
   against the simulated MBES; *truth* = ``better`` when the sidescan map's MBES MAE is the
   lower;
2. one more ``sss2bathy-map`` run with ``verdict.overlap.enabled=true verdict.folds=0``:
   the leave-one-line-out overlap score (:mod:`sss2bathy.eval.overlap`, ``overlap.json``):
   each overlapping line held out in turn, the sidescan fit and heights-only fitted from the
   other lines and scored at the held-out line's altimeter points inside their swath
   footprint, off their tracks.

Each verdict's call against heights-only is set against the truth: *agrees* (a conclusive
call equal to the truth's; blank when inconclusive) and *sign agrees* (the sign of the mean
paired difference, sidescan - heights-only, says the truth's answer, conclusive or not).
Writes ``<out>/overlap_study.md`` and ``.csv`` after every seed; one fit at a time, one torch
thread.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from studies.tables import fmt_cell, markdown_table, to_csv, write_tables
from studies.xtf_study import make_survey, map_command, run_map, run_verdict_study, verdict_call

log = logging.getLogger("sss2bathy.overlap_study")

HEIGHTS_ONLY = "siren_heights_only"
COLUMNS = (
    "seed",
    "nadir_call",
    "nadir_diff_m",
    "nadir_half_m",
    "overlap_call",
    "overlap_diff_m",
    "overlap_half_m",
    "overlap_vs_plane",
    "overlap_lines",
    "overlap_points",
    "overlap_mae_sidescan",
    "overlap_mae_heights",
    "overlap_mae_plane",
    "mbes_mae_sidescan",
    "mbes_mae_heights",
    "truth",
    "nadir_agrees",
    "overlap_agrees",
    "nadir_sign_agrees",
    "overlap_sign_agrees",
    "wall_s",
    "run",
)


def _agrees(call: str, truth: str) -> bool | None:
    """A conclusive call against the truth; None when either is not conclusive."""
    if call not in ("better", "worse") or truth not in ("better", "worse"):
        return None
    return call == truth


def _sign_agrees(diff: float, truth: str) -> bool | None:
    """Whether the mean paired difference (sidescan - heights-only) points the truth's way
    (negative: better); None when it is 0 or not finite or the truth unknown."""
    if not math.isfinite(diff) or diff == 0.0 or truth not in ("better", "worse"):
        return None
    return (diff < 0) == (truth == "better")


def overlap_row(
    nadir: Mapping[str, Any], overlap: Mapping[str, Any], run: str = "", wall_s: float = math.nan
) -> dict[str, Any]:
    """One table row: the verdict study's row ``nadir``
    (:func:`studies.xtf_study.verdict_row`) and an ``overlap.json``
    (:meth:`sss2bathy.eval.overlap.OverlapResult.to_dict`).

    Raises:
        ValueError: ``overlap`` records no overlap score (its reason quoted).
    """
    if not overlap.get("computable", False):
        raise ValueError(f"overlap.json: expected an overlap score, found {overlap.get('reason')}")
    vh = verdict_call(overlap, HEIGHTS_ONLY)
    vp = verdict_call(overlap, "plane")
    methods = overlap.get("methods") or {}
    mean = lambda name: float((methods.get(name) or {}).get("mean", math.nan))  # noqa: E731
    truth = str(nadir["truth"])
    return {
        "seed": int(nadir["seed"]),
        "nadir_call": nadir["vs_heights"],
        "nadir_diff_m": float(nadir["diff_heights_m"]),
        "nadir_half_m": float(nadir["half_heights_m"]),
        "overlap_call": vh["call"],
        "overlap_diff_m": vh["diff"],
        "overlap_half_m": vh["half"],
        "overlap_vs_plane": vp["call"],
        "overlap_lines": int(overlap.get("folds") or 0),
        "overlap_points": int(overlap.get("n_points") or 0),
        "overlap_mae_sidescan": mean(str(overlap.get("subject"))),
        "overlap_mae_heights": mean(HEIGHTS_ONLY),
        "overlap_mae_plane": mean("plane"),
        "mbes_mae_sidescan": float(nadir["map_mae_sidescan"]),
        "mbes_mae_heights": float(nadir["map_mae_heights"]),
        "truth": truth,
        "nadir_agrees": _agrees(str(nadir["vs_heights"]), truth),
        "overlap_agrees": _agrees(vh["call"], truth),
        "nadir_sign_agrees": _sign_agrees(float(nadir["diff_heights_m"]), truth),
        "overlap_sign_agrees": _sign_agrees(vh["diff"], truth),
        "wall_s": float(wall_s),
        "run": run,
    }


def agreement(rows: Sequence[Mapping[str, Any]], key: str) -> tuple[int, int]:
    """``(agree, decided)``: rows whose ``key`` is True, and rows where it is not None."""
    decided = [r[key] for r in rows if r.get(key) is not None]
    return sum(bool(v) for v in decided), len(decided)


def to_markdown(rows: Sequence[Mapping[str, Any]], command: str = "") -> str:
    """The study's table and its agreement counts."""
    pm = lambda d, h: f"{d:+.3f} +- {h:.3f}" if math.isfinite(h) else f"{d:+.3f}"  # noqa: E731
    yes = lambda v: "" if v is None else ("yes" if v else "no")  # noqa: E731
    header = (
        "seed", "nadir vs heights-only", "nadir diff (m)", "overlap vs heights-only",
        "overlap diff (m)", "overlap vs plane", "held-out lines", "points",
        "overlap MAE sidescan / heights / plane (m)", "MBES MAE sidescan / heights (m)",
        "truth", "nadir agrees", "overlap agrees", "nadir sign", "overlap sign",
    )  # fmt: skip
    body = [
        (
            r["seed"],
            r["nadir_call"],
            pm(r["nadir_diff_m"], r["nadir_half_m"]),
            r["overlap_call"],
            pm(r["overlap_diff_m"], r["overlap_half_m"]),
            r["overlap_vs_plane"],
            r["overlap_lines"],
            r["overlap_points"],
            " / ".join(
                f"{r[k]:.3f}"
                for k in ("overlap_mae_sidescan", "overlap_mae_heights", "overlap_mae_plane")
            ),
            f"{r['mbes_mae_sidescan']:.3f} / {r['mbes_mae_heights']:.3f}",
            r["truth"],
            yes(r["nadir_agrees"]),
            yes(r["overlap_agrees"]),
            yes(r["nadir_sign_agrees"]),
            yes(r["overlap_sign_agrees"]),
        )  # fmt: skip
        for r in rows
    ]
    counts = {k: agreement(rows, k) for k in (
        "nadir_agrees", "overlap_agrees", "nadir_sign_agrees", "overlap_sign_agrees")}  # fmt: skip
    text = [
        "# Overlap study",
        "",
        "nadir = the K-fold verdict on held-out altimeter blocks (under the vehicle); overlap "
        "= the leave-one-line-out overlap score (each line held out in turn, the map fitted "
        "from the other lines, scored at the held-out line's altimeter points inside their "
        "swath footprint, off their tracks). diff = mean paired MAE difference, sidescan - "
        "heights-only (m), +- its 95 % half-width; calls better / worse / inconclusive. "
        "truth = better when the sidescan map's MAE against the simulated MBES is the lower "
        "(the final maps on every line). agrees = a conclusive call equal to the truth "
        "(blank: inconclusive); sign = the sign of diff points the truth's way.",
        "",
        *(f"    {command}" for command in [command] if command),
        *([""] if command else []),
        *markdown_table(header, body, align="rlrlrlrrrrlllll"),
        "",
        "Agreement with the MBES: "
        + "; ".join(
            f"{label} {counts[k][0]} of {counts[k][1]}"
            for label, k in (
                ("nadir verdict (conclusive calls)", "nadir_agrees"),
                ("overlap score (conclusive calls)", "overlap_agrees"),
                ("nadir sign", "nadir_sign_agrees"),
                ("overlap sign", "overlap_sign_agrees"),
            )
        )
        + f" (of {len(rows)} surveys).",
        "",
    ]
    return "\n".join(text)


def run_overlap_study(
    out_dir: str | Path,
    seeds: Sequence[int],
    scale: str = "tiny",
    folds: int = 5,
    method: str = "siren_lambert",
    min_points: int = 10,
    rerun: bool = False,
    command: str = "",
) -> list[dict[str, Any]]:
    """The study (module docstring): rows in seed order; finished runs reused unless
    ``rerun``; tables rewritten after every seed."""
    out = Path(out_dir).resolve()
    rows: list[dict[str, Any]] = []
    for seed in seeds:
        # the nadir verdict's runs carry no overlap score: that is the run below
        (nadir,) = run_verdict_study(
            out, [seed], scale, folds, method,
            map_args=["verdict.overlap.enabled=false"], rerun=rerun,
        )  # fmt: skip
        survey = make_survey(out / "xtf" / f"s{int(seed)}", int(seed), scale=scale)
        run_dir = out / "runs" / f"s{int(seed)}" / f"{method}_overlap"
        if rerun or not (run_dir / "overlap.json").is_file():
            cmd = map_command(
                survey, method, "demo", seed, run_dir, out / "data", scale,
                map_args=[
                    "holdout.fraction=0", "verdict.overlap.enabled=true",
                    f"verdict.overlap.min_points={int(min_points)}", "mosaic.placement=none",
                ],
                verdict_folds=0,
            )  # fmt: skip
            log.info("seed %s overlap: %s", seed, " ".join(cmd))
            run_map(cmd, run_dir)
        wall_path = run_dir / "study_wall_s.txt"
        wall = float(wall_path.read_text()) if wall_path.is_file() else math.nan
        overlap = json.loads((run_dir / "overlap.json").read_text())
        row = overlap_row(nadir, overlap, str(run_dir), wall)
        log.info("%s", row)
        rows.append(row)
        csv_rows = [{k: fmt_cell(r[k]) if r[k] is not None else "" for k in COLUMNS} for r in rows]
        write_tables(out, "overlap_study", to_markdown(rows, command), to_csv(csv_rows, COLUMNS))
    return rows


def main(argv: list[str] | None = None) -> int:
    """``python -m studies.overlap_study [--scale tiny|demo] [--seeds ...] [--out DIR]``."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default=None, help="default outputs/verdict_study (tiny) or _<scale>")
    p.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    p.add_argument("--scale", default="tiny", help="survey and SIREN scale (tiny | demo)")
    p.add_argument("--folds", type=int, default=5, help="the nadir verdict's verdict.folds")
    p.add_argument("--method", default="siren_lambert")
    p.add_argument("--min-points", type=int, default=10, help="verdict.overlap.min_points")
    p.add_argument("--rerun", action="store_true", help="refit runs that already finished")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    out = args.out or (
        "outputs/verdict_study" if args.scale == "tiny" else f"outputs/verdict_study_{args.scale}"
    )
    command = "python -m studies.overlap_study " + " ".join(
        argv if argv is not None else sys.argv[1:]
    )
    try:
        rows = run_overlap_study(
            out, args.seeds, args.scale, args.folds, args.method, args.min_points,
            rerun=args.rerun, command=command.strip(),
        )  # fmt: skip
    except (RuntimeError, ValueError, FileNotFoundError) as exc:
        print(f"overlap_study: {exc}", file=sys.stderr)
        return 1
    print(to_markdown(rows))
    print(f"written: {Path(out) / 'overlap_study.md'}, {Path(out) / 'overlap_study.csv'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
