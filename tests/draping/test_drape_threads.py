"""Draping a line's chunks on several threads (``DrapeConfig.threads``): the same bits as
one thread on every path (embree's direct call or embreex's own call, compiled or numpy
bookkeeping, grid or mesh normals), errors from a chunk reach the caller, and the
field's validation."""

from __future__ import annotations

import threading

import numpy as np
import pytest

import sss2bathy.draping.drape as drape_mod
import sss2bathy.draping.surface as surface_mod
from sss2bathy.draping import DrapeConfig, DrapeSurface, drape_line
from sss2bathy.draping.config import AUTO_THREADS_MAX
from sss2bathy.draping.drape import _chunks
from tests.draping.test_drape_kernels import _holey_rough_grid, _line

FIELDS = ("points", "n_lat", "grazing_rad", "mask")


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a).view(np.uint8)


@pytest.fixture(scope="module")
def grid_surface() -> DrapeSurface:
    return DrapeSurface.from_grid(_holey_rough_grid())


@pytest.fixture(scope="module")
def line():
    return _line(n_pings=23)  # 8 chunks of 2-3 pings at 3 per chunk (9 on 3 threads)


def _spy_threads(monkeypatch) -> set[str]:
    """Record the names of the threads that drape chunks."""
    names: set[str] = set()
    chunk = drape_mod._drape_chunk

    def spy(*args, **kwargs):
        names.add(threading.current_thread().name)
        return chunk(*args, **kwargs)

    monkeypatch.setattr(drape_mod, "_drape_chunk", spy)
    return names


@pytest.mark.parametrize(
    ("direct", "bookkeeping", "mesh"),
    [
        (True, "numba", False),
        (False, "numba", False),
        (True, "numpy", False),
        (True, "numba", True),
    ],
)
def test_threads_give_the_same_bits(monkeypatch, grid_surface, line, direct, bookkeeping, mesh):
    surface = DrapeSurface.from_mesh(grid_surface.mesh) if mesh else grid_surface
    monkeypatch.setattr(surface_mod, "DIRECT_EMBREE", direct)
    monkeypatch.setattr(drape_mod, "BOOKKEEPING", bookkeeping)
    ref = drape_line(line, surface, DrapeConfig(pings_per_chunk=3, threads=1))
    names = _spy_threads(monkeypatch)
    got = drape_line(line, surface, DrapeConfig(pings_per_chunk=3, threads=3))
    if surface.engine == "embree":
        assert len(names) > 1 and all(n.startswith("drape") for n in names), names
    assert (ref.mask == 0).mean() > 0.3 and len(np.unique(ref.mask)) >= 4
    assert np.isnan(ref.n_lat).any()
    for name in FIELDS:
        a, b = getattr(got, name), getattr(ref, name)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        np.testing.assert_array_equal(_bits(a), _bits(b), name)
        np.testing.assert_array_equal(a, b, name)  # NaN positions included


@pytest.mark.parametrize(
    ("n_pings", "per_chunk", "threads", "sizes"),
    [
        (1000, 32, 1, {31: 24, 32: 8}),
        (1000, 32, 2, {31: 24, 32: 8}),
        (100, 32, 2, {25: 4}),
        (100, 32, 3, {16: 2, 17: 4}),
        (23, 3, 3, {2: 4, 3: 5}),
        (5, 32, 4, {5: 1}),
        (3, 1, 4, {1: 3}),
        (0, 32, 2, {}),
    ],
)
def test_chunks_cover_the_line_in_equal_shares(n_pings, per_chunk, threads, sizes):
    chunks = _chunks(n_pings, per_chunk, threads)
    assert [c.start for c in chunks[1:]] == [c.stop for c in chunks[:-1]]
    assert (chunks[0].start, chunks[-1].stop) == (0, n_pings) if chunks else n_pings == 0
    got = [c.stop - c.start for c in chunks]
    assert {s: got.count(s) for s in set(got)} == sizes


def test_one_thread_and_single_chunk_use_no_pool(monkeypatch, grid_surface, line):
    names = _spy_threads(monkeypatch)
    drape_line(line, grid_surface, DrapeConfig(pings_per_chunk=3, threads=1))
    drape_line(line, grid_surface, DrapeConfig(pings_per_chunk=64, threads=4))
    assert names == {threading.current_thread().name}


def test_an_error_in_a_chunk_reaches_the_caller(monkeypatch, grid_surface, line):
    chunk = drape_mod._drape_chunk

    def failing(surf, fan, sl, *args):
        if sl.start <= 9 < sl.stop:
            raise RuntimeError("ping 9 failed")
        return chunk(surf, fan, sl, *args)

    monkeypatch.setattr(drape_mod, "_drape_chunk", failing)
    with pytest.raises(RuntimeError, match="ping 9 failed"):
        drape_line(line, grid_surface, DrapeConfig(pings_per_chunk=3, threads=2))


@pytest.mark.parametrize("bad", [0, -2, 1.5, 2.0, True, "many", "", None])
def test_threads_validation(bad):
    with pytest.raises(ValueError, match=r"^drape\.threads: expected a positive integer or "):
        DrapeConfig(threads=bad)
    with pytest.raises(ValueError, match=r"found " + repr(bad).replace(".", r"\.")):
        DrapeConfig.coerce({"threads": bad})


def test_threads_count_and_cache_dict():
    assert 1 <= DrapeConfig().n_threads() <= AUTO_THREADS_MAX
    # auto follows torch's thread count (torch_threads=1 when jobs share a CPU)
    import torch

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        assert DrapeConfig().n_threads() == 1
        assert DrapeConfig(threads=3).n_threads() == 3  # an explicit count is kept
    finally:
        torch.set_num_threads(before)
    assert DrapeConfig(threads=7).n_threads() == 7
    assert DrapeConfig(threads=1).cache_dict() == DrapeConfig(threads="auto").cache_dict()
    assert "threads" not in DrapeConfig().cache_dict()


def test_benchmark_split_casts_and_thread_figures(grid_surface):
    from benchmarks.draping import bench_drape, count_rays, record_rays, split_cast

    batches = record_rays(_line(n_pings=4), grid_surface, DrapeConfig(pings_per_chunk=2))
    for direct in (False, True):
        split = split_cast(grid_surface, batches, 3, direct=direct)
        assert split is not None
        cast, close = split
        cast()
        close()
    assert count_rays(batches) > 0
    doc = bench_drape(n_pings=12, n_bins=32, cell_m=4.0, warmup=0, repeats=1, threads=2)
    names = {f["name"] for f in doc["figures"]}
    assert doc["params"]["threads"] == 2
    assert {
        "draping speed-up, 2 threads / 1 thread",
        "draping / raw embree, 2 threads",
        "draping / direct embree, 2 threads",
        "draping / raw throughput",
    } <= names
    one = bench_drape(n_pings=12, n_bins=32, cell_m=4.0, warmup=0, repeats=1, threads=1)
    assert not any("threads" in f["name"] for f in one["figures"])
