"""The occlusion term: which crossings a sonar sees along a ping, and which way its gradient
moves the bathymetry."""

from __future__ import annotations

import math

import torch

from sss2bathy.losses.shadow import (
    depression_angle,
    extended_shadow,
    occluding_angle,
    occlusion_loss,
)

ALTITUDE = 10.0


def _profile(heights: list[float]) -> tuple[torch.Tensor, ...]:
    """One ping's starboard side over ground ranges 2, 4, 6, ... m, sonar at 10 m."""
    n = len(heights)
    y = torch.arange(1, n + 1, dtype=torch.float64) * 2.0
    points = torch.stack([torch.zeros(n, dtype=torch.float64), y, torch.zeros_like(y)], -1)
    sonar = torch.tensor([[0.0, 0.0, ALTITUDE]], dtype=torch.float64).expand(n, 3)
    height = torch.tensor(heights, dtype=torch.float64, requires_grad=True)
    index = torch.zeros(n, dtype=torch.long)
    return points, sonar, height, index, index + 1, torch.arange(n)


def test_a_flat_seabed_is_seen_everywhere_and_an_object_hides_what_is_behind_it():
    points, sonar, height, ping, side, bins = _profile([0.0] * 8)
    angle = depression_angle(points, height, sonar)
    assert math.isclose(float(angle[0].detach()), math.atan2(ALTITUDE, 2.0))
    occluder = occluding_angle(angle, ping, side, bins, (1, 2, 8))
    assert math.isinf(float(occluder[0]))
    assert bool((angle[1:] < occluder[1:]).all())  # every crossing seen
    # a 5 m object at 6 m hides the seabed up to 12 m behind it (10 / (10 - 5) x 6 m)
    points, sonar, height, ping, side, bins = _profile([0, 0, 5, 0, 0, 0, 0, 0])
    angle = depression_angle(points, height, sonar)
    hidden = angle > occluding_angle(angle, ping, side, bins, (1, 2, 8))
    assert hidden.tolist() == [False, False, False, True, True, False, False, False]


def test_the_loss_is_zero_when_the_shadows_match_and_raises_the_object_when_they_do_not():
    shadow = torch.tensor([False, False, False, True, True, False, False, False])
    points, sonar, height, ping, side, bins = _profile([0, 0, 5, 0, 0, 0, 0, 0])
    angle = depression_angle(points, height, sonar)
    loss, logs = occlusion_loss(angle, ping, side, bins, shadow, (1, 2, 8))
    assert float(loss) == 0.0 and float(logs["shadow_seen"]) == 0.0
    assert float(logs["lit_hidden"]) == 0.0
    # the same shadow over a flat fit: violated, and the gradient raises the bin in front
    points, sonar, height, ping, side, bins = _profile([0.0] * 8)
    angle = depression_angle(points, height, sonar)
    loss, logs = occlusion_loss(angle, ping, side, bins, shadow, (1, 2, 8))
    assert float(loss) > 0 and float(logs["shadow_seen"]) == 1.0
    loss.backward()
    assert float(height.grad[2]) < 0  # descending the loss raises the object's bin
    assert float(height.grad[4]) > 0  # ... and lowers the last shadowed bin (bin 3 is
    # both shadowed and, for bin 4, the occluder: its two pulls cancel)
    # lit bins hidden by too high an object are violations too
    points, sonar, height, ping, side, bins = _profile([0, 0, 9, 0, 0, 0, 0, 0])
    angle = depression_angle(points, height, sonar)
    loss, logs = occlusion_loss(angle, ping, side, bins, shadow, (1, 2, 8))
    assert float(loss) > 0 and float(logs["lit_hidden"]) > 0


def test_pings_and_sides_do_not_occlude_each_other():
    points, sonar, height, ping, side, bins = _profile([0, 0, 5, 0])
    angle = depression_angle(points, height, sonar)
    # the same four crossings split over two pings: ping 1's first bin has no occluder (ping
    # 0's crossings are not along its line of sight), its second is occluded by its first
    ping = torch.tensor([0, 0, 1, 1])
    bins = torch.tensor([0, 1, 0, 1])
    occluder = occluding_angle(angle, ping, side, bins, (2, 2, 2))
    assert math.isinf(float(occluder[2])) and float(occluder[3]) == float(angle[2])
    assert float(occluder[1]) == float(angle[0])


def test_a_shadow_is_a_run_of_bins_not_a_dark_speckle():
    s = torch.tensor([[0, 1, 0, 1, 1, 0, 1, 1, 1, 1, 0, 1]], dtype=torch.bool)
    assert extended_shadow(s, 3).int().tolist() == [[0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 0, 0]]
    assert extended_shadow(s, 2).int().tolist() == [[0, 0, 0, 1, 1, 0, 1, 1, 1, 1, 0, 0]]
    assert torch.equal(extended_shadow(s, 1), s) and torch.equal(extended_shadow(s, 0), s)
    assert not extended_shadow(s, 13).any()  # longer than the row
