"""What a SIREN fit takes from its datamodule, as one typed value.

:class:`SirenInputs` holds the survey frame and the evaluation inputs a
:class:`~sss2bathy.modules.siren.SirenModule` needs at set-up: the SIREN's input bounds
and height range (from sonar tracks and altimeter heights only, never the MBES grid), the
sonar's beam limits and bin ranges, the size of the ping table (the warm-start cache),
the MBES grid (or None), the sonar tracks and swath half-width (the scored area), the
held-out altimeter split and what the georeferenced map export needs.

A datamodule provides it through ``siren_inputs()`` (``SirenInputs.from_attributes(self)``
in :class:`~sss2bathy.data.pings.PingAltimeterDataModule`); :meth:`SirenInputs.of` asks for
that, or reads the same attributes of a datamodule without the accessor.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from sss2bathy.data.holdout import AltimeterSplit
from sss2bathy.survey import BathyGrid, SensorParams

_ATTRIBUTES = (
    "bounds", "z_range", "sensor", "table", "grid", "track_xy", "swath_half_width_m",
)  # fmt: skip


@dataclass(frozen=True)
class SirenInputs:
    """The datamodule's side of a SIREN fit.

    Attributes:
        bounds: ``(x_min, y_min, x_max, y_max)`` of the SIREN's input frame (m).
        z_range: ``(z_min, z_max)`` of its output (m).
        sensor: the sidescan's :class:`~sss2bathy.survey.SensorParams` (beam limits).
        range_m: ``(n_bins,)`` slant range of every bin (m).
        n_pings: pings of the ping table (rows of the warm-start cache).
        grid: the MBES grid, or None (a sidescan-only survey).
        track_xy: ``(P, 2)`` sonar positions of the lines used (m).
        swath_half_width_m: default radius of the scored area around the tracks (m).
        holdout: held-out altimeter points, or None.
        altimeter: ``(M, 3)`` fitted altimeter points, or None.
        origin: the survey origin (``{crs, easting, northing}``) for the georeferenced map.
        n_lines: lines of the ping table (its ``line`` indices are ``0 .. n_lines - 1``).
    """

    bounds: tuple[float, float, float, float]
    z_range: tuple[float, float]
    sensor: SensorParams
    range_m: torch.Tensor
    n_pings: int
    grid: BathyGrid | None
    track_xy: np.ndarray
    swath_half_width_m: float
    holdout: AltimeterSplit | None = None
    altimeter: torch.Tensor | None = None
    origin: dict[str, Any] | None = None
    n_lines: int = 1

    @property
    def n_bins(self) -> int:
        return int(self.range_m.shape[0])

    @classmethod
    def of(cls, datamodule: Any) -> SirenInputs:
        """The inputs of a set-up datamodule: its ``siren_inputs()`` when it has one, else
        read from the attributes of a set-up ``PingAltimeterDataModule``.

        Raises:
            ValueError: no datamodule, or one that is not set up (names the attribute).
        """
        accessor = getattr(datamodule, "siren_inputs", None)
        if callable(accessor):
            inputs = accessor()
            if not isinstance(inputs, SirenInputs):
                raise ValueError(
                    "datamodule.siren_inputs(): expected a SirenInputs, found "
                    f"{type(inputs).__name__}"
                )
            return inputs
        return cls.from_attributes(datamodule)

    @classmethod
    def from_attributes(cls, datamodule: Any) -> SirenInputs:
        """Read from the attributes of a set-up ``PingAltimeterDataModule`` (what its
        ``siren_inputs()`` returns).

        Raises:
            ValueError: no datamodule, or one that is not set up (names the attributes).
        """
        missing = [a for a in _ATTRIBUTES if getattr(datamodule, a, None) is None and a != "grid"]
        if datamodule is None or missing:
            raise ValueError(
                "datamodule: expected a set-up PingAltimeterDataModule (bounds, z_range, "
                f"sensor, grid) passed to the trainer, found "
                f"{'none' if datamodule is None else f'one without {missing}'}"
            )
        table = datamodule.table
        return cls(
            bounds=tuple(datamodule.bounds),
            z_range=tuple(datamodule.z_range),
            sensor=datamodule.sensor,
            range_m=table.range_m,
            n_pings=int(table.n_pings),
            grid=datamodule.grid,
            track_xy=datamodule.track_xy,
            swath_half_width_m=float(datamodule.swath_half_width_m),
            holdout=getattr(datamodule, "holdout_split", None),
            altimeter=getattr(datamodule, "altimeter", None),
            origin=getattr(datamodule, "origin", None),
            n_lines=int(table.line.max()) + 1 if len(table.line) else 1,
        )


__all__ = ["SirenInputs"]
