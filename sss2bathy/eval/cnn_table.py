"""Table-2-style CNN results (paper "Quantitative Results For CNN"): ours beside the paper's.

Rows are ``{name: {"mae", "rel", "rmse", "delta1", "delta2", "delta3"}}`` with the deltas in
percent (as :func:`sss2bathy.metrics.NormalMetrics` computes them).

Each of our test sets can carry a **constant-prediction row**: the training lines' mean
n_lat predicted everywhere, scored with the same metrics on the same valid bins
(``constant_rows``, ``{name: {..., "value": the constant}}``). The ``skill`` column is
CNN MAE / constant MAE (< 1: the CNN beats a constant). They are stored in a run's
``metrics.json`` as ``test/{name}/constant/nlat_{metric}`` (:func:`constant_rows_from_metrics`).

The per-line, per-side mean bias of the predictions is written by :func:`write_cnn_bias`
(``cnn_bias.csv``, ``cnn_bias_range.csv``, ``cnn_bias.png``).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from sss2bathy.eval.paper_numbers import CNN_TABLE, PAPER_LABEL
from sss2bathy.utils.atomic import atomic_write_text, save_figure

COLUMNS = ("mae", "rel", "rmse", "delta1", "delta2", "delta3")
HEADERS = ("MAE", "REL", "RMSE", "δ<1.05 (%)", "δ<1.05² (%)", "δ<1.05³ (%)")
OURS_LABEL = "ours (synthetic survey)"
MD_NAME = "cnn_table.md"
CSV_NAME = "cnn_table.csv"
BIAS_CSV_NAME = "cnn_bias.csv"
BIAS_RANGE_CSV_NAME = "cnn_bias_range.csv"
BIAS_PNG_NAME = "cnn_bias.png"
CNN_PREDICTOR = "CNN"
CONSTANT_KEY = "constant"
# logged names of the six metrics: ``nlat_<metric>`` (n_lat is unitless; the deltas are in
# percent), so an n_lat metric never shares a tag with a map metric in metres
NLAT_PREFIX = "nlat_"
SIDES = ("port", "starboard")


def _fmt(key: str, value: float) -> str:
    if not math.isfinite(value):
        return "n/a"
    return f"{value:.2f}" if key.startswith("delta") else f"{value:.4f}"


def _check_rows(rows: Mapping[str, Mapping[str, float]]) -> dict[str, dict[str, float]]:
    if not isinstance(rows, Mapping) or not rows:
        raise ValueError(f"rows: expected a non-empty mapping name -> metrics, found {rows!r}")
    out = {}
    for name, metrics in rows.items():
        if not isinstance(metrics, Mapping):
            raise ValueError(f"rows['{name}']: expected a mapping of metrics, found {metrics!r}")
        missing = [k for k in COLUMNS if k not in metrics]
        if missing:
            raise ValueError(f"rows['{name}']: expected keys {list(COLUMNS)}, missing {missing}")
        try:
            out[str(name)] = {k: float(metrics[k]) for k in COLUMNS}
        except (TypeError, ValueError) as exc:
            raise ValueError(
                f"rows['{name}']: expected numeric metrics, found {metrics!r}"
            ) from exc
    return out


def metric_column(logged: str) -> str | None:
    """The table column of a logged metric name: ``nlat_mae`` -> ``mae`` (also the bare
    ``mae`` of run records written before the ``nlat_`` names), else None."""
    name = logged[len(NLAT_PREFIX) :] if logged.startswith(NLAT_PREFIX) else logged
    return name if name in COLUMNS else None


def table_rows_from_metrics(metrics: Mapping[str, Any]) -> dict[str, dict[str, float]]:
    """Group ``test/{name}/nlat_{metric}`` (or ``test/nlat_{metric}``; the bare ``{metric}``
    of older run records too) values into table rows ``{name: {metric: value}}`` for the six
    paper metrics; rows missing one are left out."""
    rows: dict[str, dict[str, float]] = {}
    for key, value in metrics.items():
        parts = str(key).split("/")
        column = metric_column(parts[-1])
        if parts[0] != "test" or column is None or len(parts) not in (2, 3):
            continue
        name = parts[1] if len(parts) == 3 else "test"
        row = rows.setdefault(name, {})
        if parts[-1].startswith(NLAT_PREFIX) or column not in row:
            row[column] = float(value)
    return {k: v for k, v in rows.items() if set(COLUMNS) <= set(v)}


def constant_rows_from_metrics(metrics: Mapping[str, Any]) -> dict[str, dict[str, float]]:
    """Group ``test/{name}/constant/nlat_{metric}`` (older records: ``.../{metric}``) and
    ``test/{name}/constant/value`` into constant-prediction rows
    ``{name: {metric: value, "value": constant}}``; rows missing a metric are left out."""
    rows: dict[str, dict[str, float]] = {}
    for key, value in metrics.items():
        parts = str(key).split("/")
        if len(parts) == 4 and parts[0] == "test" and parts[2] == CONSTANT_KEY:
            column = "value" if parts[3] == "value" else metric_column(parts[3])
            row = rows.setdefault(parts[1], {})
            if column is not None and (parts[3].startswith(NLAT_PREFIX) or column not in row):
                row[column] = float(value)
    need = {*COLUMNS, "value"}
    return {k: v for k, v in rows.items() if need <= set(v)}


def constant_metric_keys(name: str, row: Mapping[str, float]) -> dict[str, float]:
    """The ``metrics.json`` keys of one constant row (the inverse of
    :func:`constant_rows_from_metrics`)."""
    out = {f"test/{name}/{CONSTANT_KEY}/{NLAT_PREFIX}{k}": float(row[k]) for k in COLUMNS}
    return {**out, f"test/{name}/{CONSTANT_KEY}/value": float(row["value"])}


def _check_constant(
    constant_rows: Mapping[str, Mapping[str, float]] | None, ours: Mapping[str, Any]
) -> dict[str, dict[str, float]]:
    if constant_rows is None:
        return {}
    out = _check_rows(constant_rows) if constant_rows else {}
    for name, row in out.items():
        if name not in ours:
            raise ValueError(
                f"constant_rows['{name}']: expected one of the CNN rows {sorted(ours)}, found "
                "a test set without a CNN row"
            )
        value = constant_rows[name].get("value")
        if not isinstance(value, int | float) or not math.isfinite(float(value)):
            raise ValueError(
                f"constant_rows['{name}']['value']: expected the finite constant, found {value!r}"
            )
        row["value"] = float(value)
    return out


def _skill(ours: Mapping[str, float], constant: Mapping[str, float] | None) -> float:
    if constant is None or not constant["mae"] > 0:
        return math.nan
    return ours["mae"] / constant["mae"]


def _table_rows(
    rows: Mapping[str, Mapping[str, float]],
    constant_rows: Mapping[str, Mapping[str, float]] | None,
) -> list[tuple[str, str, str, dict[str, float], float]]:
    """``(source, data set, predictor, metrics, skill)`` in table order."""
    ours = _check_rows(rows)
    const = _check_constant(constant_rows, ours)
    out = []
    for name, metrics in ours.items():
        out.append((OURS_LABEL, name, CNN_PREDICTOR, metrics, _skill(metrics, const.get(name))))
        if name in const:
            c = const[name]
            label = f"{CONSTANT_KEY} {c['value']:+.4f} (training mean)"
            out.append((OURS_LABEL, name, label, c, 1.0))
    for name, metrics in CNN_TABLE.items():
        out.append((PAPER_LABEL, name, CNN_PREDICTOR, dict(metrics), math.nan))
    return out


def cnn_table_markdown(
    rows: Mapping[str, Mapping[str, float]],
    constant_rows: Mapping[str, Mapping[str, float]] | None = None,
) -> str:
    """Markdown table: our rows (each followed by its constant-prediction row when given),
    then the paper's rows labelled as measured on its own data."""
    table = _table_rows(rows, constant_rows)
    lines = [
        '# Normal CNN: quantitative results (paper Table "Quantitative Results For CNN")',
        "",
        "Errors are on n_lat (lower is better); accuracies are % of valid bins with "
        "max((n+1)/(n_GT+1), (n_GT+1)/(n+1)) below the threshold (higher is better). "
        "*constant* rows predict the training lines' mean n_lat everywhere, scored on the "
        "same valid bins; skill = CNN MAE / constant MAE (below 1: the CNN beats a constant).",
        f"Rows labelled *{PAPER_LABEL}* are the published numbers on the paper's real "
        "Datasets I/II; ours are on our synthetic surveys: for orientation, not a like-for-like "
        "comparison.",
        "",
        "| source | data set | predictor | " + " | ".join(HEADERS) + " | skill |",
        "|---|---|---|" + "---:|" * (len(HEADERS) + 1),
    ]
    for source, name, predictor, metrics, skill in table:
        cells = " | ".join(_fmt(k, float(metrics[k])) for k in COLUMNS)
        skill_cell = f"{skill:.2f}" if math.isfinite(skill) else "n/a"
        lines.append(f"| {source} | {name} | {predictor} | {cells} | {skill_cell} |")
    return "\n".join(lines) + "\n"


def cnn_table_csv(
    rows: Mapping[str, Mapping[str, float]],
    constant_rows: Mapping[str, Mapping[str, float]] | None = None,
) -> str:
    """CSV with columns ``source, dataset, predictor, mae, rel, rmse, delta1, delta2,
    delta3, skill`` (``predictor``: ``CNN`` or ``constant``; ``constant_value`` holds the
    constant; ``skill`` = CNN MAE / constant MAE, empty where undefined)."""
    table = _table_rows(rows, constant_rows)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(("source", "dataset", "predictor", *COLUMNS, "skill", "constant_value"))
    for source, name, predictor, metrics, skill in table:
        kind = CONSTANT_KEY if predictor.startswith(CONSTANT_KEY) else predictor
        value = repr(float(metrics["value"])) if "value" in metrics else ""
        writer.writerow(
            (
                source,
                name,
                kind,
                *(repr(float(metrics[k])) for k in COLUMNS),
                repr(skill) if math.isfinite(skill) else "",
                value,
            )
        )
    return buf.getvalue()


def write_cnn_table(
    rows: Mapping[str, Mapping[str, float]],
    out_dir: str | Path,
    constant_rows: Mapping[str, Mapping[str, float]] | None = None,
) -> tuple[Path, Path]:
    """Write ``cnn_table.md`` and ``cnn_table.csv`` into ``out_dir`` (atomically).

    Args:
        rows: ``{data set name: {mae, rel, rmse, delta1, delta2, delta3}}`` (deltas in %).
        out_dir: folder, created if needed.
        constant_rows: the constant prediction's rows of the same data sets, each with
            ``value`` (the constant); None: no constant rows.

    Returns:
        ``(markdown path, csv path)``.
    """
    markdown = cnn_table_markdown(rows, constant_rows)
    table = cnn_table_csv(rows, constant_rows)
    out = Path(out_dir)
    md_path, csv_path = out / MD_NAME, out / CSV_NAME
    atomic_write_text(md_path, markdown)
    atomic_write_text(csv_path, table)
    return md_path, csv_path


# ------------------------------------------------------------------------- bias
LINE_COLUMNS = ("dataset", "line", "side", "count", "mean_truth", "mean_pred", "bias")
RANGE_COLUMNS = (
    "dataset", "side", "range_bin", "bin_lo", "bin_hi", "count", "mean_truth", "mean_pred",
    "bias",
)  # fmt: skip


def _check_bias_rows(rows: Any, columns: Sequence[str], name: str) -> list[dict[str, Any]]:
    if not isinstance(rows, Sequence) or isinstance(rows, str):
        raise ValueError(f"{name}: expected a list of rows, found {type(rows).__name__}")
    for i, row in enumerate(rows):
        missing = [c for c in columns if c not in row]
        if missing:
            raise ValueError(f"{name}[{i}]: expected keys {list(columns)}, missing {missing}")
    return [dict(r) for r in rows]


def _rows_csv(rows: Sequence[Mapping[str, Any]], columns: Sequence[str]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow(
            [repr(float(row[c])) if isinstance(row[c], float) else row[c] for c in columns]
        )
    return buf.getvalue()


def plot_cnn_bias(
    line_rows: Sequence[Mapping[str, Any]], range_rows: Sequence[Mapping[str, Any]], path: Path
) -> Path:
    """``cnn_bias.png``: per test set (a row of panels), the mean bias of every line x side
    as bars with the mean truth as dots, and the bias against range per side."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sets = list(dict.fromkeys(r["dataset"] for r in line_rows))
    fig, axes = plt.subplots(
        len(sets), 2, figsize=(12, 3.2 * len(sets)), squeeze=False,
        gridspec_kw={"width_ratios": [2, 1]},
    )  # fmt: skip
    colours = {"port": "tab:red", "starboard": "tab:green"}
    for ax_bar, ax_rng, name in zip(axes[:, 0], axes[:, 1], sets, strict=True):
        rows = [r for r in line_rows if r["dataset"] == name]
        lines = list(dict.fromkeys(r["line"] for r in rows))
        width = 0.4
        for k, side in enumerate(SIDES):
            xs = [lines.index(r["line"]) + (k - 0.5) * width for r in rows if r["side"] == side]
            ax_bar.bar(
                xs, [r["bias"] for r in rows if r["side"] == side], width,
                color=colours[side], alpha=0.7, label=f"{side}: mean prediction - mean truth",
            )  # fmt: skip
            ax_bar.plot(
                xs, [r["mean_truth"] for r in rows if r["side"] == side], "o", ms=3,
                color="k" if k == 0 else "0.5", label=f"{side}: mean truth",
            )  # fmt: skip
        ax_bar.axhline(0, color="k", lw=0.5)
        ax_bar.set_xticks(range(len(lines)), lines, rotation=60, fontsize=7)
        ax_bar.set_ylabel("n_lat")
        ax_bar.set_title(f"{name}: per-line, per-side mean bias", fontsize=9)
        ax_bar.legend(fontsize=6, ncol=2)
        for side in SIDES:
            rr = [r for r in range_rows if r["dataset"] == name and r["side"] == side]
            centres = [(r["bin_lo"] + r["bin_hi"]) / 2 for r in rr]
            ax_rng.plot(centres, [r["bias"] for r in rr], "-o", ms=3, color=colours[side],
                        label=f"{side} bias")  # fmt: skip
            ax_rng.plot(centres, [r["mean_truth"] for r in rr], ":", color=colours[side],
                        label=f"{side} mean truth")  # fmt: skip
        ax_rng.axhline(0, color="k", lw=0.5)
        ax_rng.set_xlabel("bin across track (slant range grows with it)")
        ax_rng.set_title(f"{name}: bias vs range", fontsize=9)
        ax_rng.legend(fontsize=6)
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


def write_cnn_bias(
    line_rows: Sequence[Mapping[str, Any]],
    range_rows: Sequence[Mapping[str, Any]],
    out_dir: str | Path,
) -> tuple[Path, Path, Path]:
    """Write ``cnn_bias.csv`` (one row per test set x line x side: ``dataset, line, side,
    count, mean_truth, mean_pred, bias``), ``cnn_bias_range.csv`` (bias against bins across
    track per side) and the figure ``cnn_bias.png`` into ``out_dir``.

    ``side`` is ``port`` or ``starboard``; ``count`` the valid pixels summed (as windows
    count them); bias = mean prediction - mean truth.
    """
    lines = _check_bias_rows(line_rows, LINE_COLUMNS, "line_rows")
    ranged = _check_bias_rows(range_rows, RANGE_COLUMNS, "range_rows")
    if not lines:
        raise ValueError(
            "line_rows: expected at least one (line, side) with valid bins, found none"
        )
    for name, rows in (("line_rows", lines), ("range_rows", ranged)):
        bad = sorted({str(r["side"]) for r in rows} - set(SIDES))
        if bad:
            raise ValueError(f"{name}: expected side in {list(SIDES)}, found {bad}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = (out / BIAS_CSV_NAME, out / BIAS_RANGE_CSV_NAME, out / BIAS_PNG_NAME)
    atomic_write_text(paths[0], _rows_csv(lines, LINE_COLUMNS))
    atomic_write_text(paths[1], _rows_csv(ranged, RANGE_COLUMNS))
    plot_cnn_bias(lines, ranged, paths[2])
    return paths


# ------------------------------------------------------------------- scale split
#: the low-pass boxes of :func:`scale_split` (pings along track x bins across track): a
#: masked moving average of the error over each box, centred on the pixel
SCALE_BOXES: tuple[tuple[int, int], ...] = ((4, 8), (16, 32), (48, 96))
#: the box whose low-passed error is the headline "low-pass" number (and its slope)
HEADLINE_BOX = (16, 32)
#: pings of the along-track average of each ping's swath-mean error (``swath{N}_mae``)
SWATH_PINGS = 16
SCALE_MD_NAME = "cnn_scale_split.md"
SCALE_CSV_NAME = "cnn_scale_split.csv"


def lowpass_waterfall(
    values: Any, valid: Any, pings: int, bins: int, min_fraction: float = 0.25
) -> tuple[Any, Any]:
    """Masked moving average of one head's waterfall ``values (P, B)`` over ``pings x bins``
    boxes centred on each pixel (``scipy.ndimage.uniform_filter``, zeros beyond the edges,
    divided by the valid count); returns ``(low-passed (P, B), kept (P, B) bool)``: kept =
    valid and at least ``min_fraction`` of the box valid."""
    import numpy as np
    from scipy.ndimage import uniform_filter

    v = np.asarray(values, dtype=np.float64)
    m = np.asarray(valid, dtype=bool) & np.isfinite(v)
    if v.ndim != 2 or m.shape != v.shape:
        raise ValueError(
            f"values, valid: expected two (P, B) arrays of one shape, found {v.shape}, {m.shape}"
        )
    if not (isinstance(pings, int) and isinstance(bins, int) and pings >= 1 and bins >= 1):
        raise ValueError(f"box: expected positive integers pings x bins, found {pings} x {bins}")
    size = (pings, bins)
    total = uniform_filter(np.where(m, v, 0.0), size=size, mode="constant")
    count = uniform_filter(m.astype(np.float64), size=size, mode="constant")
    out = total / np.maximum(count, 1e-12)
    keep = m & (count >= min_fraction)
    return np.where(keep, out, np.nan), keep


def _slope(pred: Any, truth: Any) -> float:
    """Least-squares slope of ``pred`` on ``truth`` (1: no shrinkage, < 1: shrunk slopes)."""
    import numpy as np

    t = truth - truth.mean()
    den = float(np.sum(t * t))
    return float(np.sum(t * (pred - pred.mean())) / den) if den > 0 else math.nan


def scale_split(
    heads: Sequence[tuple[Any, Any, Any]],
    boxes: Sequence[tuple[int, int]] = SCALE_BOXES,
) -> dict[str, float]:
    """The n_lat error of a data set split by spatial scale.

    ``heads``: ``(pred (P, B), truth (P, B), valid (P, B) bool)`` per line and side (whole
    stitched waterfalls: the filters need more than a window). Returns:

    * ``mae``: pixel MAE; ``lp{p}x{b}_mae``: MAE of the error low-passed over each box of
      ``boxes`` (:func:`lowpass_waterfall`), over the kept pixels -- the error correlated
      over that many pings and bins, the part a map integrates; ``lp{p}x{b}_share``: that
      over ``mae``;
    * ``swath16_mae``: the error averaged over each ping's valid bins (pings at least 25 %
      valid), then over :data:`SWATH_PINGS` pings along track, MAE over those pings -- the
      error a swath's height profile integrates (the issue's map error followed it);
    * ``line_side_bias``: the pixel-weighted mean of |mean error| per (line, side);
    * ``slope``: least-squares slope of prediction on truth per pixel; ``lp_slope``: the
      same after low-passing both over :data:`HEADLINE_BOX` (below 1: shrunk slopes);
    * ``n``: valid pixels.
    """
    import numpy as np

    if not heads:
        raise ValueError("heads: expected at least one (pred, truth, valid) head, found none")
    errs, preds, truths, lp_p, lp_t = [], [], [], [], []
    lp_errs: dict[tuple[int, int], list] = {tuple(b): [] for b in boxes}
    swath: list = []
    bias_sum, bias_n = 0.0, 0
    for i, (pred, truth, valid) in enumerate(heads):
        p = np.asarray(pred, dtype=np.float64)
        t = np.asarray(truth, dtype=np.float64)
        m = np.asarray(valid, dtype=bool) & np.isfinite(p) & np.isfinite(t)
        if p.shape != t.shape or p.shape != m.shape or p.ndim != 2:
            raise ValueError(
                f"heads[{i}]: expected pred, truth, valid of one (P, B) shape, found "
                f"{p.shape}, {t.shape}, {m.shape}"
            )
        if not m.any():
            continue
        e = np.where(m, p - t, np.nan)
        errs.append(e[m])
        preds.append(p[m])
        truths.append(t[m])
        bias_sum += abs(float(e[m].mean())) * int(m.sum())
        bias_n += int(m.sum())
        for box in lp_errs:
            lp, keep = lowpass_waterfall(e, m, *box)
            lp_errs[box].append(lp[keep])
        count = m.sum(axis=1)
        ping_ok = count >= 0.25 * m.shape[1]
        ping_mean = np.where(m, e, 0.0).sum(axis=1) / np.maximum(count, 1)
        lp_ping, kept = lowpass_waterfall(ping_mean[:, None], ping_ok[:, None], SWATH_PINGS, 1)
        swath.append(lp_ping[kept])
        lpp, keep = lowpass_waterfall(p, m, *HEADLINE_BOX)
        lpt, _ = lowpass_waterfall(t, m, *HEADLINE_BOX)
        lp_p.append(lpp[keep])
        lp_t.append(lpt[keep])
    if not errs:
        raise ValueError("heads: expected valid pixels, found none in any head")
    err = np.concatenate(errs)
    mae = float(np.abs(err).mean())
    out: dict[str, float] = {"mae": mae}
    for (pb, bb), parts in lp_errs.items():
        lp = np.concatenate(parts)
        lp_mae = float(np.abs(lp).mean()) if lp.size else math.nan
        out[f"lp{pb}x{bb}_mae"] = lp_mae
        out[f"lp{pb}x{bb}_share"] = lp_mae / mae if mae > 0 else math.nan
    sw = np.concatenate(swath)
    out[f"swath{SWATH_PINGS}_mae"] = float(np.abs(sw).mean()) if sw.size else math.nan
    out["line_side_bias"] = bias_sum / bias_n
    out["slope"] = _slope(np.concatenate(preds), np.concatenate(truths))
    out["lp_slope"] = _slope(np.concatenate(lp_p), np.concatenate(lp_t))
    out["n"] = float(err.size)
    return out


def scale_split_markdown(rows: Mapping[str, Mapping[str, float]], title: str = "") -> str:
    """Markdown table of :func:`scale_split` rows ``{data set: split}``."""
    if not rows:
        raise ValueError("rows: expected at least one data set, found none")
    keys = [k for k in next(iter(rows.values())) if k != "n"]
    lines = [
        f"# {title or 'CNN n_lat error split by scale'}",
        "",
        "lpPxB: the error low-passed by a masked moving average over P pings x B bins, centred "
        "on each pixel (boxes at least 25% valid); share = lp MAE / pixel MAE; line_side_bias: "
        "mean |mean error| per line and side; slope: prediction on truth (per pixel; lp_slope "
        f"after low-passing both over {HEADLINE_BOX[0]}x{HEADLINE_BOX[1]}).",
        "",
        "| data set | " + " | ".join(keys) + " |",
        "|---|" + "---:|" * len(keys),
    ]
    for name, row in rows.items():
        lines.append(f"| {name} | " + " | ".join(f"{float(row[k]):.4f}" for k in keys) + " |")
    return "\n".join(lines) + "\n"


def write_scale_split(
    rows: Mapping[str, Mapping[str, float]], out_dir: str | Path, title: str = ""
) -> tuple[Path, Path]:
    """Write ``cnn_scale_split.md`` and ``.csv`` (one row per data set) into ``out_dir``."""
    markdown = scale_split_markdown(rows, title)
    keys = list(next(iter(rows.values())))
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(("dataset", *keys))
    for name, row in rows.items():
        writer.writerow((name, *(repr(float(row[k])) for k in keys)))
    out = Path(out_dir)
    paths = (out / SCALE_MD_NAME, out / SCALE_CSV_NAME)
    atomic_write_text(paths[0], markdown)
    atomic_write_text(paths[1], buf.getvalue())
    return paths
