"""Where a batch's isotemporal arcs cross the SIREN, and the SIREN's normals there
(paper eq. 10-12, then eq. 1-3): the geometry step of every sidescan SIREN fit.

Plain torch (no Lightning): :class:`~sss2bathy.modules.siren.SirenModule` calls
:func:`arc_geometry` once per training step, and the Lambertian waterfall figure and the
benchmarks call it through the module's ``sidescan_geometry``.

1. for every bin the sensor model can use, the depression angle where its arc crosses the
   SIREN (:func:`~sss2bathy.models.intersection.find_intersections`, under ``no_grad``),
   warm-started from the bin's previous solution (``theta_cache``, NaN = none yet,
   +inf = no crossing last time; with ``finder.neighbour_start`` a bin never solved starts
   from the solved bins of its ping and side, and a ping seen for the first time solves
   every ``finder.seed_stride``-th bin cold first:
   :func:`~sss2bathy.models.intersection.find_row_intersections`);
2. at the valid crossings, the SIREN's height gradient *with a graph*
   (:meth:`~sss2bathy.models.siren.Siren.height_and_gradient`) and the head-plane normal
   (:func:`~sss2bathy.geometry.head_plane_normal_from_gradient`, eq. 1-3), packed into an
   :class:`~sss2bathy.models.sensors.ArcGeometry` for the sensor model's loss.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from sss2bathy.geometry import arc_point, head_plane_normal_from_gradient
from sss2bathy.models.intersection import FinderSettings, find_row_intersections
from sss2bathy.models.sensors import ArcGeometry
from sss2bathy.models.siren import Siren, autocast_disabled


def arc_geometry(
    siren: Siren,
    batch: dict[str, torch.Tensor],
    use: torch.Tensor,
    theta_limits: tuple[float, float],
    finder: FinderSettings | Mapping[str, Any] | None,
    theta_cache: torch.Tensor | None = None,
) -> tuple[ArcGeometry, dict[str, torch.Tensor]]:
    """Crossings of a batch's bins with the SIREN, and the SIREN's normals there.

    Args:
        siren: the bathymetry.
        batch: ping batch (``position``, ``rotation``, ``range_m``, ``line``, ``index``).
        use: ``(P, 2, B)`` bool, the bins to use (the sensor model's ``bin_mask``).
        theta_limits: beam limits (rad).
        finder: :class:`~sss2bathy.models.intersection.FinderSettings` (or a mapping of its
            fields; missing ones take its defaults).
        theta_cache: ``(n_pings, 2, B)`` per-bin warm-start angles indexed by the batch's
            ``index`` (NaN = none yet, +inf = no crossing last time), updated in place;
            ``None`` = cold solves.

    Returns:
        ``(geo, stats)``: the valid bins' :class:`ArcGeometry` (gradient and normals with
        graph; ``geo.ping`` indexes the batch) and finder statistics (``valid_fraction``,
        ``finder_iters`` = mean solver evaluations per bin).
    """
    finder = FinderSettings.from_mapping(finder)
    warm = finder.warm_start and theta_cache is not None
    index = batch["index"]
    sonar, rot = batch["position"], batch["rotation"]
    # Geometry in float32 even under an enclosing autocast (bf16 would move crossings and
    # normals by centimetres); the SIREN picks its own precision (Siren.precision).
    with autocast_disabled(sonar.device):
        rows, valid, n_iter = find_row_intersections(
            siren,
            sonar,
            rot,
            batch["range_m"],
            use,
            theta_limits,
            theta_cache[index] if warm else None,
            settings=finder,
        )
        if warm:
            # +inf marks "no crossing": next time only the beam's ends are checked
            theta_cache[index] = rows.to(theta_cache.dtype)
        pi, si, bi = valid.nonzero(as_tuple=True)
        sonar, rot, range_m = sonar[pi], rot[pi], batch["range_m"][bi]
        theta = rows[pi, si, bi].to(sonar.dtype)
        points = arc_point(sonar, rot, range_m, theta, si)
    # the SIREN blocks its points itself (Siren.chunk: cache-sized on CPU)
    height, grad = siren.height_and_gradient(points[:, :2])
    with autocast_disabled(sonar.device):
        n_lat, n_up = head_plane_normal_from_gradient(grad[:, 0], grad[:, 1], rot, si)
    geo = ArcGeometry(
        points=points,
        theta=theta,
        range_m=range_m,
        side=si,
        sonar=sonar,
        rotation=rot,
        grad=grad,
        n_lat=n_lat,
        n_up=n_up,
        ping=pi,
        bin=bi,
        line=batch["line"][pi],
        height=height,
    )
    n_bins = use.sum().clamp_min(1)
    stats = {"valid_fraction": valid.sum() / n_bins, "finder_iters": n_iter.sum() / n_bins}
    return geo, stats


__all__ = ["arc_geometry"]
