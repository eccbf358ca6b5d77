"""The compiled fan set-up and ray cast of draping against the paths they replace, to the
bit: embree's ``rtcIntersect1`` called from compiled code on embreex's scene
(``surface.DIRECT_EMBREE``) against embreex's full-output call, the compiled fan angles
(``fan_ramps``) against the numpy ones, and ``DrapedLine.validate`` (its one-pass
compiled check against numpy's)."""

from __future__ import annotations

import numpy as np
import pytest

import sss2bathy.draping.drape as drape_mod
import sss2bathy.draping.draped as draped_mod
import sss2bathy.draping.surface as surface_mod
from sss2bathy.draping import DrapeConfig, DrapedLine, DrapeSurface, drape_line, kernels
from sss2bathy.survey import MASK_NO_HIT, SurveyFormatError
from tests.draping.test_drape_kernels import _holey_rough_grid, _line


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a).view(np.uint8)


@pytest.fixture(scope="module")
def surface() -> DrapeSurface:
    return DrapeSurface.from_grid(_holey_rough_grid())


def test_direct_embree_cast_matches_embreex(monkeypatch, surface):
    if surface.engine != "embree":
        pytest.skip("embree not available")
    rs = np.random.default_rng(2)
    K, M = 40, 300
    origins = np.column_stack([rs.uniform(-30, 30, K), rs.uniform(-30, 30, K), np.full(K, -11.0)])
    t = rs.uniform(-0.2, 3.3, (K, M))  # some rays upwards or off the grid: misses
    az = rs.uniform(0, 2 * np.pi, (K, 1))
    d = np.stack([np.cos(t) * np.cos(az), np.cos(t) * np.sin(az), -np.sin(t)], -1)
    d = d.reshape(-1, 3).astype(np.float32)
    monkeypatch.setattr(surface_mod, "DIRECT_EMBREE", False)
    want_tri, want = surface.cast(origins, d, repeat=M, distances=True)
    monkeypatch.setattr(surface_mod, "DIRECT_EMBREE", True)
    tri, dist = surface.cast(origins, d, repeat=M, distances=True)
    assert surface.intersector._handle, "the direct call should be available here"
    assert (want_tri < 0).any() and (want_tri >= 0).mean() > 0.5
    assert tri.dtype == want_tri.dtype and dist.dtype == want.dtype
    np.testing.assert_array_equal(tri, want_tri)
    np.testing.assert_array_equal(_bits(dist), _bits(want))


def test_drape_line_same_bits_with_and_without_direct_embree(monkeypatch, surface):
    line = _line()
    monkeypatch.setattr(surface_mod, "DIRECT_EMBREE", False)
    ref = drape_line(line, surface)
    monkeypatch.setattr(surface_mod, "DIRECT_EMBREE", True)
    got = drape_line(line, surface, DrapeConfig(pings_per_chunk=5))
    for name in ("points", "n_lat", "grazing_rad", "mask"):
        np.testing.assert_array_equal(_bits(getattr(got, name)), _bits(getattr(ref, name)))


def test_compiled_fan_angles_match_numpy(monkeypatch, surface):
    line = _line()
    range_m = line.range_m.astype(np.float64)
    fan = drape_mod._Fan(line, surface, range_m, float(np.diff(range_m)[0]), DrapeConfig())
    ramps = []
    compiled = kernels.fan_ramps

    def spy(*args):
        ramps.append(True)
        return compiled(*args)

    monkeypatch.setattr(kernels, "fan_ramps", spy)
    monkeypatch.setattr(drape_mod, "BOOKKEEPING", "numpy")
    ref = fan.angles(slice(2, 13))
    assert not ramps
    monkeypatch.setattr(drape_mod, "BOOKKEEPING", "numba")
    got = fan.angles(slice(2, 13))
    assert ramps
    assert np.all(np.diff(got, axis=-1) >= 0)
    np.testing.assert_array_equal(_bits(got), _bits(ref))


def _draped(P: int = 3, B: int = 5) -> dict[str, np.ndarray]:
    rs = np.random.default_rng(0)
    return {
        "points": rs.normal(size=(P, 2, B, 3)).astype(np.float32),
        "n_lat": rs.uniform(-1, 1, (P, 2, B)).astype(np.float32),
        "grazing_rad": rs.uniform(0, 1, (P, 2, B)).astype(np.float32),
        "mask": np.zeros((P, 2, B), np.uint8),
    }


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("coord", [0, 1, 2])
def test_validate_rejects_any_non_finite_coordinate_at_valid_bins(value, coord):
    arrays = _draped()
    arrays["points"][1, 0, 2, coord] = value
    with pytest.raises(SurveyFormatError, match="points"):
        DrapedLine(**arrays)
    arrays["mask"][1, 0, 2] = MASK_NO_HIT  # not a valid bin: allowed
    DrapedLine(**arrays)


def _numpy_validate_passes(monkeypatch, arrays: dict[str, np.ndarray]) -> bool:
    with monkeypatch.context() as m:
        m.setattr(draped_mod, "_values_ok_compiled", lambda *a: False)
        try:
            DrapedLine(**arrays)
        except SurveyFormatError:
            return False
    return True


def _bad_cases() -> list[tuple[str, tuple, float]]:
    lim = np.float32(1.0 + 1e-5)  # numpy compares float32 |n_lat| with it in float32
    above = np.nextafter(lim, np.float32(2.0))
    return [
        ("mask", (1, 0, 2), 64),
        ("mask", (2, 1, 4), 0x80 | MASK_NO_HIT),
        *[("n_lat", (0, 1, 3), x) for x in (np.nan, np.inf, -2.0, lim, -lim, above, -above)],
        *[("points", (1, 1, 1, c), x) for c in range(3) for x in (np.nan, np.inf, -np.inf)],
    ]


@pytest.mark.parametrize("invalid_bin", [False, True])
@pytest.mark.parametrize("case", range(len(_bad_cases())))
def test_compiled_validate_agrees_with_numpy(monkeypatch, case, invalid_bin):
    # the one-pass compiled check decides exactly where numpy's checks pass
    name, idx, value = _bad_cases()[case]
    arrays = _draped()
    arrays[name][idx] = value
    if invalid_bin and name != "mask":
        arrays["mask"][idx[:3]] = MASK_NO_HIT  # not a valid bin: anything goes
    want = _numpy_validate_passes(monkeypatch, arrays)
    a = {k: np.asarray(v) for k, v in arrays.items()}
    assert draped_mod._values_ok_compiled(a["mask"], a["n_lat"], a["points"]) == want
    if want:
        DrapedLine(**arrays)
    else:
        with pytest.raises(SurveyFormatError, match=name):
            DrapedLine(**arrays)


def test_compiled_validate_runs_only_where_it_can(monkeypatch):
    a = _draped()
    assert draped_mod._values_ok_compiled(a["mask"], a["n_lat"], a["points"])  # kernels loaded
    strided = np.asfortranarray(a["n_lat"])
    assert not draped_mod._values_ok_compiled(a["mask"], strided, a["points"])
    DrapedLine(a["points"], strided, a["grazing_rad"], a["mask"])  # numpy decides
    monkeypatch.setattr(drape_mod, "BOOKKEEPING", "numpy")
    assert not draped_mod._values_ok_compiled(a["mask"], a["n_lat"], a["points"])


def test_mid_rays_match_numpy():
    rs = np.random.default_rng(3)
    K, n = 20, 500
    u = rs.normal(size=(K, 6))[:, ::2]  # strided, like fan slices may be
    v, s = rs.normal(size=(K, 3)), rs.normal(size=(K, 3)) * 100
    k_c = np.sort(rs.integers(0, K, n))
    t = rs.uniform(-0.5, 2.0, n).astype(np.float32)
    cos_t, sin_t = np.cos(t), np.sin(t)
    origins, dirs = kernels.mid_rays(cos_t, sin_t, k_c, u, v, s)
    want = (cos_t[:, None] * u[k_c] + sin_t[:, None] * v[k_c]).astype(np.float32)
    np.testing.assert_array_equal(origins, s[k_c])
    assert dirs.dtype == np.float32
    np.testing.assert_array_equal(_bits(dirs), _bits(want))


def test_benchmark_direct_cast_runs_on_recorded_rays(surface):
    from benchmarks.draping import direct_cast, record_rays

    batches = record_rays(_line(n_pings=4), surface, DrapeConfig(pings_per_chunk=2))
    cast = direct_cast(surface, batches)
    if surface.engine != "embree":
        assert cast is None
        return
    assert cast is not None
    cast()


def test_scene_pointer_refuses_objects_it_does_not_recognise():
    class Fake:
        is_committed = 1

        def run(self, *args, **kwargs):  # pragma: no cover - not reached
            raise AssertionError("not an embree scene")

    class Holder:
        scene = Fake()

    assert surface_mod._embree_scene_pointer(Holder()) == 0
    del Fake.is_committed
    assert surface_mod._embree_scene_pointer(Holder()) == 0
