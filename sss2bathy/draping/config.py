"""Draping configuration (the ``data.drape`` config block)."""

from __future__ import annotations

import sys
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

from sss2bathy.utils.checks import (
    coerce_config,
    is_integer,
    require,
    require_int,
    require_number,
)
from sss2bathy.utils.threads import available_cores

ENGINES = ("auto", "embree", "triangle")
# ``threads: auto``: the cores this process may run on, at most this many (a line has
# few chunks, ~32 at the default chunk size for 1000 pings, and other stages share cores)
AUTO_THREADS_MAX = 4


@dataclass(frozen=True)
class DrapeConfig:
    """How bins are georeferenced on the surface.

    Per ping and head a fan of rays is cast in the head's plane. It is the union of

    * ``rays_per_bin * B`` rays spaced uniformly in the slant range they would have on a
      flat seafloor at the ping's reference altitude (dense where the range changes fast
      with the angle, i.e. at grazing angles), and
    * rays spaced at most ``fan_step_deg`` apart over the whole fan (so steep terrain,
      the nadir region and the beam edges are covered whatever the terrain).

    The fan spans depression angles ``[min(theta_min, 0) - beam_margin_deg,
    max(theta_max + beam_margin_deg, theta_down + nadir_margin_deg)]`` where
    ``theta_down`` is the angle pointing straight down in the world, so water-column
    and out-of-beam bins are classified from real hits, not guessed.

    Attributes:
        rays_per_bin: range-uniform rays per range bin (oversampling factor, > 0).
        fan_step_deg: largest angular step of the uniform part of the fan (degrees).
        beam_margin_deg: extra fan beyond the beam's upper edge (degrees, >= 0).
        nadir_margin_deg: extra fan past straight down (degrees, >= 0).
        jump_check_bins: consecutive rays whose first-hit ranges differ by more than this
            many bins (and hit different triangles) are checked for an occlusion with a
            ray cast between them.
        jump_tolerance: that middle ray's range may differ from the pair's mean range by
            at most this fraction of their range difference; otherwise the pair spans an
            occlusion (its bins are SHADOW unless seen elsewhere in the fan).
        pings_per_chunk: at most this many pings draped per vectorised step and
            ray-casting call (a line is split into equal chunks, their number a multiple
            of the thread count; speed and memory only, results do not depend on it).
            Larger chunks amortise the per-chunk Python and dispatch work; on the
            draping benchmark (512 bins, ~1500 rays per fan, ~40 bytes of temporaries
            per ray) 4 pings take ~7 % longer than 32, 8-16 ~3 % longer, 64-128 the
            same within noise.
        threads: threads draping a line's chunks of pings at once (an integer >= 1, or
            ``auto``: the cores this process may run on, at most
            :data:`AUTO_THREADS_MAX` and at most torch's thread count, e.g. the entry
            points' ``torch_threads``). Speed only: the chunks write disjoint pings and
            the results are the same bits for any count (not in the cache key). The
            compiled bookkeeping and embree's direct call run without the GIL; the
            slow ``triangle`` engine drapes with one thread.
        engine: ``auto`` (embreex, falling back to trimesh's own intersector with a
            warning), ``embree`` or ``triangle``.
        mesh_path: a mesh file (PLY/OBJ/STL/...) to drape onto instead of the survey's
            MBES grid; relative paths are taken relative to the survey folder.
    """

    rays_per_bin: float = 2.0
    fan_step_deg: float = 0.2
    beam_margin_deg: float = 5.0
    nadir_margin_deg: float = 5.0
    jump_check_bins: float = 1.0
    jump_tolerance: float = 0.25
    pings_per_chunk: int = 32
    threads: int | str = "auto"
    engine: str = "auto"
    mesh_path: str | None = None

    def __post_init__(self) -> None:
        for name in ("rays_per_bin", "fan_step_deg", "jump_check_bins", "jump_tolerance"):
            require_number(
                f"drape.{name}", getattr(self, name), lambda v: v > 0, "a positive number"
            )
        for name in ("beam_margin_deg", "nadir_margin_deg"):
            value = getattr(self, name)
            require_number(f"drape.{name}", value, lambda v: 0 <= v <= 45, "a number in [0, 45]")
        require("drape.fan_step_deg", self.fan_step_deg, self.fan_step_deg <= 5, "<= 5 degrees")
        require_int("drape.pings_per_chunk", self.pings_per_chunk)
        threads = self.threads
        ok = threads == "auto" or (is_integer(threads) and threads >= 1)
        require("drape.threads", threads, ok, "a positive integer or 'auto'")
        require("drape.engine", self.engine, self.engine in ENGINES, f"one of {ENGINES}")

    @classmethod
    def coerce(cls, cfg: DrapeConfig | Mapping[str, Any] | None) -> DrapeConfig:
        """A config from ``None`` (defaults), a plain dict / DictConfig, or a config."""
        return coerce_config(cls, cfg, "drape")

    def cache_dict(self) -> dict[str, Any]:
        """The fields that change results (excludes chunking, threads and the intersector
        engine)."""
        out = asdict(self)
        out.pop("pings_per_chunk")
        out.pop("threads")
        out.pop("engine")
        return out

    def n_threads(self) -> int:
        """``threads`` as a count: ``auto`` -> :func:`available_cores`, at most
        :data:`AUTO_THREADS_MAX` and at most torch's thread count where torch is loaded (an
        entry point run with ``torch_threads=1``, to share a CPU with other jobs, drapes on
        one thread too)."""
        if self.threads == "auto":
            n = min(available_cores(), AUTO_THREADS_MAX)
            torch = sys.modules.get("torch")  # not imported here: draping does not need it
            if torch is not None:
                n = min(n, max(1, int(torch.get_num_threads())))
            return n
        return int(self.threads)
