"""studies/mosaic_placement: the smoothed stand-in for a reconstructed map."""

import numpy as np

from sss2bathy.survey import BathyGrid
from studies.mosaic_placement import smoothed


def test_smoothing_keeps_a_plane_and_the_holes():
    y, x = np.mgrid[0:40, 0:50].astype(np.float32)
    h = -20.0 + 0.05 * x
    out = smoothed(BathyGrid(h, 0.0, 0.0, 0.5), sigma_m=1.0)
    inner = np.ones(h.shape, bool)
    inner[:6], inner[-6:], inner[:, :6], inner[:, -6:] = False, False, False, False
    np.testing.assert_allclose(out.heights[inner], h[inner], atol=1e-3)
    holey = h.copy()
    holey[10:14, 20:25] = np.nan
    kept = smoothed(BathyGrid(holey, 0.0, 0.0, 0.5), sigma_m=1.0).heights
    assert np.array_equal(np.isnan(kept), np.isnan(holey))
    bump = np.full((40, 50), -20.0, np.float32)
    bump[20, 25] = -10.0
    assert smoothed(BathyGrid(bump, 0.0, 0.0, 0.5), 1.0).heights[20, 25] < -15.0
