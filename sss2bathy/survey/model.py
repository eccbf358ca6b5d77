"""Sidescan lines, altimeter points and surveys, with validation and a folder format.

On disk a survey is a folder::

    survey.yaml          manifest: name, origin, sensor, lines, splits, metadata
    lines/<name>.npz     one compressed file per line (arrays below)
    grid.tif             the MBES grid as GeoTIFF (optional), in projected coordinates
                         (local + origin) with the origin's CRS; ``grid_frame`` in the
                         manifest says so (folders without it hold a local-frame grid.tif)

Waterfalls are ``intensity[ping, side, bin]`` with side 0 = port, 1 = starboard and
bin 0 nearest the sonar on both sides.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sss2bathy.geometry.frames import check_rotations
from sss2bathy.survey.errors import SurveyFormatError
from sss2bathy.survey.grid import BathyGrid
from sss2bathy.utils.atomic import atomic_path, atomic_write_text

FORMAT_VERSION = 1

# Per-ping origin of ``SidescanLine.altitude_m`` (``altitude_source``).
ALTITUDE_RECORDED, ALTITUDE_DETECTED, ALTITUDE_INTERPOLATED, ALTITUDE_MISSING = 0, 1, 2, 3
GRID_FRAMES = ("projected", "local")
"""Frames a survey's ``grid.tif`` can be in (manifest ``grid_frame``; absent = ``local``)."""


@dataclass(frozen=True)
class SensorParams:
    """Sidescan sensor description (SI units).

    Attributes:
        tilt_rad: depression angle of the beam axis below the vehicle's horizontal.
        beam_width_rad: full vertical beam width alpha.
        frequency_hz: acoustic frequency.
        sound_speed_mps: isovelocity sound speed.
    """

    tilt_rad: float = math.radians(30.0)
    beam_width_rad: float = math.radians(60.0)
    frequency_hz: float = 850e3
    sound_speed_mps: float = 1500.0

    def __post_init__(self) -> None:
        if not (0.0 < self.beam_width_rad < math.pi):
            raise SurveyFormatError(
                "sensor", "beam_width_rad", "a value in (0, pi)", self.beam_width_rad
            )
        if not (-math.pi / 2 <= self.tilt_rad <= math.pi / 2):
            raise SurveyFormatError("sensor", "tilt_rad", "a value in [-pi/2, pi/2]", self.tilt_rad)
        if not self.frequency_hz > 0:
            raise SurveyFormatError("sensor", "frequency_hz", "> 0", self.frequency_hz)
        if not self.sound_speed_mps > 0:
            raise SurveyFormatError("sensor", "sound_speed_mps", "> 0", self.sound_speed_mps)

    @property
    def beam_limits_rad(self) -> tuple[float, float]:
        """``(theta_min, theta_max)`` of the vertical beam, depression angles."""
        return (
            self.tilt_rad - self.beam_width_rad / 2,
            self.tilt_rad + self.beam_width_rad / 2,
        )


@dataclass
class SidescanLine:
    """One survey line of sidescan with its navigation.

    Attributes:
        name: unique line name.
        time_s: ``(P,)`` strictly increasing ping times (s).
        position: ``(P, 3)`` sonar position in world ENU (m).
        rotation: ``(P, 3, 3)`` vehicle -> world rotations.
        altitude_m: ``(P,)`` altitude above the seafloor (m); NaN where missing.
        intensity: ``(P, 2, B)`` waterfalls, side 0 port / 1 starboard, bin 0 nearest.
        range_m: ``(B,)`` slant range per bin (m), positive and increasing.
        sensor: sensor parameters.
        extras: optional named per-ping/per-bin arrays (e.g. the simulator's ground truth
            ``true_n_lat (P, 2, B)``, ``true_points (P, 2, B, 3)``); saved with the line.
        altitude_source: optional ``(P,)`` uint8 origin of each altitude: ``ALTITUDE_RECORDED``
            (altimeter), ``_DETECTED`` (first bottom return), ``_INTERPOLATED`` (between
            detected pings) or ``_MISSING`` (altitude NaN); saved with the line.
    """

    name: str
    time_s: np.ndarray
    position: np.ndarray
    rotation: np.ndarray
    altitude_m: np.ndarray
    intensity: np.ndarray
    range_m: np.ndarray
    sensor: SensorParams = field(default_factory=SensorParams)
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    altitude_source: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.altitude_source is not None:
            self.altitude_source = np.asarray(self.altitude_source)
        self.time_s = np.asarray(self.time_s, dtype=np.float64)
        self.position = np.asarray(self.position, dtype=np.float64)
        self.rotation = np.asarray(self.rotation, dtype=np.float64)
        self.altitude_m = np.asarray(self.altitude_m, dtype=np.float32)
        self.intensity = np.asarray(self.intensity, dtype=np.float32)
        self.range_m = np.asarray(self.range_m, dtype=np.float32)
        self.validate()

    @property
    def n_pings(self) -> int:
        return int(self.time_s.shape[0])

    @property
    def n_bins(self) -> int:
        return int(self.range_m.shape[0])

    @property
    def port(self) -> np.ndarray:
        """``(P, B)`` port waterfall."""
        return self.intensity[:, 0]

    @property
    def starboard(self) -> np.ndarray:
        """``(P, B)`` starboard waterfall."""
        return self.intensity[:, 1]

    def validate(self, file: Any = None) -> None:
        """Raise :class:`SurveyFormatError` on the first inconsistency; repairs nothing."""
        src = file or f"line '{self.name}'"
        P = self.time_s.shape[0] if self.time_s.ndim == 1 else -1
        if self.time_s.ndim != 1 or P < 1:
            raise SurveyFormatError(src, "time_s", "a 1D array of >= 1 ping", self.time_s.shape)
        if not np.all(np.isfinite(self.time_s)):
            raise SurveyFormatError(src, "time_s", "finite times", "NaN/inf")
        if P > 1 and not np.all(np.diff(self.time_s) > 0):
            bad = int(np.argmax(np.diff(self.time_s) <= 0)) + 1
            raise SurveyFormatError(
                src, "time_s", "strictly increasing times", f"non-increasing at ping {bad}"
            )
        if self.position.shape != (P, 3):
            raise SurveyFormatError(src, "position", f"shape ({P}, 3)", self.position.shape)
        if not np.all(np.isfinite(self.position)):
            bad = int(np.argmax(~np.isfinite(self.position).all(axis=1)))
            raise SurveyFormatError(src, "position", "finite positions", f"NaN at ping {bad}")
        if self.rotation.shape != (P, 3, 3):
            raise SurveyFormatError(src, "rotation", f"shape ({P}, 3, 3)", self.rotation.shape)
        ok = check_rotations(self.rotation).numpy()
        if not ok.all():
            bad = int(np.argmax(~ok))
            raise SurveyFormatError(
                src, "rotation", "orthonormal rotations (det +1)", f"invalid at ping {bad}"
            )
        if self.altitude_m.shape != (P,):
            raise SurveyFormatError(src, "altitude_m", f"shape ({P},)", self.altitude_m.shape)
        if np.any(self.altitude_m[np.isfinite(self.altitude_m)] < 0):
            raise SurveyFormatError(src, "altitude_m", "altitudes >= 0 or NaN", "negative values")
        if self.range_m.ndim != 1 or self.range_m.shape[0] < 1:
            raise SurveyFormatError(src, "range_m", "a 1D array of >= 1 bin", self.range_m.shape)
        if not np.all(np.isfinite(self.range_m)) or np.any(self.range_m <= 0):
            raise SurveyFormatError(
                src, "range_m", "positive finite slant ranges", f"min {np.nanmin(self.range_m)}"
            )
        if self.range_m.shape[0] > 1 and not np.all(np.diff(self.range_m) > 0):
            raise SurveyFormatError(src, "range_m", "increasing slant ranges", "non-increasing")
        B = self.range_m.shape[0]
        if self.intensity.shape != (P, 2, B):
            raise SurveyFormatError(src, "intensity", f"shape ({P}, 2, {B})", self.intensity.shape)
        if self.altitude_source is not None:
            src_ = self.altitude_source
            if src_.shape != (P,) or not np.issubdtype(src_.dtype, np.integer):
                raise SurveyFormatError(src, "altitude_source", f"({P},) integers", src_.shape)
            if np.any((src_ < 0) | (src_ > ALTITUDE_MISSING)):
                raise SurveyFormatError(src, "altitude_source", "codes 0..3", np.unique(src_))
            if np.any((src_ == ALTITUDE_MISSING) != ~np.isfinite(self.altitude_m)):
                raise SurveyFormatError(
                    src, "altitude_source", "code 3 exactly where altitude_m is NaN", "a mismatch"
                )
        for key, arr in self.extras.items():
            if arr.shape[:1] != (P,):
                raise SurveyFormatError(
                    src, f"extras.{key}", f"leading dimension {P} (pings)", arr.shape
                )

    # ----------------------------------------------------------------- storage
    def save(self, path: str | Path) -> None:
        arrays = {
            "time_s": self.time_s,
            "position": self.position,
            "rotation": self.rotation,
            "altitude_m": self.altitude_m,
            "intensity": self.intensity,
            "range_m": self.range_m,
        }
        if self.altitude_source is not None:
            arrays["altitude_source"] = self.altitude_source.astype(np.uint8)
        arrays.update({f"extra__{k}": v for k, v in self.extras.items()})
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(f, **arrays)

    @classmethod
    def load(cls, path: str | Path, name: str, sensor: SensorParams) -> SidescanLine:
        path = Path(path)
        if not path.is_file():
            raise SurveyFormatError(path, "file", "an existing line .npz", "missing file")
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
        except Exception as exc:  # zipfile/pickle/OSError: report as format error
            raise SurveyFormatError(path, "file", "a readable .npz archive", exc) from exc
        required = ["time_s", "position", "rotation", "altitude_m", "intensity", "range_m"]
        for key in required:
            if key not in arrays:
                raise SurveyFormatError(path, key, "an array in the archive", "missing")
        for key, arr in arrays.items():
            if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_):
                raise SurveyFormatError(path, key, "a numeric array", f"dtype {arr.dtype}")
        extras = {k[len("extra__") :]: v for k, v in arrays.items() if k.startswith("extra__")}
        try:
            return cls(
                name=name,
                sensor=sensor,
                extras=extras,
                altitude_source=arrays.get("altitude_source"),
                **{k: arrays[k] for k in required},
            )
        except SurveyFormatError as err:
            raise SurveyFormatError(path, err.field, err.expected, err.found) from None

    def altimeter_points(self) -> np.ndarray:
        """``(M, 3)`` seafloor points directly below the sonar where altitude is known."""
        ok = np.isfinite(self.altitude_m)
        pts = self.position[ok].copy()
        pts[:, 2] -= self.altitude_m[ok]
        return pts


@dataclass
class AltimeterPoints:
    """Seafloor points below the vehicle: ``xyz (N, 3)`` and the index of their line ``line (N,)``."""

    xyz: np.ndarray
    line: np.ndarray

    @classmethod
    def from_lines(cls, lines: list[SidescanLine]) -> AltimeterPoints:
        pts = [ln.altimeter_points() for ln in lines]
        idx = [np.full(len(p), i, dtype=np.int32) for i, p in enumerate(pts)]
        if not pts:
            return cls(np.zeros((0, 3)), np.zeros((0,), np.int32))
        return cls(np.concatenate(pts), np.concatenate(idx))


@dataclass
class Survey:
    """A survey: lines, an optional MBES grid, named line splits and the frame origin.

    Attributes:
        name: survey name (the folder under ``data/``).
        lines: sidescan lines (their names unique).
        grid: MBES ground-truth grid, or ``None``.
        splits: split name -> line names (e.g. ``train``, ``test``).
        origin: ``{"crs": ..., "easting": ..., "northing": ...}``: the local ENU frame is the
            projected CRS shifted by (easting, northing).
        metadata: free-form (e.g. the generating config and its hash).
    """

    name: str
    lines: list[SidescanLine]
    grid: BathyGrid | None = None
    splits: dict[str, list[str]] = field(default_factory=dict)
    origin: dict[str, Any] = field(
        default_factory=lambda: {"crs": None, "easting": 0.0, "northing": 0.0}
    )
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        names = [ln.name for ln in self.lines]
        if len(set(names)) != len(names):
            raise SurveyFormatError(self.name, "lines", "unique line names", names)
        for split, members in self.splits.items():
            missing = sorted(set(members) - set(names))
            if missing:
                raise SurveyFormatError(
                    self.name, f"splits.{split}", "names of lines in the survey", missing
                )

    def line(self, name: str) -> SidescanLine:
        for ln in self.lines:
            if ln.name == name:
                return ln
        raise KeyError(f"survey '{self.name}': no line named '{name}'")

    def split_lines(self, split: str) -> list[SidescanLine]:
        """Lines of a named split; ``all`` gives every line."""
        if split == "all":
            return list(self.lines)
        if split not in self.splits:
            raise ValueError(
                f"survey '{self.name}': split '{split}' does not exist; "
                f"expected one of {sorted(self.splits) + ['all']}"
            )
        return [self.line(n) for n in self.splits[split]]

    # ----------------------------------------------------------------- storage
    def save(self, folder: str | Path) -> Path:
        folder = Path(folder)
        (folder / "lines").mkdir(parents=True, exist_ok=True)
        sensors = {ln.sensor for ln in self.lines}
        if len(sensors) > 1:
            raise ValueError(f"survey '{self.name}': all lines must share one sensor")
        sensor = next(iter(sensors)) if sensors else SensorParams()
        for ln in self.lines:
            ln.save(folder / "lines" / f"{ln.name}.npz")
        if self.grid is not None:
            from sss2bathy.survey.georef import write_geotiff

            write_geotiff(self.grid, folder / "grid.tif", origin=self._grid_origin())
        manifest = {
            "format_version": FORMAT_VERSION,
            "name": self.name,
            "origin": dict(self.origin),
            "sensor": asdict(sensor),
            "lines": [ln.name for ln in self.lines],
            "splits": {k: list(v) for k, v in self.splits.items()},
            "grid": "grid.tif" if self.grid is not None else None,
            "grid_frame": "projected" if self.grid is not None else None,
            "metadata": self.metadata,
        }
        atomic_write_text(folder / "survey.yaml", yaml.safe_dump(manifest, sort_keys=False))
        return folder

    def _grid_origin(self) -> dict[str, Any]:
        """The origin the grid is written with (its CRS, when set, must be the grid's; an
        origin without one leaves the grid's own label, if any)."""
        return {"crs": None, "easting": 0.0, "northing": 0.0, **(self.origin or {})}

    @staticmethod
    def read_manifest(folder: str | Path) -> dict[str, Any]:
        """The checked ``survey.yaml`` of a survey folder."""
        manifest_path = Path(folder) / "survey.yaml"
        if not manifest_path.is_file():
            raise SurveyFormatError(manifest_path, "file", "a survey manifest", "missing file")
        try:
            manifest = yaml.safe_load(manifest_path.read_text())
        except yaml.YAMLError as exc:
            raise SurveyFormatError(manifest_path, "file", "valid YAML", exc) from exc
        if not isinstance(manifest, dict):
            raise SurveyFormatError(manifest_path, "file", "a YAML mapping", type(manifest))
        return manifest

    @classmethod
    def load_grid(
        cls, folder: str | Path, manifest: dict[str, Any] | None = None
    ) -> BathyGrid | None:
        """The survey's MBES grid in its local frame, or ``None`` without one.

        ``grid_frame: projected`` (written by :meth:`save`): the file's coordinates are shifted
        back by the origin and its CRS must be the origin's. No ``grid_frame`` (folders written
        before it existed): the file is read as it is, in the local frame.
        """
        folder = Path(folder)
        manifest = cls.read_manifest(folder) if manifest is None else manifest
        if not manifest.get("grid"):
            return None
        path = folder / manifest["grid"]
        frame = manifest.get("grid_frame") or "local"
        if frame not in GRID_FRAMES:
            raise SurveyFormatError(
                folder / "survey.yaml", "grid_frame", f"one of {list(GRID_FRAMES)}", frame
            )
        if frame == "local":
            return BathyGrid.load_geotiff(path)
        from sss2bathy.survey.georef import read_geotiff

        origin = {"crs": None, "easting": 0.0, "northing": 0.0, **(manifest.get("origin") or {})}
        return read_geotiff(path, origin=origin)

    @classmethod
    def load(cls, folder: str | Path) -> Survey:
        folder = Path(folder)
        manifest_path = folder / "survey.yaml"
        manifest = cls.read_manifest(folder)
        for key in ("name", "lines", "sensor"):
            if key not in manifest:
                raise SurveyFormatError(manifest_path, key, "a manifest key", "missing")
        if manifest.get("format_version") != FORMAT_VERSION:
            raise SurveyFormatError(
                manifest_path, "format_version", str(FORMAT_VERSION), manifest.get("format_version")
            )
        try:
            sensor = SensorParams(**manifest["sensor"])
        except (TypeError, SurveyFormatError) as exc:
            raise SurveyFormatError(
                manifest_path, "sensor", "valid sensor parameters", exc
            ) from exc
        lines = [
            SidescanLine.load(folder / "lines" / f"{n}.npz", n, sensor) for n in manifest["lines"]
        ]
        grid = cls.load_grid(folder, manifest)
        try:
            return cls(
                name=manifest["name"],
                lines=lines,
                grid=grid,
                splits={k: list(v) for k, v in (manifest.get("splits") or {}).items()},
                origin=manifest.get("origin") or {},
                metadata=manifest.get("metadata") or {},
            )
        except SurveyFormatError as err:
            raise SurveyFormatError(manifest_path, err.field, err.expected, err.found) from None

    def altimeter(self, split: str = "all") -> AltimeterPoints:
        return AltimeterPoints.from_lines(self.split_lines(split))
