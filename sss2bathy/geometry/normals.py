"""Surface normals of height fields in world, vehicle and head-plane form (paper eq. 1-3)."""

from __future__ import annotations

import torch

from sss2bathy.geometry._compat import numpy_compatible
from sss2bathy.geometry.frames import side_sign


@numpy_compatible
def world_normal(dzdx: torch.Tensor, dzdy: torch.Tensor) -> torch.Tensor:
    """Unnormalised world normal of a height field, ``N = [-dz/dx, -dz/dy, 1]`` (eq. 1).

    Args:
        dzdx, dzdy: ``(...)`` height gradients (m/m).

    Returns:
        ``(..., 3)`` normals (not unit length; divide by the norm when needed).
    """
    return torch.stack([-dzdx, -dzdy, torch.ones_like(dzdx)], dim=-1)


@numpy_compatible
def vehicle_normal(normal_world: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """Normal in the vehicle/sonar frame, ``N_v = R^T N`` (eq. 2). Shapes ``(..., 3)``, ``(..., 3, 3)``."""
    return (R.transpose(-1, -2) @ normal_world.unsqueeze(-1)).squeeze(-1)


@numpy_compatible
def head_plane_unit(
    lat: torch.Tensor, up: torch.Tensor, eps: float = 1e-12
) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 3's normalisation: ``(n_lat, n_up) = (lat, up) / max(|(lat, up)|, eps)``.

    ``lat = sigma N_v,y`` and ``up = N_v,z`` are the normal's components along the head
    plane's axes (:func:`~sss2bathy.geometry.arc_basis`: ``N . u`` and ``N . w``), in any
    length. NaN stays NaN. Shapes ``(...)`` each.
    """
    norm = torch.sqrt(lat * lat + up * up).clamp_min(eps)
    return lat / norm, up / norm


@numpy_compatible
def head_plane_normal(
    normal_vehicle: torch.Tensor, side: torch.Tensor | int, eps: float = 1e-12
) -> tuple[torch.Tensor, torch.Tensor]:
    """2D unit normal in the head's plane, ``(n_lat, n_up) = normalize(sigma N_v,y, N_v,z)`` (eq. 3).

    ``n_lat`` > 0: surface tilted away from the sonar (darker); < 0: facing it (brighter).
    The same value means the same thing on both heads.

    Args:
        normal_vehicle: ``(..., 3)`` normal in the vehicle frame (any length).
        side: ``(...)`` integer side index (0 port, 1 starboard).

    Returns:
        ``n_lat``, ``n_up``, each ``(...)``.
    """
    lat = side_sign(side, normal_vehicle[..., 1]) * normal_vehicle[..., 1]
    return head_plane_unit(lat, normal_vehicle[..., 2], eps)


@numpy_compatible
def head_plane_components(
    normal_world: torch.Tensor, u: torch.Tensor, w: torch.Tensor, eps: float = 1e-12
) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 2-3 through the head plane's world axes: ``normalize(N . u, N . w)``.

    With ``(u, w)`` of :func:`~sss2bathy.geometry.arc_basis` (``sigma R e_y``, ``R e_z``)
    this is :func:`head_plane_normal` of ``R^T N`` without forming ``R^T N``: cheaper for
    many normals that share few rotations. Shapes ``(..., 3)`` each; returns ``(...)``.
    """
    return head_plane_unit((normal_world * u).sum(-1), (normal_world * w).sum(-1), eps)


@numpy_compatible
def head_plane_normal_from_gradient(
    dzdx: torch.Tensor, dzdy: torch.Tensor, R: torch.Tensor, side: torch.Tensor | int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 1 -> 2 -> 3 in one call: head-plane ``(n_lat, n_up)`` from height gradients."""
    return head_plane_normal(vehicle_normal(world_normal(dzdx, dzdy), R), side)


@numpy_compatible
def incidence_cosine(
    normal_world: torch.Tensor, point: torch.Tensor, sonar: torch.Tensor
) -> torch.Tensor:
    """Cosine of the incidence angle: ``N . (s - p) / max(|N| |s - p|, 1e-12)``, unclamped.

    1 when the sonar looks straight down the normal; < 0 for a back-facing hit (in
    shadow). ``normal_world`` any length. Shapes ``(..., 3)``; returns ``(...)``. Taken
    from the dot product directly, so its gradient is finite head-on (where that of
    :func:`incidence_angle` is not).
    """
    to_sonar = sonar - point
    return (normal_world * to_sonar).sum(-1) / (
        torch.linalg.vector_norm(normal_world, dim=-1) * torch.linalg.vector_norm(to_sonar, dim=-1)
    ).clamp_min(1e-12)


@numpy_compatible
def incidence_angle(
    normal_world: torch.Tensor, point: torch.Tensor, sonar: torch.Tensor
) -> torch.Tensor:
    """Angle (rad) between the surface normal and the direction from ``point`` to ``sonar``.

    0 when the sonar looks straight down the normal; > pi/2 when the surface faces away
    (a back-facing hit, i.e. in shadow). Shapes ``(..., 3)``; returns ``(...)``.
    """
    return torch.acos(incidence_cosine(normal_world, point, sonar).clamp(-1.0, 1.0))


@numpy_compatible
def grazing_angle(
    normal_world: torch.Tensor, point: torch.Tensor, sonar: torch.Tensor
) -> torch.Tensor:
    """Grazing angle (rad) between the incoming ray and the local surface: ``pi/2 - incidence``."""
    return torch.pi / 2 - incidence_angle(normal_world, point, sonar)
