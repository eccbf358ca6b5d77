"""The draping result of one line, and its validated ``.npz`` format."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sss2bathy.survey import MASK_VALID, SurveyFormatError
from sss2bathy.survey.masks import MASK_NAMES
from sss2bathy.utils.atomic import atomic_path

DRAPED_FORMAT_VERSION = 1
_ALL_BITS = int(np.bitwise_or.reduce(np.array(list(MASK_NAMES), dtype=np.uint8)))


@dataclass
class DrapedLine:
    """Every bin of a line georeferenced on the MBES surface.

    Attributes:
        points: ``(P, 2, B, 3)`` float32 world ENU points (m) on the surface; NaN where the
            bin has no surface point (water column, shadow, no hit).
        n_lat: ``(P, 2, B)`` float32 head-plane normal component (paper eq. 3, our sign
            convention: > 0 tilted away from the sonar); NaN where there is no point.
        grazing_rad: ``(P, 2, B)`` float32 grazing angle between the incoming ray and the
            surface (rad); NaN where there is no point.
        mask: ``(P, 2, B)`` uint8, 0 valid, else the OR of ``MASK_*`` reasons. Out-of-beam
            bins keep their point and normal.
        meta: provenance (cache key, line name, input hashes); saved with the arrays.
    """

    points: np.ndarray
    n_lat: np.ndarray
    grazing_rad: np.ndarray
    mask: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float32)
        self.n_lat = np.asarray(self.n_lat, dtype=np.float32)
        self.grazing_rad = np.asarray(self.grazing_rad, dtype=np.float32)
        self.mask = np.asarray(self.mask, dtype=np.uint8)
        self.validate()

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(P, 2, B)``."""
        return self.mask.shape  # type: ignore[return-value]

    @property
    def valid(self) -> np.ndarray:
        """``(P, 2, B)`` bool, True where the mask is 0."""
        return self.mask == MASK_VALID

    def validate(self, file: Any = "draped line") -> None:
        """Raise :class:`SurveyFormatError` on inconsistent shapes or values."""
        m = self.mask
        if m.ndim != 3 or m.shape[1] != 2 or m.shape[0] < 1 or m.shape[2] < 1:
            raise SurveyFormatError(file, "mask", "shape (P, 2, B) with P, B >= 1", m.shape)
        for name in ("n_lat", "grazing_rad"):
            arr = getattr(self, name)
            if arr.shape != m.shape:
                raise SurveyFormatError(file, name, f"shape {m.shape}", arr.shape)
        if self.points.shape != (*m.shape, 3):
            raise SurveyFormatError(file, "points", f"shape {(*m.shape, 3)}", self.points.shape)
        if _values_ok_compiled(m, self.n_lat, self.points):
            return
        if np.any(m & ~np.uint8(_ALL_BITS)):
            raise SurveyFormatError(file, "mask", f"bits within {_ALL_BITS:#x}", int(m.max()))
        valid = m == MASK_VALID
        if np.any(valid & ~(np.abs(self.n_lat) <= 1.0 + 1e-5)):  # NaN fails the test
            raise SurveyFormatError(
                file, "n_lat", "finite values in [-1, 1] at valid bins", "other"
            )
        # all three coordinates finite (as isfinite(points).all(-1), without numpy's slow
        # reduction over a length-3 axis)
        finite = np.isfinite(self.points)
        finite = finite[..., 0] & finite[..., 1] & finite[..., 2]
        if np.any(valid & ~finite):
            raise SurveyFormatError(file, "points", "finite points at valid bins", "NaN/inf")

    def save(self, path: str | Path) -> None:
        """Write a compressed ``.npz`` (arrays and JSON ``meta``) atomically."""
        meta = json.dumps({"format_version": DRAPED_FORMAT_VERSION, **self.meta}, sort_keys=True)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(
                    f,
                    points=self.points,
                    n_lat=self.n_lat,
                    grazing_rad=self.grazing_rad,
                    mask=self.mask,
                    meta=np.array(meta),
                )

    @classmethod
    def load(cls, path: str | Path) -> DrapedLine:
        """Read and validate a file written by :meth:`save` (raises SurveyFormatError)."""
        path = Path(path)
        if not path.is_file():
            raise SurveyFormatError(path, "file", "an existing draped-line .npz", "missing file")
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
        except Exception as exc:  # zipfile/OSError/ValueError: report as a format error
            raise SurveyFormatError(path, "file", "a readable .npz archive", exc) from exc
        expected = {
            "points": np.float32,
            "n_lat": np.float32,
            "grazing_rad": np.float32,
            "mask": np.uint8,
        }
        for key, dtype in expected.items():
            if key not in arrays:
                raise SurveyFormatError(path, key, "an array in the archive", "missing")
            if arrays[key].dtype != dtype:
                raise SurveyFormatError(path, key, f"dtype {np.dtype(dtype)}", arrays[key].dtype)
        try:
            meta = json.loads(str(arrays["meta"])) if "meta" in arrays else {}
        except json.JSONDecodeError as exc:
            raise SurveyFormatError(path, "meta", "a JSON string", exc) from exc
        if meta.get("format_version") != DRAPED_FORMAT_VERSION:
            raise SurveyFormatError(
                path, "meta.format_version", str(DRAPED_FORMAT_VERSION), meta.get("format_version")
            )
        meta.pop("format_version")
        out = cls.__new__(cls)
        out.points, out.n_lat = arrays["points"], arrays["n_lat"]
        out.grazing_rad, out.mask, out.meta = arrays["grazing_rad"], arrays["mask"], meta
        out.validate(path)
        return out


def _values_ok_compiled(mask: np.ndarray, n_lat: np.ndarray, points: np.ndarray) -> bool:
    """:meth:`DrapedLine.validate`'s value checks in one compiled pass
    (:func:`sss2bathy.draping.kernels.draped_values_ok`): True where they pass; False
    where they fail or the pass is not run, and numpy's checks decide (and name the
    failure). Run only where draping's kernels are already loaded (a process that drapes,
    so loading a saved line does not import numba) and the arrays are C-contiguous."""
    kernels = sys.modules.get("sss2bathy.draping.kernels")
    if kernels is None or not all(a.flags.c_contiguous for a in (mask, n_lat, points)):
        return False
    # drape.BOOKKEEPING = "numpy" (the reference) turns the compiled pass off too; drape's
    # own switch, from the loaded module (drape imports this module, not the reverse)
    drape = sys.modules.get("sss2bathy.draping.drape")
    if drape is not None and not drape._use_numba():
        return False
    return bool(
        kernels.draped_values_ok(
            mask,
            n_lat,
            points,
            np.uint8(~_ALL_BITS & 0xFF),
            np.uint8(MASK_VALID),
            np.float32(1.0 + 1e-5),
        )
    )
