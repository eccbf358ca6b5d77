"""GeoTIFF provenance (units, vertical reference, method, CNN checkpoint SHA-256, version,
command line) and a map grid whose cell edges fall on multiples of the cell in true
coordinates."""

from __future__ import annotations

import hashlib
import math
from types import SimpleNamespace

import numpy as np
import pytest
import rasterio

import sss2bathy
from sss2bathy.callbacks import RunHparams
from sss2bathy.callbacks.writers import map_provenance
from sss2bathy.data.normal_source import NormalSource
from sss2bathy.eval.maps import grid_over_bounds, save_map_outputs
from sss2bathy.io.export import VERTICAL_REFERENCE, provenance_tags, write_geotiff

# an XTF-like origin: a multiple of 100 m; and an odd one
ORIGINS = [
    {"crs": "EPSG:32630", "easting": 451200.0, "northing": 6123400.0},
    {"crs": "EPSG:32630", "easting": 451203.37, "northing": 6123411.91},
]


def test_every_geotiff_says_its_unit_reference_version_and_command(tmp_path, monkeypatch):
    monkeypatch.setattr("sys.argv", ["sss2bathy-map", "files=/d/a b.xtf", "scale=tiny"])
    grid = grid_over_bounds((0.0, 0.0, 20.0, 10.0), 0.5)
    grid.heights[:] = -12.5
    path = write_geotiff(grid, tmp_path / "g.tif", origin=ORIGINS[0])
    with rasterio.open(path) as src:
        tags = src.tags()
        assert src.units == ("m",) and src.descriptions == ("height (m, up)",)
    assert tags["SSS2BATHY_UNITS"] == "m"
    assert tags["SSS2BATHY_VERTICAL_REFERENCE"] == VERTICAL_REFERENCE[None]
    assert tags["SSS2BATHY_VERSION"] == sss2bathy.__version__
    assert tags["SSS2BATHY_COMMAND"] == "sss2bathy-map 'files=/d/a b.xtf' scale=tiny"
    assert tags["SSS2BATHY_FRAME"] == "projected"  # the georeferencing's own tags stay
    assert "SSS2BATHY_METHOD" not in tags and "SSS2BATHY_CNN_CHECKPOINT_SHA256" not in tags


def test_provenance_names_the_method_and_hashes_the_checkpoint(tmp_path):
    ckpt = tmp_path / "last.ckpt"
    ckpt.write_bytes(b"weights" * 1000)
    tags = provenance_tags("siren_cnn_n2d", ckpt, survey_kind="xtf", command=["x", "y=1"])
    assert tags["SSS2BATHY_METHOD"] == "siren_cnn_n2d"
    assert tags["SSS2BATHY_CNN_CHECKPOINT_SHA256"] == hashlib.sha256(ckpt.read_bytes()).hexdigest()
    assert tags["SSS2BATHY_CNN_CHECKPOINT"] == str(ckpt)
    assert "sea surface through the vehicle depth" in tags["SSS2BATHY_VERTICAL_REFERENCE"]
    assert tags["SSS2BATHY_COMMAND"] == "x y=1"


def test_map_export_carries_the_runs_provenance(tmp_path):
    """What SirenMapExport adds to map.tif: the experiment of the run's RunHparams, the CNN
    checkpoint's SHA-256 (normals from a CNN), the XTF vertical reference."""
    ckpt = tmp_path / "cnn.ckpt"
    ckpt.write_bytes(b"\x00\x01" * 500)
    trainer = SimpleNamespace(
        callbacks=[RunHparams(run={"experiment": "siren_cnn_n2d"})],
        datamodule=SimpleNamespace(
            normals=NormalSource("cnn", checkpoint=str(ckpt)), survey_cfg={"kind": "xtf"}
        ),
    )
    pred = grid_over_bounds((0.0, 0.0, 8.0, 6.0), 1.0, origin=ORIGINS[1])
    pred.heights[:] = -20.0
    paths = save_map_outputs(tmp_path / "run", pred, origin=ORIGINS[1])
    from sss2bathy.io.export import add_geotiff_tags

    add_geotiff_tags(paths["map_tif"], map_provenance(trainer))
    with rasterio.open(paths["map_tif"]) as src:
        tags = src.tags()
        assert src.units == ("m",)
    assert tags["SSS2BATHY_METHOD"] == "siren_cnn_n2d"
    assert tags["SSS2BATHY_CNN_CHECKPOINT_SHA256"] == hashlib.sha256(ckpt.read_bytes()).hexdigest()
    assert tags["SSS2BATHY_VERTICAL_REFERENCE"] == VERTICAL_REFERENCE["xtf"]
    # a SIREN without CNN normals: no checkpoint tag
    trainer.datamodule.normals = "none"
    assert "SSS2BATHY_CNN_CHECKPOINT_SHA256" not in map_provenance(trainer)


@pytest.mark.parametrize("origin", ORIGINS)
@pytest.mark.parametrize("cell", [0.5, 1.0, 0.3])
def test_map_grid_cell_edges_fall_on_multiples_of_the_cell(tmp_path, origin, cell):
    bounds = (-123.37, -40.02, 310.6, 95.4)  # local frame
    grid = grid_over_bounds(bounds, cell, origin=origin)
    xmin, ymin, xmax, ymax = grid.bounds  # cell centres
    assert xmin <= bounds[0] < xmin + cell and ymin <= bounds[1] < ymin + cell
    assert xmax >= bounds[2] and ymax >= bounds[3]
    path = write_geotiff(grid, tmp_path / "m.tif", origin=origin)
    with rasterio.open(path) as src:
        west, north = src.transform.c, src.transform.f
    for edge in (west, north):
        k = edge / cell
        assert math.isclose(k, round(k), abs_tol=1e-6), (edge, cell)
    assert grid.x0 + origin["easting"] == pytest.approx(west + cell / 2, abs=1e-6)


def test_an_already_snapped_bound_is_kept():
    grid = grid_over_bounds((10.5, 20.5, 30.0, 35.0), 1.0)
    assert (grid.x0, grid.y0) == (10.5, 20.5)
    assert np.isnan(grid.heights).all()
