"""Section ``finder``: the intersection finder on one batch, paper GD vs Newton and secant.

:func:`~sss2bathy.models.intersection.find_intersections` with the paper's fixed-step
gradient descent (``gd``) against safeguarded Newton and the height-only secant solver (the
fit's default), cold and warm-started from the crossings on a perturbed surface (a fit's
next epoch), at the same tolerance: time per batch, evaluations per bin, agreement of the
valid bins and of the crossing points, speed-up ratios.
"""

from __future__ import annotations

import copy
import statistics
from collections import Counter
from collections.abc import Callable, Mapping
from typing import Any

import torch

from benchmarks.scene import DEPTH_M, bench_siren, paper_beam_limits, synthetic_pings, to_device
from benchmarks.timing import figure, resolve_device, time_in_turns

TITLE = "Intersection finder"


def _crossing_points(arcs: Mapping[str, torch.Tensor], theta: torch.Tensor) -> torch.Tensor:
    from sss2bathy.geometry import arc_point

    return arc_point(arcs["sonar"], arcs["R"], arcs["range_m"], theta, arcs["side"])


def _residual_m(surface, arcs: Mapping[str, torch.Tensor], theta: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        p = _crossing_points(arcs, torch.nan_to_num(theta))
        return surface.height(p[:, :2].contiguous()) - p[:, 2]


def _agreement(arcs, theta_a, valid_a, theta_b, valid_b) -> dict[str, float]:
    both = valid_a & valid_b
    d = (_crossing_points(arcs, theta_a) - _crossing_points(arcs, theta_b)).norm(dim=-1)
    d = d[both]
    return {
        "same_validity": float((valid_a == valid_b).float().mean()),
        "found_of_reference": float(both.sum() / valid_b.sum().clamp_min(1)),
        "median_point_diff_mm": float(d.median() * 1e3) if d.numel() else float("nan"),
        "max_point_diff_mm": float(d.max() * 1e3) if d.numel() else float("nan"),
    }


def bench_finder(
    *,
    n_pings: int = 64,
    n_bins: int = 512,
    max_range_m: float = 50.0,
    hidden: int = 128,
    n_layers: int = 5,
    omega0: float = 30.0,
    relief_m: float = 50.0,
    perturb: float = 2e-3,
    tol_m: float = 1e-3,
    gd_max_iter: int = 2000,
    warmup: int = 1,
    repeats: int = 5,
    gd_repeats: int = 3,
    device: str | torch.device | None = None,
    seed: int = 0,
) -> dict:
    """The intersection finder on one batch: paper gradient descent vs Newton and secant.

    Gradient descent is given as many steps as its slowest converging bin needs (found in
    an untimed run capped at ``gd_max_iter``), so it stops as soon as it has reached the
    accuracy it can reach; the bins without a crossing run all of them, as in the paper.
    Newton and the secant solver (height-only) run with the finder's defaults: the cold
    scan (slope-bounded steps, ``n_scan`` resolution) and then their refinement.

    The warm start is the cold Newton solution on the SIREN, used on a copy whose weights
    moved by ``perturb`` (relative, Gaussian; a fit's next epoch): the root-mean-square
    height change is reported. Accuracy is the same for all (``|f| <= tol_m``); agreement
    compares valid bins and crossing points with Newton on the same surface. All solvers
    are timed in turns (:func:`~benchmarks.timing.time_in_turns`); the SIREN counts the
    points of its height and height-with-gradient passes, reported per bin for each solver.
    """
    from sss2bathy.models.intersection import find_intersections, find_row_intersections

    dev = resolve_device(device)
    (batch,), bounds = synthetic_pings(
        n_pings, n_bins, max_range_m=max_range_m, depth_m=DEPTH_M, altimeter_points=1, seed=seed
    )
    batch = to_device(batch, dev)
    surface = bench_siren(hidden, n_layers, omega0, bounds, DEPTH_M, relief_m, seed, True).to(dev)
    moved = copy.deepcopy(surface)
    gen = torch.Generator().manual_seed(seed + 1)
    with torch.no_grad():
        for p in moved.parameters():
            p.add_(perturb * p.abs().mean() * torch.randn(p.shape, generator=gen).to(dev))
    pi, si, bi = (batch["mask"] == 0).nonzero(as_tuple=True)
    arcs = {
        "sonar": batch["position"][pi],
        "R": batch["rotation"][pi],
        "range_m": batch["range_m"][bi],
        "side": si,
    }
    limits = paper_beam_limits()

    def solve(surf, solver: str, theta0=None, max_iter=None):
        return find_intersections(
            surf,
            arcs["sonar"],
            arcs["R"],
            arcs["range_m"],
            arcs["side"],
            limits,
            solver=solver,
            theta0=theta0,
            max_iter=max_iter,
            tol_m=tol_m,
        )

    use = batch["mask"] == 0

    def solve_rows(surf, solver: str, theta0=None, max_iter=None):
        # whole pings seen for the first time (``theta0`` must be None): every
        # seed_stride-th bin of a row cold, the rest from them (find_row_intersections);
        # back to the flat order of ``arcs``
        assert theta0 is None, "seeded rows are a cold solve"
        rows, valid, n_iter = find_row_intersections(
            surf,
            batch["position"],
            batch["rotation"],
            batch["range_m"],
            use,
            limits,
            settings={
                "solver": solver,
                "max_iter": max_iter,
                "tol_m": tol_m,
                "neighbour_start": True,
            },
        )
        valid = valid[pi, si, bi]
        return torch.where(valid, rows[pi, si, bi], torch.nan), valid, n_iter[pi, si, bi]

    ref_theta, ref_valid, _ = solve(surface, "newton")
    theta0 = torch.where(ref_valid, ref_theta, torch.inf)
    moved_theta, moved_valid, _ = solve(moved, "newton")
    # Gradient descent runs a fixed number of steps on the bins that never converge (no
    # crossing in the beam): give it just the steps its slowest converging bin needs.
    gd_iters = {}
    for key, surf, t0 in (("gd", surface, None), ("gd_warm", moved, theta0)):
        _, valid, n_iter = solve(surf, "gd", t0, gd_max_iter)
        gd_iters[key] = int(n_iter[valid].max()) if bool(valid.any()) else gd_max_iter
    cold, warm = (ref_theta, ref_valid), (moved_theta, moved_valid)
    runs = {
        "gd": (surface, "gd", None, gd_iters["gd"], gd_repeats, cold),
        "newton": (surface, "newton", None, None, repeats, cold),
        "secant": (surface, "secant", None, None, repeats, cold),
        "secant_seeded": (surface, "secant", None, None, repeats, cold),
        "gd_warm": (moved, "gd", theta0, gd_iters["gd_warm"], gd_repeats, warm),
        "newton_warm": (moved, "newton", theta0, None, repeats, warm),
        "secant_warm": (moved, "secant", theta0, None, repeats, warm),
    }
    labels = {
        "gd": "paper GD (eq. 12), cold",
        "newton": "Newton, cold",
        "secant": "secant (height-only), cold",
        "secant_seeded": "secant, cold, seeded rows",
        "gd_warm": "paper GD, warm",
        "newton_warm": "Newton, warm",
        "secant_warm": "secant, warm",
    }
    results: dict[str, dict[str, Any]] = {key: {} for key in runs}

    def runner(key: str) -> Callable[[], None]:
        surf, solver, t0, max_iter, _, _ = runs[key]

        def run() -> None:
            before = Counter(surf.points)
            fn = solve_rows if key.endswith("_seeded") else solve
            results[key]["out"] = fn(surf, solver, t0, max_iter)
            results[key]["points"] = Counter(surf.points) - before

        return run

    times, cpu_times = time_in_turns(
        {key: runner(key) for key in runs},
        {key: run[4] for key, run in runs.items()},
        warmup,
        dev,
    )
    detail: dict[str, dict] = {}
    figures = []
    n_bins_used = int(pi.numel())
    for key, (surf, _, _, _, _, (r_theta, r_valid)) in runs.items():
        theta, valid, n_iter = results[key]["out"]
        points = results[key]["points"]
        res = _residual_m(surf, arcs, theta)[valid].abs()
        it = n_iter[valid].float()
        detail[key] = {
            "valid": int(valid.sum()),
            "iters_mean": float(it.mean()) if it.numel() else float("nan"),
            "iters_max": int(it.max()) if it.numel() else 0,
            "heights_per_bin": points["height"] / max(n_bins_used, 1),
            "gradients_per_bin": points["gradient"] / max(n_bins_used, 1),
            "max_residual_mm": float(res.max() * 1e3) if res.numel() else float("nan"),
            **_agreement(arcs, theta, valid, r_theta, r_valid),
        }
        d = detail[key]
        figures.append(
            figure(
                f"{labels[key]}: time per batch",
                "s",
                times[key],
                f"{d['valid']} valid; evals/bin {d['iters_mean']:.1f} (max {d['iters_max']}); "
                f"surface passes/bin: {d['heights_per_bin']:.2f} heights + "
                f"{d['gradients_per_bin']:.2f} with gradient; "
                f"finds {100 * d['found_of_reference']:.1f} % of Newton's, "
                f"points within {d['max_point_diff_mm']:.1f} mm",
            )
        )
    med = {k: statistics.median(v) for k, v in times.items()}
    cpu_med = {k: statistics.median(v) for k, v in cpu_times.items()}
    pairs = {
        "gd / newton (cold)": ("gd", "newton"),
        "gd / secant (cold)": ("gd", "secant"),
        "gd / secant seeded rows (cold)": ("gd", "secant_seeded"),
        "gd / newton_warm": ("gd", "newton_warm"),
        "gd_warm / newton_warm": ("gd_warm", "newton_warm"),
        "gd_warm / secant_warm": ("gd_warm", "secant_warm"),
    }
    speedups = {name: med[a] / med[b] for name, (a, b) in pairs.items()}
    cpu_speedups = {name: cpu_med[a] / max(cpu_med[b], 1e-9) for name, (a, b) in pairs.items()}
    for name, value in speedups.items():
        note = "target >= 10x" if "(cold)" in name else ""
        figures.append(figure(f"speed-up {name}", "x", value, note))
    with torch.no_grad():
        xy = _crossing_points(arcs, torch.nan_to_num(ref_theta))[ref_valid][:, :2]
        dz = moved.height(xy) - surface.height(xy)
        _, grad = surface.height_and_gradient(xy)
    slope = grad.norm(dim=-1)
    rms_m = float(dz.pow(2).mean().sqrt())
    return {
        "title": TITLE,
        "params": {
            "n_pings": n_pings,
            "n_bins": n_bins,
            "bins_solved": n_bins_used,
            "tol_m": tol_m,
            "gd_max_iter": gd_max_iter,
            "gd_iterations_run": gd_iters,
            "siren": f"{n_layers} x {hidden}, omega0 {omega0}",
            "device": str(dev),
        },
        "figures": figures,
        "info": {
            "solvers": detail,
            "speedups": speedups,
            "cpu_time_speedups": cpu_speedups,
            "warm_start_height_change_rms_m": rms_m,
            "surface_slope_median": float(slope.median()),
            "surface_slope_p90": float(slope.quantile(0.9)),
        },
        "notes": (
            f"{n_bins_used} non-water-column bins of {n_pings} pings over a SIREN surface "
            f"(slope median {float(slope.median()):.3f}, p90 {float(slope.quantile(0.9)):.3f}), "
            f"all to |f| <= {tol_m * 1e3:g} mm. Warm: the crossings of the cold solve, on a "
            f"surface moved by {rms_m * 1e3:.1f} mm RMS. 'evals' = solver evaluations per bin "
            "(with a derivative for GD and Newton, height-only for the secant); 'surface "
            "passes' count every point through the SIREN, the cold scan's and warm brackets' "
            "heights included. Newton and secant share the cold scan (slope-bounded steps "
            "from the beam's upper edge, finder defaults). 'Seeded rows' = whole pings seen "
            "for the first time through find_row_intersections with neighbour_start: every "
            "8th bin of each ping and side scanned cold, the rest warm-started from the depth "
            "they give (the fit's first visit of a ping under siren_schedule=budget). "
            "Solvers timed in turns (round "
            "robin) so that a varying background load weighs on all alike; "
            "info.cpu_time_speedups gives the same ratios in process CPU time. Agreement vs "
            "Newton on the same surface."
        ),
    }
