"""Do the SIREN maps show wrecks? Fits on a synthetic survey with objects, scored per object.

    .venv/bin/python -m studies.wreck_study                       (demo scale, both settings)
    .venv/bin/python -m studies.wreck_study --scale tiny --methods siren_lambert
    .venv/bin/python -m studies.wreck_study --variant w30=model.siren.omega0=30

Generates ``data/survey=synthetic_wrecks`` (five hulls and boxes 1-4 m high beside the
tracks of an AUV sidescan, ``conf/data/survey/synthetic_wrecks.yaml``), fits each method with
the scale's own settings (``scale``) and with those the map route chooses for the survey's
scale (``chosen``: :func:`sss2bathy.cli.map_settings.apply_map_settings`, the finer SIREN
and, for the sidescan methods, the occlusion term; ``detail``: ``map_settings=detail``, the
scale's SIREN plus a detail network), plus any
``--variant``, one ``sss2bathy-train`` process at a time (one torch thread), and scores
every map against the true grid: each object's height above its surroundings
(:func:`sss2bathy.sim.terrain.object_relief`, the same number on the true grid is the
truth), its error, the fraction of objects *visible* (fitted >= half the true height) and
the map's MAE. Writes ``<out>/wreck_study.md`` and ``.csv``; a finished run (its
``metrics.json``) is reused. SIREN-CNN-N2d uses the CNN shipped in the package
(``siren_cnn_n2d_pretrained``; its training seabeds include hulls and boxes, none of this
survey's); SIREN-GT-N2d (the true normals) is its upper bound.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np

from studies.tables import markdown_table, to_csv, write_tables

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
METHODS = ("siren_lambert", "siren_cnn_n2d_pretrained", "siren_gt_n2d", "siren_heights_only")


def run(args: list[str], log: Path) -> None:
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as fh:
        done = subprocess.run([sys.executable, "-m", *args], cwd=ROOT, stdout=fh, stderr=fh)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(args[:3])} ... failed (exit {done.returncode}); see {log}")


def chosen_overrides(survey_folder: Path, base: list[str], mode: str = "survey") -> list[str]:
    """The map route's settings (``map_settings=mode``) for this survey, as ``train``
    overrides (``+key=value`` for a key the composed config lacks)."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf, open_dict

    from sss2bathy.cli.map_settings import apply_map_settings, survey_scale
    from sss2bathy.survey import Survey

    survey = Survey.load(survey_folder)
    lines = survey.split_lines("test")
    scale = survey_scale([ln.position for ln in lines], [ln.range_m for ln in lines])
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=base)
    before = cfg.copy()
    with open_dict(cfg):
        applied = apply_map_settings(cfg, scale, [], mode=mode)
    absent = object()
    return [
        f"{'+' if OmegaConf.select(before, k, default=absent) is absent else ''}{k}={v}"
        for k, v in applied.items()
    ]


def score(run_dir: Path, truth: np.ndarray, cell: float, objects: list) -> dict:
    from sss2bathy.sim.terrain import object_relief

    d = np.load(run_dir / "map.npz")
    heights = np.where(d["region"], d["heights"], np.nan)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    true = np.array([object_relief(truth, cell, o) for o in objects])
    fit = np.array([object_relief(heights, cell, o) for o in objects])
    return {
        "map_mae_m": metrics.get("final/mae", float("nan")),
        "holdout_alt_mae_m": metrics.get("final/holdout_alt_mae", float("nan")),
        "object_height_mae_m": float(np.nanmean(np.abs(fit - true))),
        "visible_fraction": float(np.mean(fit >= 0.5 * true)),
        "fitted_m": " ".join(f"{v:.2f}" for v in fit),
        "true_m": " ".join(f"{v:.2f}" for v in true),
    }


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scale", default="demo")
    p.add_argument("--survey", default="synthetic_wrecks")
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    p.add_argument("--settings", nargs="*", default=["scale", "chosen", "detail"])
    p.add_argument(
        "--variant", action="append", default=[], metavar="NAME=KEY=V[,KEY=V]",
        help="extra settings to fit, e.g. w30=model.siren.omega0=30",
    )  # fmt: skip
    p.add_argument("--out", default=str(ROOT / "outputs" / "wreck_study"))
    args = p.parse_args(argv)

    import yaml

    from sss2bathy.io.export import read_geotiff
    from sss2bathy.sim.config import ObjectParams

    out = Path(args.out)
    data_dir = ROOT / "data"
    run(["sss2bathy.cli.prepare", f"data/survey={args.survey}", f"scale={args.scale}",
         f"paths.data_dir={data_dir}"], out / "prepare.log")  # fmt: skip
    folder = data_dir / args.survey
    manifest = yaml.safe_load((folder / "survey.yaml").read_text())
    objects = [ObjectParams(**o) for o in manifest["metadata"]["config"]["terrain"]["objects"]]
    truth = read_geotiff(folder / "grid.tif", manifest["origin"])
    base = [f"data/survey={args.survey}", f"scale={args.scale}", "logger=none",
            "callbacks=none", "torch_threads=1", f"paths.data_dir={data_dir}"]  # fmt: skip
    modes = {"chosen": "survey", "detail": "detail"}  # the map route's map_settings
    for name in args.settings:
        if name != "scale" and name not in modes:
            raise SystemExit(f"--settings: expected scale, chosen or detail, found {name!r}")
    variants: dict[str, list[str]] = {}
    for item in args.variant:
        name, _, spec = item.partition("=")
        if not name or not spec:
            raise SystemExit(f"--variant: expected NAME=KEY=VALUE[,KEY=VALUE], found {item!r}")
        variants[name] = spec.split(",")

    def overrides_of(label: str, method: str) -> list[str]:
        if label in variants:
            return variants[label]
        if label in modes:  # per method: heights only gets no occlusion term, no detail
            return chosen_overrides(folder, [*base, f"experiment={method}"], modes[label])
        return []

    rows = []
    for label in [*args.settings, *variants]:
        for method in args.methods:
            overrides = overrides_of(label, method)
            run_dir = out / "runs" / f"{method}_{label}_{args.scale}"
            if not (run_dir / "metrics.json").is_file():
                print(
                    f"fitting {method} ({label}: {' '.join(overrides) or 'the scale'})", flush=True
                )
                run(["sss2bathy.cli.train", f"experiment={method}", *base, *overrides,
                     f"hydra.run.dir={run_dir}"], run_dir.with_suffix(".log"))  # fmt: skip
            row = {"method": method, "settings": label, "overrides": " ".join(overrides)}
            row.update(score(run_dir, truth.heights, truth.cell_size, objects))
            rows.append(row)
            print(row, flush=True)

    heights = ", ".join(f"{o.kind} {o.height_m:g} m" for o in objects)
    lines = [
        f"# Wreck study: {args.survey} at scale={args.scale}",
        "",
        f"Objects ({heights}); height = top (90th percentile over the footprint) minus the "
        "median 2-6 m around it; visible = fitted >= 50 % of true. SIREN-CNN-N2d: the "
        "shipped CNN (siren_cnn_n2d_pretrained); SIREN-GT-N2d (true normals): its bound.",
        "",
        f"Command: `.venv/bin/python -m studies.wreck_study {' '.join(argv or sys.argv[1:])}`",
        "",
    ]
    lines += markdown_table(
        ["method", "settings", "map MAE (m)", "held-out alt. MAE (m)", "object height MAE (m)"]
        + ["visible", "fitted heights (m)", "true heights (m)"],
        (
            [r["method"], r["settings"] + (f" (`{r['overrides']}`)" if r["overrides"] else "")]
            + [f"{r['map_mae_m']:.3f}", f"{r['holdout_alt_mae_m']:.3f}"]
            + [f"{r['object_height_mae_m']:.2f}", f"{r['visible_fraction']:.0%}"]
            + [r["fitted_m"], r["true_m"]]
            for r in rows
        ),
    )
    paths = write_tables(out, "wreck_study", "\n".join(lines) + "\n", to_csv(rows, list(rows[0])))
    print(f"wrote {paths['md']}")
    if any(math.isnan(r["object_height_mae_m"]) for r in rows):
        print("note: some objects lie outside a map's coverage (NaN)", file=sys.stderr)


if __name__ == "__main__":
    main()
