"""studies/map_products_figure: the three panels from a map run's GeoTIFFs, and the one-line
error for a run that lacks one."""

from __future__ import annotations

import numpy as np
import rasterio
from rasterio.transform import from_origin

from studies.map_products_figure import main, read_band


def _tif(path, values, nodata=-9999.0):
    with rasterio.open(
        path, "w", driver="GTiff", height=values.shape[0], width=values.shape[1], count=1,
        dtype="float32", crs="EPSG:32619", transform=from_origin(512600.0, 5365900.0, 0.5, 0.5),
        nodata=nodata,
    ) as dst:  # fmt: skip
        dst.write(values.astype(np.float32), 1)


def test_three_panels_from_a_run_and_a_missing_layer(tmp_path, capsys):
    y, x = np.mgrid[0:40, 0:60]
    heights = -25.0 + 0.02 * x - 0.01 * y
    heights[:, :5] = -9999.0  # nodata
    _tif(tmp_path / "map.tif", heights)
    _tif(tmp_path / "mosaic.tif", np.random.default_rng(0).uniform(0.2, 1.8, (40, 60)))
    _tif(tmp_path / "uncertainty.tif", 0.1 + 0.01 * x)
    band, extent, cell = read_band(tmp_path / "map.tif")
    assert np.isnan(band[:, :5]).all() and np.isfinite(band[:, 5:]).all()
    assert extent == (512600.0, 512630.0, 5365880.0, 5365900.0) and cell == 0.5
    out = tmp_path / "fig.png"
    assert main([str(tmp_path), str(out)]) == 0 and out.stat().st_size > 10_000
    (tmp_path / "uncertainty.tif").unlink()
    assert main([str(tmp_path), str(out)]) == 2
    assert "uncertainty.tif" in capsys.readouterr().err
