"""XTF study: does the sidescan beat interpolating the altimeter on an AUV survey without MBES?

Measured on generated AUV-like XTF surveys:

1. :func:`make_survey` simulates ``synthetic_d1`` (``plan.mount=auv``, constant altitude) at
   a scale, seeded, and writes the lines of one split to XTF with :func:`write_xtf`, after
   zeroing (0 m) or blanking (NaN) the altitude of a few short runs of pings so the
   importer's first-bottom-return detector has to repair them. The simulator's true
   altitude of every ping goes to ``truth.npz`` beside the files.
2. :func:`run_map` runs ``sss2bathy-map`` (one process, one fit at a time) for each method,
   schedule variant and seed, holding out blocks of altimeter points.
3. :func:`study_row` scores a finished run: held-out altimeter MAE of the map, that of
   along-track interpolation of the kept altimeter points, their ratio, the lines' overlap
   (:func:`swath_overlap`, from the imported lines) and the altitude repairs against the
   truth (:func:`repair_errors`); :func:`to_markdown` / :func:`to_csv` write the table.
4. ``--verdict-folds K`` (:func:`run_verdict_study`): does ``sss2bathy-map``'s K-fold verdict
   (:mod:`sss2bathy.eval.verdict`) agree with the MBES? Per seed the sidescan method with
   ``verdict.folds=K`` (the verdict and its final map) and a heights-only map, both scored
   against the simulated MBES grid on the same cells (:func:`score_maps_on_truth`); the
   verdict's sidescan-vs-heights-only call against the MBES's (:func:`verdict_agreement`),
   in ``verdict_study.md`` / ``.csv``.

Seed ``s`` is the survey's simulation seed *and* the fit's seed (its held-out blocks and
SIREN initialisation), so every seed is a new survey. Choose settings on a seed that the
table does not report (e.g. 0) and report on others. Variants with
``model.select_best=holdout_alt_mae`` choose the final map *by* the held-out MAE, so their
held-out MAE is optimistic; the table marks them.

    python -m studies.xtf_study --seeds 1 2 3 --out outputs/xtf_study
    python -m studies.xtf_study --cnn-checkpoint outputs/runs/cnn/<run>/checkpoints/last.ckpt
    make xtf-study [CKPT=...] [ARGS=...]
    python -m studies.xtf_study --verdict-folds 5 --scale tiny --seeds 1 2 3
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from scipy.spatial import cKDTree

from sss2bathy.io.xtf import write_xtf
from sss2bathy.metrics.bathy import MAP_TAGS
from sss2bathy.sim.config import SyntheticSurveyConfig
from sss2bathy.sim.generate import generate_survey
from sss2bathy.survey.grid import BathyGrid
from sss2bathy.survey.model import (
    ALTITUDE_DETECTED,
    ALTITUDE_INTERPOLATED,
    ALTITUDE_MISSING,
    Survey,
)
from sss2bathy.utils.atomic import atomic_path, atomic_write_text
from studies.tables import to_csv as to_csv_table
from studies.tables import write_tables

log = logging.getLogger("sss2bathy.xtf_study")

CONF = Path(__file__).resolve().parents[1] / "conf"
TRUTH_FILE = "truth.npz"

# variant -> extra sss2bathy-map arguments (the SIREN schedule); "demo" = the scale's own
VARIANTS: dict[str, tuple[str, ...]] = {
    "demo": (),
    "fast": ("siren_schedule=fast",),
    "fast_best": ("siren_schedule=fast",),
}
# variant -> extra sss2bathy-train overrides (through sss2bathy-map's overrides=[...])
VARIANT_OVERRIDES: dict[str, tuple[str, ...]] = {
    "demo": (),
    "fast": (),
    "fast_best": ("model.select_best=holdout_alt_mae", "model.eval_every_n_epochs=1"),
}
# variants whose final map is chosen by the held-out MAE (reported, but optimistic)
SELECTED_ON_HOLDOUT = frozenset({"fast_best"})
METHOD_LABEL = {
    "siren_lambert": "SIREN-Lambert",
    "siren_heights_only": "SIREN heights-only",
    "siren_cnn_n2d": "SIREN-CNN-N2d",
}
COLUMNS = (
    "method",
    "variant",
    "seed",
    "holdout_mae",
    "interp_mae",
    "ratio",
    "holdout_n",
    "overlap",
    "repair_n",
    "repair_max_m",
    "repair_median_m",
    "wall_s",
    "run",
)


# ---------------------------------------------------------------- pure parts


def swath_overlap(
    tracks: Sequence[np.ndarray],
    half_widths: Sequence[np.ndarray],
    cell_m: float = 1.0,
) -> dict[str, float]:
    """Share of the surveyed ground seen by at least 2 (and 3) lines.

    A cell (``cell_m`` squares over the tracks' bounding box, padded by the widest swath)
    is seen by a line when its horizontal distance to the line's nearest ping is within
    that ping's ground half-width (``sqrt(max_range**2 - altitude**2)`` on flat ground).

    Args:
        tracks: per line ``(P, 2)`` horizontal ping positions (m).
        half_widths: per line ``(P,)`` ground half-width of each ping's swath (m); NaN = the
            ping sees nothing.

    Returns:
        ``{"covered_m2", "overlap", "overlap3"}``: covered area, and the shares of it seen
        by >= 2 and >= 3 lines (NaN with nothing covered).
    """
    if len(tracks) != len(half_widths):
        raise ValueError(
            f"half_widths: expected one array per track ({len(tracks)}), found {len(half_widths)}"
        )
    if float(cell_m) <= 0:
        raise ValueError(f"cell_m: expected a positive cell size, found {cell_m}")
    pts, hws = [], []
    for i, (xy, hw) in enumerate(zip(tracks, half_widths, strict=True)):
        xy = np.asarray(xy, np.float64)
        hw = np.asarray(hw, np.float64)
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise ValueError(f"tracks[{i}]: expected shape (P, 2), found {xy.shape}")
        if hw.shape != (len(xy),):
            raise ValueError(f"half_widths[{i}]: expected shape ({len(xy)},), found {hw.shape}")
        ok = np.isfinite(hw) & np.isfinite(xy).all(axis=1)
        pts.append(xy[ok])
        hws.append(hw[ok])
    if not any(len(p) for p in pts):
        return {"covered_m2": 0.0, "overlap": math.nan, "overlap3": math.nan}
    pad = max(float(h.max()) for h in hws if len(h))
    allp = np.concatenate([p for p in pts if len(p)])
    lo, hi = allp.min(axis=0) - pad, allp.max(axis=0) + pad
    xs = np.arange(lo[0], hi[0] + cell_m, cell_m)
    ys = np.arange(lo[1], hi[1] + cell_m, cell_m)
    xx, yy = np.meshgrid(xs, ys)
    query = np.stack([xx.ravel(), yy.ravel()], axis=1)
    count = np.zeros(len(query), np.int32)
    for p, h in zip(pts, hws, strict=True):
        if not len(p):
            continue
        d, idx = cKDTree(p).query(query)
        count += d <= h[idx]
    covered = count >= 1
    n = int(covered.sum())
    if n == 0:
        return {"covered_m2": 0.0, "overlap": math.nan, "overlap3": math.nan}
    return {
        "covered_m2": n * float(cell_m) ** 2,
        "overlap": float((count >= 2).sum() / n),
        "overlap3": float((count >= 3).sum() / n),
    }


def ground_half_width(max_range_m: float, altitude_m: np.ndarray) -> np.ndarray:
    """``(P,)`` flat-ground half-width of a swath, ``sqrt(r**2 - a**2)``; NaN where the
    altitude is missing or beyond the range."""
    a = np.asarray(altitude_m, np.float64)
    r2 = float(max_range_m) ** 2
    with np.errstate(invalid="ignore"):
        hw = np.sqrt(r2 - a * a)
    return np.where(np.isfinite(a) & (a < float(max_range_m)), hw, np.nan)


def repair_errors(
    altitude_m: np.ndarray, source: np.ndarray, truth_m: np.ndarray
) -> dict[str, float]:
    """Error of the importer's altitude repairs against the true altitude.

    Args:
        altitude_m: ``(P,)`` imported altitude.
        source: ``(P,)`` its ``altitude_source`` codes (``sss2bathy.survey.model``).
        truth_m: ``(P,)`` true altitude.

    Returns:
        ``{"n", "detected", "interpolated", "missing", "max", "median"}``: repaired pings
        (detected or interpolated between detected ones) and their absolute error's max and
        median (NaN without repairs); ``missing`` = pings left without an altitude.
    """
    alt = np.asarray(altitude_m, np.float64)
    src = np.asarray(source)
    truth = np.asarray(truth_m, np.float64)
    if not alt.shape == src.shape == truth.shape or alt.ndim != 1:
        raise ValueError(
            "altitude_m, source, truth_m: expected equal 1-D shapes, found "
            f"{alt.shape}, {src.shape} and {truth.shape}"
        )
    repaired = (src == ALTITUDE_DETECTED) | (src == ALTITUDE_INTERPOLATED)
    err = np.abs(alt[repaired] - truth[repaired])
    return {
        "n": int(repaired.sum()),
        "detected": int((src == ALTITUDE_DETECTED).sum()),
        "interpolated": int((src == ALTITUDE_INTERPOLATED).sum()),
        "missing": int((src == ALTITUDE_MISSING).sum()),
        "max": float(err.max()) if err.size else math.nan,
        "median": float(np.median(err)) if err.size else math.nan,
    }


def dropout_pings(n_pings: int, runs: int, run_pings: int, seed: int) -> np.ndarray:
    """``(P,)`` bool: ``runs`` non-overlapping runs of ``run_pings`` pings whose altitude is
    removed, seeded, away from the line's first and last ``run_pings`` pings."""
    n, runs, length = int(n_pings), int(runs), int(run_pings)
    out = np.zeros(n, bool)
    if runs <= 0:
        return out
    slots = (n - 2 * length) // (2 * length)
    if length < 1 or slots < runs:
        raise ValueError(
            f"dropout: expected room for {runs} runs of {length} pings in a line, found "
            f"{n_pings} pings"
        )
    for k in np.random.default_rng(int(seed)).choice(slots, size=runs, replace=False):
        start = length + 2 * length * int(k)
        out[start : start + length] = True
    return out


def _ratio(fit: float, interp: float) -> float:
    return fit / interp if math.isfinite(fit) and math.isfinite(interp) and interp > 0 else math.nan


def _f(value: Any, fmt: str = ".3f") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return format(value, fmt) if isinstance(value, float) else str(value)


def summarise(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Per method and variant: seeds, mean held-out / interpolation MAE, mean and max ratio,
    how many seeds beat interpolation, in first-appearance order."""
    groups: dict[tuple[str, str], list[Mapping[str, Any]]] = {}
    for r in rows:
        groups.setdefault((str(r["method"]), str(r["variant"])), []).append(r)
    out = []
    for (method, variant), rs in groups.items():
        ratios = np.array([float(r["ratio"]) for r in rs], float)
        fits = np.array([float(r["holdout_mae"]) for r in rs], float)
        interps = np.array([float(r["interp_mae"]) for r in rs], float)
        ok = np.isfinite(ratios)
        out.append(
            {
                "method": method,
                "variant": variant,
                "seeds": len(rs),
                "holdout_mae": float(fits[ok].mean()) if ok.any() else math.nan,
                "interp_mae": float(interps[ok].mean()) if ok.any() else math.nan,
                "ratio_mean": float(ratios[ok].mean()) if ok.any() else math.nan,
                "ratio_max": float(ratios[ok].max()) if ok.any() else math.nan,
                "beats": int((ratios[ok] < 1).sum()),
            }
        )
    return out


def to_markdown(rows: Sequence[Mapping[str, Any]], title: str = "XTF study") -> str:
    """Markdown of the study rows: a per-run table and a per-method/variant summary."""
    md = [
        f"# {title}",
        "",
        "Generated AUV-like XTF surveys (synthetic_d1, constant altitude, no MBES), one per "
        "seed; `sss2bathy-map` fits on all the sidescan and the kept altimeter points. "
        "held-out = MAE (m) of the map at the held-out altimeter points; interp = the same "
        "for along-track linear interpolation of the kept altimeter; ratio < 1: the fit "
        "beats interpolation. overlap = share of the covered ground seen by >= 2 lines. "
        "repair = |imported - true| altitude (m) over the pings whose altitude came from "
        "the first-bottom-return detector. Variants marked * choose the final map by the "
        "held-out MAE itself (optimistic).",
        "",
        "| method | variant | seed | held-out (m) | interp (m) | ratio | points | overlap "
        "| repaired | repair max (m) | repair median (m) | wall (s) |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        variant = str(r["variant"]) + ("*" if r["variant"] in SELECTED_ON_HOLDOUT else "")
        md.append(
            "| "
            + " | ".join(
                [
                    METHOD_LABEL.get(str(r["method"]), str(r["method"])),
                    variant,
                    str(r["seed"]),
                    _f(r["holdout_mae"]),
                    _f(r["interp_mae"]),
                    _f(r["ratio"], ".2f"),
                    _f(r["holdout_n"], ".0f") if r["holdout_n"] is not None else "-",
                    _f(r["overlap"] * 100, ".0f") + " %" if math.isfinite(r["overlap"]) else "-",
                    str(r["repair_n"]),
                    _f(r["repair_max_m"]),
                    _f(r["repair_median_m"]),
                    "failed" if str(r["run"]).startswith("FAILED") else _f(r["wall_s"], ".0f"),
                ]
            )
            + " |"
        )
    md += [
        "",
        "| method | variant | seeds | mean held-out (m) | mean interp (m) | mean ratio "
        "| worst ratio | seeds beating interp |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for s in summarise(rows):
        variant = s["variant"] + ("*" if s["variant"] in SELECTED_ON_HOLDOUT else "")
        md.append(
            f"| {METHOD_LABEL.get(s['method'], s['method'])} | {variant} | {s['seeds']} "
            f"| {_f(s['holdout_mae'])} | {_f(s['interp_mae'])} | {_f(s['ratio_mean'], '.2f')} "
            f"| {_f(s['ratio_max'], '.2f')} | {s['beats']}/{s['seeds']} |"
        )
    return "\n".join(md) + "\n"


def to_csv(rows: Sequence[Mapping[str, Any]]) -> str:
    """CSV of the study rows (:data:`COLUMNS`)."""
    return to_csv_table(rows, COLUMNS, ignore_extra=True)


def write_table(rows: Sequence[Mapping[str, Any]], out_dir: str | Path) -> dict[str, Path]:
    """``xtf_study.md`` and ``xtf_study.csv`` under ``out_dir``."""
    return write_tables(out_dir, "xtf_study", to_markdown(rows), to_csv(rows))


# ---------------------------------------------------------------- verdict against the MBES

VERDICT_COLUMNS = (
    "seed",
    "vs_heights",
    "diff_heights_m",
    "half_heights_m",
    "vs_interp",
    "diff_interp_m",
    "half_interp_m",
    "outcome",
    "map_mae_sidescan",
    "map_mae_heights",
    "truth",
    "agrees",
    "region_mae_sidescan",
    "region_mae_heights",
    "bias_sidescan",
    "bias_heights",
    "n_cells",
    "folds",
    "block_m",
    "wall_s",
    "run",
)


def verdict_call(verdict: Mapping[str, Any], baseline: str) -> dict[str, Any]:
    """The subject-against-``baseline`` comparison of a ``verdict.json``
    (:meth:`sss2bathy.eval.verdict.KFoldVerdict.to_dict`): ``call`` = ``"better"`` (the
    subject wins), ``"worse"`` (the baseline wins) or ``"inconclusive"``, ``diff`` = mean
    of ``MAE_subject - MAE_baseline`` (m) and ``half`` = its 95 % half-width (m).

    Raises:
        ValueError: no comparison with ``baseline`` in the verdict.
    """
    subject = verdict.get("subject")
    for c in verdict.get("comparisons") or []:
        if c.get("a") == subject and c.get("b") == baseline:
            winner = c.get("winner")
            call = "inconclusive" if winner is None else "better" if winner == subject else "worse"
            return {
                "call": call,
                "diff": float(c.get("mean_diff", math.nan)),
                "half": float(c.get("half_width_95", math.nan)),
            }
    found = [c.get("b") for c in verdict.get("comparisons") or []]
    raise ValueError(
        f"verdict: expected a comparison of {subject!r} with {baseline!r}, found {found}"
    )


def truth_call(mae_sidescan: float, mae_heights: float) -> str:
    """The MBES's answer: ``"better"`` when the sidescan map's MAE is the lower, ``"worse"``
    when it is not, ``"unknown"`` when either is not finite."""
    if not (math.isfinite(mae_sidescan) and math.isfinite(mae_heights)):
        return "unknown"
    return "better" if mae_sidescan < mae_heights else "worse"


def verdict_agreement(rows: Sequence[Mapping[str, Any]]) -> dict[str, int]:
    """How often the verdict's sidescan-vs-heights-only call (``vs_heights``) matches the
    MBES's (``truth``): ``conclusive`` = rows with a better/worse call and a known truth,
    ``agree`` = those whose call is the truth's, ``inconclusive`` and ``n`` = all rows."""
    conclusive = [
        r
        for r in rows
        if r.get("vs_heights") in ("better", "worse") and r.get("truth") in ("better", "worse")
    ]
    return {
        "n": len(rows),
        "conclusive": len(conclusive),
        "agree": sum(r["vs_heights"] == r["truth"] for r in conclusive),
        "inconclusive": sum(r.get("vs_heights") == "inconclusive" for r in rows),
    }


def verdict_row(
    seed: int,
    verdict: Mapping[str, Any],
    scores: Mapping[str, Mapping[str, float]],
    run: str = "",
    wall_s: float = math.nan,
) -> dict[str, Any]:
    """One row of the verdict study: the verdict's calls (``verdict.json``) and the two final
    maps' scores against the MBES (``scores``: ``{"sidescan"|"heights": {"mae",
    "region_mae", "bias", "n_cells"}}``, :func:`score_maps_on_truth`)."""
    vh = verdict_call(verdict, "siren_heights_only")
    vi = verdict_call(verdict, "interpolation")
    side, heights = scores["sidescan"], scores["heights"]
    truth = truth_call(float(side["mae"]), float(heights["mae"]))
    conclusive = vh["call"] != "inconclusive" and truth != "unknown"
    return {
        "seed": int(seed),
        "vs_heights": vh["call"],
        "diff_heights_m": vh["diff"],
        "half_heights_m": vh["half"],
        "vs_interp": vi["call"],
        "diff_interp_m": vi["diff"],
        "half_interp_m": vi["half"],
        "outcome": str(verdict.get("outcome")),
        "map_mae_sidescan": float(side["mae"]),
        "map_mae_heights": float(heights["mae"]),
        "truth": truth,
        "agrees": (vh["call"] == truth) if conclusive else None,
        "region_mae_sidescan": float(side.get("region_mae", math.nan)),
        "region_mae_heights": float(heights.get("region_mae", math.nan)),
        "bias_sidescan": float(side.get("bias", math.nan)),
        "bias_heights": float(heights.get("bias", math.nan)),
        "n_cells": int(side.get("n_cells", 0)),
        "folds": int(verdict.get("folds") or 0),
        "block_m": float(verdict.get("block_m") or math.nan),
        "wall_s": float(wall_s),
        "run": run,
    }


def verdict_to_markdown(
    rows: Sequence[Mapping[str, Any]], title: str = "Verdict study", method: str = "siren_lambert"
) -> str:
    """Markdown of the verdict study rows (the sidescan fits by ``method``) and the agreement
    count."""
    agree = verdict_agreement(rows)
    folds = sorted({int(r["folds"]) for r in rows}) or [0]
    md = [
        f"# {title}",
        "",
        "Generated overlapping AUV-like XTF surveys (synthetic_d1, one per seed, no MBES "
        f"given to the fit). `sss2bathy-map method={method} verdict.folds="
        f"{'/'.join(map(str, folds))}` gives the K-fold verdict and the sidescan map; "
        "`method=siren_heights_only verdict.folds=0` the heights-only map. verdict = the "
        "sidescan fit against heights-only / interpolation on held-out altimeter blocks: "
        "better, worse or inconclusive; diff = mean paired MAE difference (sidescan - "
        "baseline, m) +- its 95 % half-width. MBES MAE (m) = each final map against the "
        "simulated MBES grid on the same cells (the sidescan map's written cells); truth = "
        "better when the sidescan map's MBES MAE is the lower. agrees: the verdict's call "
        "against heights-only matches the truth (blank when inconclusive).",
        "",
        "| seed | vs heights-only | diff (m) | vs interpolation | diff (m) | outcome "
        "| MBES MAE sidescan | MBES MAE heights-only | truth | agrees |",
        "|---:|---|---:|---|---:|---|---:|---:|---|---|",
    ]
    for r in rows:
        agrees = {True: "yes", False: "NO", None: ""}[r["agrees"]]
        md.append(
            f"| {r['seed']} | {r['vs_heights']} "
            f"| {_f(r['diff_heights_m'], '+.3f')} +- {_f(r['half_heights_m'])} "
            f"| {r['vs_interp']} | {_f(r['diff_interp_m'], '+.3f')} +- {_f(r['half_interp_m'])} "
            f"| {r['outcome']} | {_f(r['map_mae_sidescan'])} | {_f(r['map_mae_heights'])} "
            f"| {r['truth']} | {agrees} |"
        )
    md += [
        "",
        f"Agreement: {agree['agree']} of {agree['conclusive']} conclusive cases agree with the "
        f"MBES ({agree['inconclusive']} of {agree['n']} inconclusive).",
    ]
    return "\n".join(md) + "\n"


def verdict_to_csv(rows: Sequence[Mapping[str, Any]]) -> str:
    """CSV of the verdict study rows (:data:`VERDICT_COLUMNS`)."""
    return to_csv_table(rows, VERDICT_COLUMNS, ignore_extra=True)


def map_on_grid(
    heights: np.ndarray,
    x0: float,
    y0: float,
    cell_m: float,
    like: BathyGrid,
    shift_xy: Sequence[float] = (0.0, 0.0),
) -> BathyGrid:
    """A map grid (``heights``, SW cell centre ``x0, y0``, ``cell_m``) bilinearly sampled at
    the cell centres of ``like``, whose frame is the map's shifted by ``shift_xy`` (m: a
    point ``p`` of ``like`` is ``p + shift_xy`` in the map's frame); NaN outside the map."""
    src = BathyGrid(np.asarray(heights, np.float32), x0, y0, cell_m)
    xx, yy = np.meshgrid(like.x + float(shift_xy[0]), like.y + float(shift_xy[1]))
    return BathyGrid(src.sample(xx, yy), like.x0, like.y0, like.cell_size, like.crs)


def mask_on_grid(
    mask: np.ndarray,
    x0: float,
    y0: float,
    cell_m: float,
    like: BathyGrid,
    shift_xy: Sequence[float] = (0.0, 0.0),
) -> np.ndarray:
    """``(ny, nx)`` bool of ``like``: the value of the map-grid ``mask`` cell that holds each
    of ``like``'s cell centres (nearest cell; False outside the map)."""
    m = np.asarray(mask, bool)
    xx, yy = np.meshgrid(like.x + float(shift_xy[0]), like.y + float(shift_xy[1]))
    ix = np.floor((xx - x0) / cell_m + 0.5).astype(np.int64)
    iy = np.floor((yy - y0) / cell_m + 0.5).astype(np.int64)
    ok = (ix >= 0) & (ix < m.shape[1]) & (iy >= 0) & (iy < m.shape[0])
    out = np.zeros(like.shape, bool)
    out[ok] = m[iy[ok], ix[ok]]
    return out


# ---------------------------------------------------------------- survey and runs


@dataclass(frozen=True)
class StudySurvey:
    """A generated XTF survey: its files' folder, survey name and truth file."""

    xtf_dir: Path
    name: str
    crs: str

    @property
    def truth_path(self) -> Path:
        return self.xtf_dir / TRUTH_FILE


def survey_config(preset: str, scale: str) -> dict[str, Any]:
    """The ``data/survey=<preset>`` config at ``scale`` (resolved), composed as the entry
    points compose it (``conf/predict.yaml``), so the scale's survey sizes apply."""
    with initialize_config_dir(config_dir=str(CONF), version_base=None):
        cfg = compose("predict", overrides=[f"data/survey={preset}", f"scale={scale}"])
    return OmegaConf.to_container(cfg.data.survey, resolve=True)  # type: ignore[return-value]


def make_survey(
    out_dir: str | Path,
    seed: int,
    scale: str = "demo",
    split: str = "test",
    dropout_runs: int = 2,
    dropout_pings_per_run: int = 3,
) -> StudySurvey:
    """Simulate an AUV ``synthetic_d1`` survey (``seed``, ``scale``) and write ``split``'s
    lines to ``out_dir/line_*.xtf``, with ``dropout_runs`` runs of
    ``dropout_pings_per_run`` pings per line whose altitude is removed (alternately 0 m
    and NaN, both written as XTF's "no altitude" 0). ``out_dir/truth.npz`` holds every
    line's true altitude and dropped pings and the MBES grid (:func:`truth_grid`). Reused
    when ``truth.npz`` exists with the MBES grid."""
    out = Path(out_dir)
    name = f"xtf_study_{scale}_s{int(seed)}"
    cfg = survey_config("synthetic_d1", scale)
    crs = str(cfg["origin"]["crs"])
    survey_ = StudySurvey(out, name, crs)
    if survey_.truth_path.is_file():
        with np.load(survey_.truth_path, allow_pickle=False) as old:
            if "mbes/heights" in old:
                return survey_
    cfg["name"] = name
    cfg["seed"] = int(seed)
    cfg["plan"]["mount"] = "auv"
    config = SyntheticSurveyConfig.from_mapping(cfg)
    survey, _ = generate_survey(config)
    lines = survey.split_lines(split)
    if not lines:
        raise ValueError(f"split: expected lines in {split!r}, found none ({survey.splits})")
    out.mkdir(parents=True, exist_ok=True)
    truth: dict[str, np.ndarray] = {}
    if survey.grid is not None:
        truth["mbes/heights"] = np.asarray(survey.grid.heights, np.float32)
        truth["mbes/geometry"] = np.array(
            [
                survey.grid.x0,
                survey.grid.y0,
                survey.grid.cell_size,
                float(survey.origin.get("easting") or 0.0),
                float(survey.origin.get("northing") or 0.0),
            ]
        )
    for i, line in enumerate(lines):
        drop = dropout_pings(
            line.n_pings, dropout_runs, dropout_pings_per_run, seed=int(seed) * 1000 + i
        )
        alt = np.array(line.altitude_m, np.float32)
        truth[f"{line.name}/altitude"] = alt.copy()
        truth[f"{line.name}/dropped"] = drop
        starts = np.flatnonzero(drop & ~np.r_[False, drop[:-1]])
        for k, s in enumerate(starts):
            alt[s : s + dropout_pings_per_run] = 0.0 if k % 2 == 0 else np.nan
        write_xtf(replace(line, altitude_m=alt), out / f"{line.name}.xtf", survey.origin)
    with atomic_path(survey_.truth_path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **truth)
    return survey_


#: the map settings of the study's runs (``--map-args map_settings=NAME`` for others)
STUDY_SETTINGS = "map_settings=scale"


def map_command(
    survey: StudySurvey,
    method: str,
    variant: str,
    seed: int,
    run_dir: Path,
    data_dir: Path,
    scale: str = "demo",
    cnn_checkpoint: str | None = None,
    extra: Sequence[str] = (),
    map_args: Sequence[str] = (),
    verdict_folds: int = 0,
) -> list[str]:
    """The ``sss2bathy-map`` command line of one study run (1 thread, no logger):
    ``extra`` = further ``sss2bathy-train`` overrides, ``map_args`` = further
    ``sss2bathy-map`` arguments (e.g. ``holdout.block_pings=20``), ``verdict_folds`` = its
    ``verdict.folds`` (0: one held-out draw per run, the study's seeds are its repeats)."""
    if variant not in VARIANTS:
        raise ValueError(f"variant: expected one of {sorted(VARIANTS)}, found {variant!r}")
    overrides = ["callbacks=none", "trainer.enable_progress_bar=false"]
    overrides += list(VARIANT_OVERRIDES[variant]) + list(extra)
    cmd = [
        sys.executable,
        "-m",
        "sss2bathy.cli.map",
        f"files={survey.xtf_dir}",
        f"method={method}",
        f"seed={int(seed)}",
        f"survey.name={survey.name}",
        f"survey.crs={survey.crs}",
        "survey.n_bins=null",
        f"scale={scale}",
        "torch_threads=1",
        "logger=none",
        f"paths.data_dir={data_dir}",
        f"paths.output_dir={run_dir.parent}",
        f"hydra.run.dir={run_dir}",
        f"verdict.folds={int(verdict_folds)}",
        *VARIANTS[variant],
        # the study's tables are of the scale preset's SIREN settings unless map_args say
        # otherwise (e.g. map_settings=detail, the map route's default)
        *([] if any(str(a).startswith("map_settings=") for a in map_args) else [STUDY_SETTINGS]),
        *map_args,
        "overrides=[" + ",".join(f"'{o}'" for o in overrides) + "]",
    ]
    if cnn_checkpoint is not None:
        cmd.append(f"cnn_checkpoint={cnn_checkpoint}")
    return cmd


def run_logged(cmd: Sequence[str], log_path: Path, threads: int | None) -> float:
    """Run ``cmd`` (output to ``log_path``); its wall seconds.

    Raises:
        RuntimeError: the command failed (its last log line quoted).
    """
    log_path.parent.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    if threads is not None:
        env.update(OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    t0 = time.monotonic()
    with open(log_path, "w") as f:
        rc = subprocess.run(list(cmd), stdout=f, stderr=subprocess.STDOUT, env=env).returncode
    wall = time.monotonic() - t0
    if rc != 0:
        tail = log_path.read_text().strip().splitlines()[-1:] or ["(no output)"]
        raise RuntimeError(f"{log_path}: {cmd[2]} exited {rc}: {tail[0]}")
    return wall


def run_map(cmd: Sequence[str], run_dir: Path) -> float:
    """Run one ``sss2bathy-map`` command (log in ``run_dir.log``); its wall seconds.

    Raises:
        RuntimeError: the command failed (its last log line quoted).
    """
    wall = run_logged(cmd, run_dir.with_suffix(".log"), threads=1)
    atomic_write_text(run_dir / "study_wall_s.txt", f"{wall:.1f}\n")
    return wall


def survey_scores(survey: StudySurvey, data_dir: Path) -> dict[str, Any]:
    """Overlap of the imported lines and the altitude-repair errors against ``truth.npz``.

    Raises:
        ValueError: an imported line whose ping count differs from the simulated one.
    """
    imported = Survey.load(Path(data_dir) / survey.name)
    truth = np.load(survey.truth_path, allow_pickle=False)
    tracks, widths, alts, srcs, trues = [], [], [], [], []
    for line in imported.lines:
        key = f"{line.name}/altitude"
        if key not in truth:
            raise ValueError(f"{survey.truth_path}: expected line {line.name!r}, found none")
        true_alt = truth[key]
        if true_alt.shape != (line.n_pings,):
            raise ValueError(
                f"{data_dir / survey.name}: line {line.name}: expected {true_alt.shape[0]} "
                f"pings (as simulated), found {line.n_pings}"
            )
        tracks.append(line.position[:, :2])
        widths.append(ground_half_width(float(np.max(line.range_m)), line.altitude_m))
        alts.append(line.altitude_m)
        srcs.append(line.altitude_source)
        trues.append(true_alt)
    if any(s is None for s in srcs):
        raise ValueError(f"{data_dir / survey.name}: expected altitude_source, found none")
    rep = repair_errors(np.concatenate(alts), np.concatenate(srcs), np.concatenate(trues))
    return {"overlap": swath_overlap(tracks, widths), "repair": rep}


def study_row(
    method: str, variant: str, seed: int, run_dir: Path, scores: Mapping[str, Any]
) -> dict[str, Any]:
    """One table row from a finished run's ``metrics.json`` and the survey's scores."""
    metrics_path = run_dir / "metrics.json"
    if not metrics_path.is_file():
        raise FileNotFoundError(f"{metrics_path}: expected a finished run's metrics, found none")
    metrics = json.loads(metrics_path.read_text())

    def metric(name: str) -> float:
        for key in (f"final/{name}", f"val/{MAP_TAGS.get(name, name)}"):
            v = metrics.get(key)
            if v is not None and math.isfinite(float(v)):
                return float(v)
        return math.nan

    wall_path = run_dir / "study_wall_s.txt"
    fit, interp = metric("holdout_alt_mae"), metric("holdout_interp_mae")
    n = metric("holdout_n")
    rep = scores["repair"]
    return {
        "method": method,
        "variant": variant,
        "seed": int(seed),
        "holdout_mae": fit,
        "interp_mae": interp,
        "ratio": _ratio(fit, interp),
        "holdout_n": int(n) if math.isfinite(n) else None,
        "overlap": float(scores["overlap"]["overlap"]),
        "repair_n": int(rep["n"]),
        "repair_max_m": float(rep["max"]),
        "repair_median_m": float(rep["median"]),
        "wall_s": float(wall_path.read_text()) if wall_path.is_file() else math.nan,
        "run": str(run_dir),
    }


def failed_row(method: str, variant: str, seed: int, error: str) -> dict[str, Any]:
    """The table row of a run that failed: no metrics, ``run`` = ``FAILED: <error>``."""
    nan = math.nan
    return {
        "method": method, "variant": variant, "seed": int(seed), "holdout_mae": nan,
        "interp_mae": nan, "ratio": nan, "holdout_n": None, "overlap": nan, "repair_n": 0,
        "repair_max_m": nan, "repair_median_m": nan, "wall_s": nan, "run": f"FAILED: {error}",
    }  # fmt: skip


def run_study(
    out_dir: str | Path,
    seeds: Sequence[int],
    methods: Sequence[str],
    variants: Sequence[str],
    scale: str = "demo",
    cnn_checkpoint: str | None = None,
    cnn_variants: Sequence[str] | None = None,
    extra: Sequence[str] = (),
    map_args: Sequence[str] = (),
    rerun: bool = False,
) -> list[dict[str, Any]]:
    """Generate, fit and score; rows in seed, method, variant order. Runs already finished
    (``metrics.json``) are reused unless ``rerun``. The heights-only method has no
    sidescan term and runs once per seed (variant ``demo``)."""
    out = Path(out_dir).resolve()
    data_dir = out / "data"
    methods = list(methods)
    if cnn_checkpoint is not None and "siren_cnn_n2d" not in methods:
        methods.append("siren_cnn_n2d")
    if "siren_cnn_n2d" in methods and cnn_checkpoint is None:
        raise ValueError("methods: siren_cnn_n2d needs --cnn-checkpoint, found none")
    rows = []
    for seed in seeds:
        survey = make_survey(out / "xtf" / f"s{int(seed)}", int(seed), scale=scale)
        scores = None
        for method in methods:
            if method == "siren_heights_only":
                method_variants = ["demo"]
            elif method == "siren_cnn_n2d" and cnn_variants is not None:
                method_variants = list(cnn_variants)
            else:
                method_variants = list(variants)
            for variant in method_variants:
                run_dir = out / "runs" / f"s{int(seed)}" / f"{method}_{variant}"
                if rerun or not (run_dir / "metrics.json").is_file():
                    ckpt = cnn_checkpoint if method == "siren_cnn_n2d" else None
                    cmd = map_command(
                        survey,
                        method,
                        variant,
                        seed,
                        run_dir,
                        data_dir,
                        scale,
                        ckpt,
                        extra,
                        map_args,
                    )
                    log.info("seed %s %s %s: %s", seed, method, variant, " ".join(cmd))
                    try:
                        run_map(cmd, run_dir)
                    except RuntimeError as exc:  # the table says so; the other runs go on
                        log.error("%s", exc)
                        rows.append(failed_row(method, variant, seed, str(exc)))
                        write_table(rows, out)
                        continue
                if scores is None:
                    scores = survey_scores(survey, data_dir)
                row = study_row(method, variant, seed, run_dir, scores)
                log.info("%s", row)
                rows.append(row)
                write_table(rows, out)
    return rows


def truth_grid(survey: StudySurvey) -> tuple[BathyGrid, tuple[float, float]]:
    """The simulated MBES grid of a :func:`make_survey` survey (its local frame) and that
    frame's origin (easting, northing).

    Raises:
        ValueError: ``truth.npz`` without the grid (written before it held one).
    """
    with np.load(survey.truth_path, allow_pickle=False) as truth:
        if "mbes/heights" not in truth:
            raise ValueError(
                f"{survey.truth_path}: expected the MBES grid (mbes/heights), found none; "
                "delete the folder to regenerate the survey"
            )
        x0, y0, cell, easting, northing = (float(v) for v in truth["mbes/geometry"])
        grid = BathyGrid(truth["mbes/heights"], x0, y0, cell, survey.crs)
    return grid, (easting, northing)


def score_maps_on_truth(
    survey: StudySurvey, data_dir: Path, run_dirs: Mapping[str, Path], cells_from: str
) -> dict[str, dict[str, float]]:
    """Each run's final map (``map.npz``) against the MBES grid (:func:`truth_grid`), on the
    same cells for every run: the MBES cells inside the written map (``coverage``) of
    ``run_dirs[cells_from]`` (``mae``, ``std``, ``grad_cs``, ``n_cells``,
    :func:`sss2bathy.eval.maps.map_metrics`, and ``bias`` = the mean signed error) and
    inside its scored track region (``region_mae``). The maps are in the imported survey's
    frame; the shift between the two origins is applied."""
    from sss2bathy.eval.maps import map_metrics

    true, (easting, northing) = truth_grid(survey)
    imported = Survey.load(Path(data_dir) / survey.name)
    shift = (
        easting - float(imported.origin.get("easting") or 0.0),
        northing - float(imported.origin.get("northing") or 0.0),
    )

    def load(run_dir: Path) -> dict[str, Any]:
        path = Path(run_dir) / "map.npz"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: expected a finished run's map, found none")
        with np.load(path, allow_pickle=False) as d:
            return {k: d[k] for k in d.files}

    maps = {name: load(run_dir) for name, run_dir in run_dirs.items()}
    ref = maps[cells_from]
    geom = (float(ref["x0"]), float(ref["y0"]), float(ref["cell_size"]))
    written = mask_on_grid(ref["coverage"], *geom, true, shift)
    region = mask_on_grid(ref["region"], *geom, true, shift)
    preds = {
        name: map_on_grid(
            d["heights"], float(d["x0"]), float(d["y0"]), float(d["cell_size"]), true, shift
        )
        for name, d in maps.items()
    }
    # the same cells for every map: finite in all of them
    finite = np.logical_and.reduce([np.isfinite(p.heights) for p in preds.values()])
    out = {}
    for name, pred in preds.items():
        scored = map_metrics(pred, true, written & finite)
        err = (pred.heights - true.heights)[written & finite & np.isfinite(true.heights)]
        scored["bias"] = float(err.mean()) if err.size else math.nan
        scored["region_mae"] = map_metrics(pred, true, region & finite)["mae"]
        out[name] = scored
    return out


def run_verdict_study(
    out_dir: str | Path,
    seeds: Sequence[int],
    scale: str = "tiny",
    folds: int = 5,
    method: str = "siren_lambert",
    extra: Sequence[str] = (),
    map_args: Sequence[str] = (),
    rerun: bool = False,
) -> list[dict[str, Any]]:
    """Does the K-fold verdict agree with the MBES? Per seed, one generated survey
    (:func:`make_survey`), ``method`` with ``verdict.folds=folds`` (the verdict and the
    sidescan map) and ``siren_heights_only`` with ``verdict.folds=0 holdout.fraction=0`` (the
    heights-only map on every altimeter point, like the verdict run's final map), one
    process at a time;
    both maps scored against the MBES (:func:`score_maps_on_truth`). Writes
    ``verdict_study.md`` / ``.csv`` under ``out_dir`` after every seed; finished runs are
    reused unless ``rerun``."""
    if int(folds) < 2:
        raise ValueError(f"--verdict-folds: expected 2 or more folds, found {folds}")
    out = Path(out_dir).resolve()
    data_dir = out / "data"
    rows: list[dict[str, Any]] = []
    for seed in seeds:
        survey = make_survey(out / "xtf" / f"s{int(seed)}", int(seed), scale=scale)
        runs = {
            # the verdict run's final map is fitted on every altimeter point (cli.map)
            "sidescan": (method, int(folds), ()),
            "heights": ("siren_heights_only", 0, ("holdout.fraction=0",)),
        }
        run_dirs: dict[str, Path] = {}
        walls: dict[str, float] = {}
        for key, (m, k, args) in runs.items():
            run_dir = out / "runs" / f"s{int(seed)}" / f"{m}_folds{k}"
            run_dirs[key] = run_dir
            done = (run_dir / "metrics.json").is_file() and (
                k < 2 or (run_dir / "verdict.json").is_file()
            )
            if rerun or not done:
                cmd = map_command(
                    survey, m, "demo", seed, run_dir, data_dir, scale,
                    extra=extra, map_args=[*args, *map_args], verdict_folds=k,
                )  # fmt: skip
                log.info("seed %s %s folds=%d: %s", seed, m, k, " ".join(cmd))
                run_map(cmd, run_dir)
            wall_path = run_dir / "study_wall_s.txt"
            walls[key] = float(wall_path.read_text()) if wall_path.is_file() else math.nan
        verdict = json.loads((run_dirs["sidescan"] / "verdict.json").read_text())
        scores = score_maps_on_truth(survey, data_dir, run_dirs, cells_from="sidescan")
        row = verdict_row(
            seed, verdict, scores, str(run_dirs["sidescan"]), walls["sidescan"] + walls["heights"]
        )
        log.info("%s", row)
        rows.append(row)
        out.mkdir(parents=True, exist_ok=True)
        md = verdict_to_markdown(rows, method=method)
        write_tables(out, "verdict_study", md, verdict_to_csv(rows))
    return rows


def _or_one_line(study: Any, *args: Any, **kwargs: Any) -> Any:
    """``study(*args, **kwargs)``, or None after one stderr line when it fails."""
    try:
        return study(*args, **kwargs)
    except (RuntimeError, ValueError, FileNotFoundError) as exc:
        print(f"xtf_study: {exc}", file=sys.stderr)
        return None


def main(argv: list[str] | None = None) -> int:
    """``python -m studies.xtf_study [--seeds ...] [--cnn-checkpoint PATH] ...``."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument(
        "--out",
        default=None,
        help="study folder (runs, table); default outputs/xtf_study, with --verdict-folds "
        "outputs/verdict_study",
    )
    p.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    p.add_argument("--scale", default="demo", help="survey and SIREN scale (tiny | demo)")
    p.add_argument("--methods", nargs="+", default=["siren_lambert", "siren_heights_only"])
    p.add_argument("--variants", nargs="+", default=["demo", "fast", "fast_best"])
    p.add_argument("--cnn-checkpoint", default=None, help="adds the SIREN-CNN-N2d rows")
    p.add_argument("--cnn-variants", nargs="+", default=None, help="default: --variants")
    p.add_argument(
        "--extra", nargs="*", default=[], help="further sss2bathy-train overrides, every run"
    )
    p.add_argument(
        "--map-args", nargs="*", default=[], help="further sss2bathy-map arguments, every run"
    )
    p.add_argument("--rerun", action="store_true", help="refit runs that already finished")
    p.add_argument(
        "--verdict-folds",
        type=int,
        default=0,
        help="K >= 2: the verdict study instead (run_verdict_study: the first --methods "
        "with verdict.folds=K against a heights-only map, both scored on the MBES)",
    )
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    if args.verdict_folds:
        out = args.out or "outputs/verdict_study"
        vrows = _or_one_line(
            run_verdict_study, out, args.seeds, args.scale, args.verdict_folds, args.methods[0],
            extra=args.extra, map_args=args.map_args, rerun=args.rerun,
        )  # fmt: skip
        if vrows is None:
            return 1
        print(verdict_to_markdown(vrows))
        print(f"written: {Path(out) / 'verdict_study.md'}, {Path(out) / 'verdict_study.csv'}")
        return 0
    args.out = args.out or "outputs/xtf_study"
    for v in [*args.variants, *(args.cnn_variants or [])]:
        if v not in VARIANTS:
            print(f"--variants: expected some of {sorted(VARIANTS)}, found {v!r}", file=sys.stderr)
            return 2
    rows = _or_one_line(
        run_study, args.out, args.seeds, args.methods, args.variants, scale=args.scale,
        cnn_checkpoint=args.cnn_checkpoint, cnn_variants=args.cnn_variants, extra=args.extra,
        map_args=args.map_args, rerun=args.rerun,
    )  # fmt: skip
    if rows is None:
        return 1
    print(to_markdown(rows))
    print(f"written: {Path(args.out) / 'xtf_study.md'}, {Path(args.out) / 'xtf_study.csv'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
