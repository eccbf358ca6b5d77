"""Wreck-like objects on the synthetic terrain (``data.survey.terrain.objects``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sim_helpers import preset

from sss2bathy.sim.config import ObjectParams, SyntheticSurveyConfig
from sss2bathy.sim.generate import generate_survey
from sss2bathy.sim.sonar import MASK_SHADOW
from sss2bathy.sim.terrain import (
    generate_terrain,
    object_cells,
    object_profile,
    object_relief,
    place_objects,
)

HULL = {"kind": "hull", "x_m": 25.0, "y_m": 20.0, "length_m": 12.0, "beam_m": 4.0,
        "height_m": 2.5, "heading_deg": 90.0}  # fmt: skip


def tiny(**overrides) -> SyntheticSurveyConfig:
    return SyntheticSurveyConfig.from_mapping(preset("synthetic_d1", "tiny", **overrides))


def test_no_objects_leave_the_terrain_and_its_cache_key_as_they_were():
    plain = tiny()
    empty = tiny(terrain__objects=[])
    assert plain.terrain.objects == () and plain.hash() == empty.hash()
    assert (
        "objects" not in plain.to_dict()["terrain"] or plain.to_dict()["terrain"]["objects"] == []
    )
    with_obj = tiny(terrain__objects=[HULL])
    assert with_obj.hash() != plain.hash()
    a = generate_terrain(plain.terrain, plain.materials, np.random.default_rng(3))
    b = generate_terrain(with_obj.terrain, with_obj.materials, np.random.default_rng(3))
    # objects draw nothing: away from the hull every height, material and texture value
    # is bit for bit the same
    rows, cols, prof = object_cells(with_obj.terrain.objects[0], a.heights.shape, a.cell_m)
    away = np.ones(a.heights.shape, bool)
    away[rows, cols] = False
    assert np.array_equal(a.heights[away], b.heights[away])
    assert np.array_equal(a.materials[away], b.materials[away])
    assert np.array_equal(a.boulders, b.boulders)
    assert (b.heights[rows, cols] >= a.heights[rows, cols]).all()
    rock = plain.materials.index("rock")
    assert (b.materials[rows, cols][prof > 0.5] == rock).all()


def test_a_box_has_a_flat_top_at_its_height_above_the_lowest_seabed_under_it():
    cell = 0.25
    y, x = np.mgrid[0:161, 0:161] * cell
    seabed = -20.0 + 0.05 * x  # a slope: the base is the footprint's low end
    box = ObjectParams("box", 20.0, 20.0, 8.0, 4.0, 2.0, heading_rad=math.radians(90.0))
    out = place_objects(seabed, cell, (box,))
    inside = (np.abs(x - 20) < 3.8) & (np.abs(y - 20) < 1.8)
    base = -20.0 + 0.05 * 16.0
    np.testing.assert_allclose(out[inside], base + 2.0, atol=0.06)
    far = (np.abs(x - 20) > 5) | (np.abs(y - 20) > 3)
    assert np.array_equal(out[far], seabed[far])


def test_a_hull_narrows_to_its_bow_and_turns_with_its_heading():
    hull = ObjectParams("hull", 0.0, 0.0, 20.0, 6.0, 3.0, heading_rad=0.0)  # bow to North
    along = object_profile(hull, np.zeros(5), np.array([-9.0, 0.0, 6.0, 8.5, 9.9]))
    assert along[1] == pytest.approx(3.0) and along[0] == pytest.approx(3.0)
    # half-beam at u = 8.5 (the bow: the last 6 m, from u = 4): 3 sqrt(1 - (4.5/6)^2) = 1.98 m
    across = object_profile(hull, np.array([1.5, 2.2]), np.array([8.5, 8.5]))
    assert across[0] > 0 and across[1] == 0.0
    assert object_profile(hull, np.array([0.0]), np.array([10.5]))[0] == 0.0
    turned = ObjectParams("hull", 0.0, 0.0, 20.0, 6.0, 3.0, heading_rad=math.radians(90.0))
    assert object_profile(turned, np.array([9.0]), np.array([0.0]))[0] > 0  # long along x
    assert object_profile(turned, np.array([0.0]), np.array([9.0]))[0] == 0.0
    # near-vertical sides: 90 % of the height within the outer 15 % of the half-beam
    side = object_profile(hull, np.array([2.55]), np.array([0.0]))[0]
    assert side > 0.9 * 3.0 * 0.66


def test_object_relief_reads_the_height_above_the_surroundings():
    cell = 0.25
    y, x = np.mgrid[0:201, 0:201] * cell
    seabed = -18.0 + 0.3 * np.sin(x / 7.0)
    hull = ObjectParams("hull", 25.0, 25.0, 16.0, 5.0, 2.0, heading_rad=math.radians(30.0))
    with_hull = place_objects(seabed, cell, (hull,))
    assert object_relief(with_hull, cell, hull) == pytest.approx(2.0, abs=0.35)
    assert abs(object_relief(seabed, cell, hull)) < 0.35
    unmapped = with_hull.copy()
    unmapped[80:120, 80:120] = np.nan
    assert math.isnan(object_relief(unmapped, cell, hull))


@pytest.mark.parametrize(
    "obj, match",
    [
        ({**HULL, "kind": "raft"}, r"data\.survey\.terrain\.objects\[0\]\.kind: expected one of"),
        ({**HULL, "height_m": 0.0}, r"objects\[0\]\.height_m: expected a number > 0"),
        ({**HULL, "mast_m": 3.0}, r"objects\[0\]: unknown key\(s\) \['mast_m'\]"),
        ({**HULL, "material": "steel"}, r"objects\[0\]\.material: expected one of \['mud'"),
    ],
)
def test_bad_objects_raise_named_errors(obj, match):
    with pytest.raises(ValueError, match=match):
        tiny(terrain__objects=[obj])


def test_an_object_gets_a_bright_face_and_a_shadow_in_the_simulated_sidescan():
    """The ray-traced waterfall of a line past a 2.5 m hull: shadow bins behind it that
    the same survey without the hull does not have, and a brighter face before them."""
    plain = tiny()
    lines = generate_survey(plain)[0].split_lines("test")
    track = lines[0].position
    # the hull 7 m to the port side of the first test line, along it
    heading = math.atan2(*(track[-1, :2] - track[0, :2]))
    mid = track[len(track) // 2, :2]
    port = np.array([-math.cos(heading), math.sin(heading)])
    x, y = mid + 7.0 * port
    hull = {**HULL, "x_m": float(x), "y_m": float(y), "heading_deg": math.degrees(heading)}
    survey = generate_survey(tiny(terrain__objects=[hull]))[0]
    before, after = lines[0], survey.split_lines("test")[0]
    port_shadow = lambda ln: int(((ln.extras["true_mask"][:, 0] & MASK_SHADOW) > 0).sum())  # noqa: E731
    assert port_shadow(after) > port_shadow(before) + 20
    # the bins that hit the hull (its faces and deck, rock) are brighter than the seabed
    pts = after.extras["true_points"][:, 0]
    on = object_profile(ObjectParams("hull", x, y, 12.0, 4.0, 2.5, math.radians(hull["heading_deg"])),
                        pts[..., 0], pts[..., 1]) > 0.5  # fmt: skip
    seabed = (after.extras["true_mask"][:, 0] == 0) & ~on
    assert on.sum() > 20
    assert after.intensity[:, 0][on].mean() > 1.25 * after.intensity[:, 0][seabed].mean()
