"""Frames, attitude, isotemporal arcs and normals (paper eq. 1-3, 10): the one home of each.

Pure, batched functions. Every function accepts torch tensors; numpy arrays are
accepted too and numpy arrays are returned for them.
"""

from sss2bathy.geometry.frames import (
    SIDE_PORT,
    SIDE_STARBOARD,
    arc_basis,
    arc_point,
    arc_tangent,
    attitude_to_rotation,
    check_rotations,
    rotation_to_attitude,
    side_sign,
)
from sss2bathy.geometry.normals import (
    grazing_angle,
    head_plane_components,
    head_plane_normal,
    head_plane_normal_from_gradient,
    head_plane_unit,
    incidence_angle,
    incidence_cosine,
    vehicle_normal,
    world_normal,
)
from sss2bathy.geometry.seabed import flat_seabed_depression

__all__ = [
    "SIDE_PORT",
    "SIDE_STARBOARD",
    "arc_basis",
    "arc_point",
    "arc_tangent",
    "attitude_to_rotation",
    "check_rotations",
    "rotation_to_attitude",
    "side_sign",
    "grazing_angle",
    "head_plane_components",
    "head_plane_normal",
    "head_plane_normal_from_gradient",
    "head_plane_unit",
    "incidence_angle",
    "incidence_cosine",
    "vehicle_normal",
    "world_normal",
    "flat_seabed_depression",
]
