"""Flat-seabed geometry of the isotemporal arcs (numpy in, numpy out).

Used by the sonar-only masks (``data.masks``) and by the XTF import's check of the sonar
settings against the data (``io.xtf_checks``), which sits below ``data`` in the layering.
"""

from __future__ import annotations

import numpy as np

from sss2bathy.geometry.frames import arc_basis

__all__ = ["flat_seabed_depression"]


def flat_seabed_depression(
    range_m: np.ndarray, altitude_m: np.ndarray, rotation: np.ndarray
) -> np.ndarray:
    """``(P, 2, B)`` depression angle (rad) at which each bin's arc meets a flat seabed.

    The seabed is horizontal, ``altitude_m`` below the sonar. In the head plane the arc is
    ``p(theta) = s + r R [0, sigma cos(theta), -sin(theta)]`` (side 0 port sigma = +1, side 1
    starboard -1); the crossing on the head's own side (``cos(theta) > 0``) solves
    ``r (sigma R_zy cos(theta) - R_zz sin(theta)) = -altitude``. NaN where the arc does
    not reach the seabed (``r`` below the altitude, or no altitude).
    """
    r = np.asarray(range_m, np.float64)[None, None, :]
    h = np.asarray(altitude_m, np.float64)[:, None, None]
    rot = np.asarray(rotation, np.float64)
    u, w = arc_basis(rot[:, None], np.array([0, 1]))
    a = u[..., 2][:, :, None]
    b = -w[..., 2][:, :, None]
    rho = np.hypot(a, b)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = -h / r / rho
        phi = np.arctan2(b, a)
        dev = np.arccos(np.where(np.abs(c) <= 1, c, np.nan))
    roots = [np.angle(np.exp(1j * (phi + s * dev))) for s in (1.0, -1.0)]
    # the crossing on the head's own side: the larger cos(theta)
    return np.where(np.cos(roots[0]) >= np.cos(roots[1]), roots[0], roots[1])
