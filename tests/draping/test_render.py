"""The waterfall | draped n_lat figure."""

from __future__ import annotations

import matplotlib.image as mpimg
import numpy as np
import pytest

from sss2bathy.draping import drape_line
from sss2bathy.draping.render import render_draped


def test_render_draped_png(tmp_path, make_plane, make_line):
    line = make_line(n_pings=20, n_bins=80, max_range=30.0, heading_deg=20.0)
    grid = make_plane(a=0.1, b=0.0)
    d = drape_line(line, grid)
    out = render_draped(line, d, tmp_path / "fig.png")
    img = mpimg.imread(out)
    assert img.shape[0] == 500 and img.shape[1] == 1500
    # the n_lat panel shows masked bins (water column at nadir) in black
    middle = img[:, 500:1000, :3]
    assert (middle.sum(axis=-1) < 0.05).mean() > 0.01
    with pytest.raises(ValueError, match="draped: expected shape"):
        render_draped(make_line(n_pings=3, n_bins=80), d, tmp_path / "bad.png")
    assert not (tmp_path / "bad.png").exists()
    assert np.isfinite(d.n_lat[d.valid]).all()
