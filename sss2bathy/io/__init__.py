"""Real survey data in and out.

* :mod:`sss2bathy.io.xtf` — XTF sidescan: ``read_xtf`` / ``write_xtf`` (pyxtf structures).
* :mod:`sss2bathy.io.bottom` — ``detect_first_return``: altitude from the waterfall.
* :mod:`sss2bathy.io.grids` — ``read_grid``: GeoTIFF / ESRI ASCII / BAG / XYZ / meshes.
* :mod:`sss2bathy.io.export` — ``write_geotiff`` / ``write_ply``: maps out.
* :mod:`sss2bathy.io.xtf_survey` — ``prepare_xtf_survey``: the ``data/survey=xtf`` source.

Submodules are imported on use (rasterio, h5py, trimesh and pyproj load only when needed).
"""
