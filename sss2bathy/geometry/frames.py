"""World (ENU) and vehicle (FLU) frames, attitude conversion and isotemporal arcs.

Conventions (see docs/architecture.md):

* World frame: local ENU, metres (x East, y North, z Up).
* Vehicle/sonar frame: FLU (x forward, y left = port, z up); ``p_world = s + R p_vehicle``.
* Navigation attitude: heading clockwise from North, pitch bow-up positive,
  roll starboard-down positive.  :func:`attitude_to_rotation` is the only place that
  converts attitudes.
* Side sign sigma = +1 port (index 0), -1 starboard (index 1): :func:`side_sign`.
* Isotemporal arc (paper eq. 10): ``p(theta) = s + r R [0, sigma cos theta, -sin theta]``,
  theta = depression angle below the vehicle's horizontal; in world axes
  ``p(theta) = s + r (cos theta u - sin theta w)`` with :func:`arc_basis` ``(u, w)``.
"""

from __future__ import annotations

import torch

from sss2bathy.geometry._compat import as_tensor_like, numpy_compatible

SIDE_PORT = 0
SIDE_STARBOARD = 1


@numpy_compatible
def attitude_to_rotation(
    heading: torch.Tensor, pitch: torch.Tensor, roll: torch.Tensor
) -> torch.Tensor:
    """Rotation ``R`` (vehicle FLU -> world ENU) from navigation attitude.

    Args:
        heading: ``(...)`` radians, clockwise from North.
        pitch: ``(...)`` radians, bow up positive.
        roll: ``(...)`` radians, starboard down positive.

    Returns:
        ``(..., 3, 3)`` rotation matrices with ``R = Rz(pi/2 - heading) Ry(-pitch) Rx(roll)``.

    >>> import numpy as np
    >>> R = attitude_to_rotation(np.array(0.0), np.array(0.0), np.array(0.0))
    >>> np.round(R @ np.array([1.0, 0, 0]), 6).tolist()  # forward points North
    [0.0, 1.0, 0.0]
    """
    heading, pitch, roll = torch.broadcast_tensors(
        torch.as_tensor(heading), torch.as_tensor(pitch), torch.as_tensor(roll)
    )
    if not heading.is_floating_point():
        heading, pitch, roll = heading.double(), pitch.double(), roll.double()
    yaw = torch.pi / 2 - heading
    cy, sy = torch.cos(yaw), torch.sin(yaw)
    cp, sp = torch.cos(-pitch), torch.sin(-pitch)
    cr, sr = torch.cos(roll), torch.sin(roll)
    # Rz(yaw) @ Ry(-pitch) @ Rx(roll), written out.
    r00 = cy * cp
    r01 = cy * sp * sr - sy * cr
    r02 = cy * sp * cr + sy * sr
    r10 = sy * cp
    r11 = sy * sp * sr + cy * cr
    r12 = sy * sp * cr - cy * sr
    r20 = -sp
    r21 = cp * sr
    r22 = cp * cr
    rows = [
        torch.stack([r00, r01, r02], dim=-1),
        torch.stack([r10, r11, r12], dim=-1),
        torch.stack([r20, r21, r22], dim=-1),
    ]
    return torch.stack(rows, dim=-2)


@numpy_compatible
def rotation_to_attitude(R: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Inverse of :func:`attitude_to_rotation`: ``(heading, pitch, roll)`` in radians.

    Heading is wrapped to ``[0, 2 pi)``; valid for |pitch| < 90 degrees.
    """
    R = torch.as_tensor(R)
    pitch = torch.asin(torch.clamp(R[..., 2, 0], -1.0, 1.0))  # r20 = -sin(-pitch) = sin(pitch)
    roll = torch.atan2(R[..., 2, 1], R[..., 2, 2])
    yaw = torch.atan2(R[..., 1, 0], R[..., 0, 0])
    heading = torch.remainder(torch.pi / 2 - yaw, 2 * torch.pi)
    return heading, pitch, roll


def check_rotations(R: torch.Tensor, atol: float = 1e-4) -> torch.Tensor:
    """Boolean ``(...)`` mask of matrices that are proper rotations within ``atol``."""
    R = torch.as_tensor(R).double()
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    ortho = (R.transpose(-1, -2) @ R - eye).abs().amax(dim=(-1, -2)) <= atol
    proper = (torch.linalg.det(R) - 1.0).abs() <= atol
    return ortho & proper & torch.isfinite(R).all(dim=(-1, -2))


@numpy_compatible
def side_sign(side: torch.Tensor | int, like: torch.Tensor) -> torch.Tensor:
    """Side sign ``sigma = 1 - 2 side``: +1 port (index 0), -1 starboard (index 1).

    The one definition of sigma. Exact in every floating dtype.

    Args:
        side: ``(...)`` integer side indices (0 port, 1 starboard).
        like: a floating tensor whose dtype and device the result takes.

    Returns:
        ``(...)`` sigma in ``like``'s dtype, broadcastable against ``like``.

    >>> import numpy as np
    >>> side_sign(np.array([0, 1]), np.zeros(2)).tolist()
    [1.0, -1.0]
    """
    side = torch.as_tensor(side, device=like.device)
    if side.is_floating_point():
        raise ValueError("side: expected integer side indices (0 port, 1 starboard), found floats")
    return as_tensor_like(1.0, like) - 2.0 * side.to(like.dtype)


@numpy_compatible
def arc_basis(R: torch.Tensor, side: torch.Tensor | int) -> tuple[torch.Tensor, torch.Tensor]:
    """World axes ``(u, w)`` of each head's plane: ``u = sigma R e_y``, ``w = R e_z``.

    The isotemporal arc (eq. 10) is ``p(theta) = s + r (cos(theta) u - sin(theta) w)``, and
    eq. 3's numerators are ``sigma N_v,y = N . u`` and ``N_v,z = N . w``.

    Args:
        R: ``(..., 3, 3)`` vehicle -> world rotations.
        side: ``(...)`` integer side indices, broadcastable against ``R``'s batch shape.

    Returns:
        ``u``, ``w``: ``(..., 3)`` each (``w`` may be a broadcast view).
    """
    R = torch.as_tensor(R)
    u = side_sign(side, R)[..., None] * R[..., :, 1]
    return u, R[..., :, 2].expand_as(u)


@numpy_compatible
def arc_point(
    sonar: torch.Tensor,
    R: torch.Tensor,
    range_m: torch.Tensor,
    theta: torch.Tensor,
    side: torch.Tensor | int,
) -> torch.Tensor:
    """Point of an isotemporal arc (paper eq. 10 in our frame).

    ``p = s + r R [0, sigma cos(theta), -sin(theta)] = s + r (cos(theta) u - sin(theta) w)``
    with :func:`arc_basis` ``(u, w)``.

    Args:
        sonar: ``(..., 3)`` sonar position in world ENU (m).
        R: ``(..., 3, 3)`` vehicle -> world rotation.
        range_m: ``(...)`` slant range (m).
        theta: ``(...)`` depression angle below the vehicle's horizontal (rad).
        side: ``(...)`` integer side index, 0 port (sigma = +1), 1 starboard (sigma = -1).

    Returns:
        ``(..., 3)`` world points.
    """
    u, w = arc_basis(R, side)
    d_world = u * torch.cos(theta).unsqueeze(-1) - w * torch.sin(theta).unsqueeze(-1)
    return sonar + range_m.unsqueeze(-1) * d_world


@numpy_compatible
def arc_tangent(
    R: torch.Tensor, range_m: torch.Tensor, theta: torch.Tensor, side: torch.Tensor | int
) -> torch.Tensor:
    """``dp/dtheta`` of :func:`arc_point`: ``-r (sin(theta) u + cos(theta) w)``."""
    u, w = arc_basis(R, side)
    d = -u * torch.sin(theta).unsqueeze(-1) - w * torch.cos(theta).unsqueeze(-1)
    return range_m.unsqueeze(-1) * d
