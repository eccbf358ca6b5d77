"""Ping + altimeter batches for the SIREN fit (paper "Training SIREN").

Every ping of the chosen sidescan lines lives in one table of tensors (on the accelerator
when there is one); a batch is a random set of 64 pings (all bins of both heads) gathered
from the table plus 2000 random altimeter points. An epoch visits every ping once.

Batch keys (``P`` pings, ``B`` bins per side, ``A`` altimeter points):

=============  ================  ===========================================================
``position``   ``(P, 3)`` f32    sonar position, world ENU (m)
``rotation``   ``(P, 3, 3)`` f32 vehicle -> world rotation
``range_m``    ``(B,)`` f32      slant range of each bin (m), shared by all lines
``n_lat``      ``(P, 2, B)`` f32 target head-plane normal; NaN where there is none
``intensity``  ``(P, 2, B)`` f32 normalised intensity (only with ``need_intensity``)
``mask``       ``(P, 2, B)`` u8  0 valid, else ``MASK_*`` bits
``line``       ``(P,)`` long     line index within :attr:`PingAltimeterDataModule.line_names`
``ping``       ``(P,)`` long     ping index within its line
``index``      ``(P,)`` long     global ping index in the table (per-ping caches)
``altimeter``  ``(A, 3)`` f32    seafloor points below the vehicle (m)
``keep``       ``(P, 2, B)`` bool the bins drawn for this step (only with ``bin_fraction < 1``)
=============  ================  ===========================================================

``bin_fraction < 1`` draws, for every batch, each bin with that probability (``keep``): a
step then costs less (a quarter of the bins: about half a whole-ping step at the paper's
scale, the step having a part that does not scale with the bins). Neighbouring bins of a
ping sample nearly the same seabed (512 bins over 50 m at the paper's scale), so the map
gains nearly as much per step (docs/performance_log.md, "A map within 10 % of the best in
20 min"; ``siren_schedule=budget`` uses a quarter).

Normals and masks (``normals``: a :class:`~sss2bathy.data.normal_source.NormalSource`,
``data.normals`` of ``conf/data/normals/``, with the CNN's checkpoint and inference settings
inside):

* ``"gt"`` — lines draped on the MBES grid (:func:`sss2bathy.draping.drape_survey`):
  the draped ``n_lat`` and mask (SIREN-GT-N2d).
* ``"cnn"`` — CNN predictions (:func:`sss2bathy.data.cnn_normals.predict_normals`); the
  mask is the sonar-only mask OR-ed with the prediction's (SIREN-CNN-N2d). Nothing is
  draped: the result is the same with or without an MBES grid.
* ``"none"`` — no normal targets (``n_lat`` all NaN) and the very same sonar-only mask
  (:func:`sss2bathy.data.masks.sonar_mask`: water column and beam limits from the altitude,
  shadows from the intensity, no-hit where altitude or intensity is missing); for surveys
  without MBES (the Lambertian fit, real data).

The sonar-only mask's parameters are ``sonar_mask`` (``data.sonar_mask``,
:class:`~sss2bathy.data.masks.SonarMaskConfig`); intensities (``need_intensity``) are
normalised over the table's valid bins.

The SIREN's frame never looks at the MBES grid: :attr:`bounds` are the sonar tracks
expanded by the largest slant range (everything a bin can reach), :attr:`z_range` the
altimeter heights expanded by ``z_margin`` (at least ``z_margin_m``) on either side.
For evaluation the module also exposes :attr:`grid` (the MBES grid or ``None``),
:attr:`track_xy` (sonar positions of the lines used) and :attr:`swath_half_width_m`
(``sqrt(r_max^2 - median altitude^2)``, the swath's reach on flat ground).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import pytorch_lightning as pl
import torch
from torch.utils.data import DataLoader, Dataset, Sampler

from sss2bathy.data.cnn_normals import predict_normals
from sss2bathy.data.holdout import AltimeterSplit, split_altimeter, split_altimeter_fold
from sss2bathy.data.masks import SonarMaskConfig, sonar_only_mask
from sss2bathy.data.normal_source import NormalSource
from sss2bathy.data.normalize import normalize_intensity
from sss2bathy.data.sources import load_survey, survey_folder
from sss2bathy.data.windows import EpochSampler, ResumableDataLoader
from sss2bathy.draping import drape_survey
from sss2bathy.survey import BathyGrid, SensorParams, Survey
from sss2bathy.utils.checks import require_bool, require_int, require_number

log = logging.getLogger(__name__)



@dataclass
class PingTable:
    """All pings of a set of lines as tensors (``N`` pings, ``B`` bins per side).

    See the module docstring for the fields; ``intensity`` is ``None`` unless requested.
    """

    position: torch.Tensor
    rotation: torch.Tensor
    range_m: torch.Tensor
    n_lat: torch.Tensor
    mask: torch.Tensor
    line: torch.Tensor
    ping: torch.Tensor
    intensity: torch.Tensor | None = None

    @property
    def n_pings(self) -> int:
        return int(self.position.shape[0])

    @property
    def n_bins(self) -> int:
        return int(self.range_m.shape[0])

    def to(self, device: torch.device | str) -> PingTable:
        return PingTable(
            **{
                f.name: (
                    None if getattr(self, f.name) is None else getattr(self, f.name).to(device)
                )
                for f in fields(self)
            }
        )

    def gather(self, index: torch.Tensor) -> dict[str, torch.Tensor]:
        """Batch dict of the pings ``index (P,)`` (long, on the table's device)."""
        batch = {
            "position": self.position[index],
            "rotation": self.rotation[index],
            "range_m": self.range_m,
            "n_lat": self.n_lat[index],
            "mask": self.mask[index],
            "line": self.line[index],
            "ping": self.ping[index],
            "index": index,
        }
        if self.intensity is not None:
            batch["intensity"] = self.intensity[index]
        return batch


def build_ping_table(
    survey: Survey,
    survey_dir: str | Path,
    line_names: Sequence[str],
    normals: NormalSource | Mapping[str, Any] | str = "gt",
    need_intensity: bool = False,
    drape: Mapping[str, Any] | None = None,
    sonar_mask: Mapping[str, Any] | None = None,
) -> PingTable:
    """Concatenate the lines' navigation, targets and masks into one :class:`PingTable`.

    Args:
        survey, survey_dir: the survey and its folder (draping/prediction caches).
        line_names: lines to use, in order (their index is the batch's ``line``).
        normals: the normals' source (:class:`~sss2bathy.data.normal_source.NormalSource`,
            its fields, or ``"gt"`` | ``"none"``); ``cnn`` with its checkpoint a file or
            ``pretrained`` (:meth:`NormalSource.resolve` turns ``latest`` into a file).
        need_intensity: also hold normalised intensities (Lambertian sensor model).
        drape: :class:`~sss2bathy.draping.DrapeConfig` fields, or ``None`` for defaults
            (``gt`` only).
        sonar_mask: :class:`~sss2bathy.data.masks.SonarMaskConfig` fields (``None``:
            defaults), the mask of ``cnn`` and ``none``.
    """
    sonar_mask = SonarMaskConfig.coerce(sonar_mask)
    normals = NormalSource.coerce(normals)
    lines = [survey.line(n) for n in line_names]
    if not lines:
        raise ValueError(f"line_names: expected at least one line, found {list(line_names)}")
    range_m = lines[0].range_m
    for ln in lines[1:]:
        if ln.range_m.shape != range_m.shape or not np.allclose(ln.range_m, range_m):
            raise ValueError(
                f"line '{ln.name}': expected the slant ranges of line '{lines[0].name}' "
                f"({range_m.shape[0]} bins), found different ones ({ln.range_m.shape[0]} bins)"
            )
    draped = None
    if normals.source == "gt":
        draped = drape_survey(survey, survey_dir, cfg=drape, lines=list(line_names))
    predicted = None
    if normals.source == "cnn":
        if normals.checkpoint == "latest":
            normals = normals.resolve()
        predicted = predict_normals(
            normals.checkpoint,
            survey,
            survey_dir,
            list(line_names),
            None,
            dict(normals.window) if normals.window is not None else None,
            precision=normals.precision,
            overlap=normals.overlap,
        )
    n_lat, masks, intensity = [], [], []
    for ln in lines:
        if draped is not None:
            mask = draped[ln.name].mask.copy()
        else:
            mask = sonar_only_mask(ln, sonar_mask)
        if normals.source == "gt":
            target = draped[ln.name].n_lat
        elif normals.source == "cnn":
            target, pred_mask = predicted[ln.name]
            mask |= pred_mask
        else:
            target = np.full(mask.shape, np.nan, dtype=np.float32)
        n_lat.append(np.where(mask == 0, target, np.nan).astype(np.float32))
        masks.append(mask.astype(np.uint8))
        if need_intensity:
            intensity.append(normalize_intensity(ln.intensity, mask == 0))
    return PingTable(
        position=torch.from_numpy(np.concatenate([ln.position for ln in lines]).astype(np.float32)),
        rotation=torch.from_numpy(np.concatenate([ln.rotation for ln in lines]).astype(np.float32)),
        range_m=torch.from_numpy(range_m.astype(np.float32)),
        n_lat=torch.from_numpy(np.concatenate(n_lat)),
        mask=torch.from_numpy(np.concatenate(masks)),
        line=torch.cat(
            [torch.full((ln.n_pings,), i, dtype=torch.long) for i, ln in enumerate(lines)]
        ),
        ping=torch.cat([torch.arange(ln.n_pings, dtype=torch.long) for ln in lines]),
        intensity=torch.from_numpy(np.concatenate(intensity)) if need_intensity else None,
    )


class _Indices(Dataset):
    """Indices ``0 .. n-1`` (the validation loader's one dummy item)."""

    def __init__(self, n: int) -> None:
        self.n = n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> int:
        return i


def derived_seed(*keys: int) -> int:
    """A 63-bit seed mixed from integers (``numpy.random.SeedSequence``): distinct keys give
    unrelated streams, e.g. ``(seed, epoch)``."""
    return int(np.random.SeedSequence([int(k) for k in keys]).generate_state(1, np.uint64)[0] >> 1)


class PingBatchSampler(EpochSampler, Sampler[tuple[int, int]]):
    """Keys ``(epoch, k)`` of the ``n_batches`` batches of an epoch, ``k`` in order.

    Everything random about a batch derives from its key and the seed (:class:`PingBatches`),
    so a run is reproducible and a resumed run (``ResumableDataLoader``) sees the batches
    the uninterrupted run saw. The epoch is set by Lightning (``set_epoch``) and otherwise
    advances at every iteration.
    """

    def __init__(self, n_batches: int) -> None:
        if n_batches < 1:
            raise ValueError(f"n_batches: expected at least one batch, found {n_batches}")
        self.n_batches = int(n_batches)
        self.epoch = 0
        self._skip = 0

    def __len__(self) -> int:
        return self.n_batches

    def __iter__(self) -> Iterator[tuple[int, int]]:
        epoch, start = self.epoch, self._skip
        self.epoch, self._skip = epoch + 1, 0
        return iter([(epoch, k) for k in range(start, self.n_batches)])


class PingBatches(Dataset):
    """Batch ``(epoch, k)``: pings ``k * batch_pings ..`` of the epoch's order, plus random
    altimeter points.

    The order is a permutation of all pings drawn from ``(seed, epoch)`` (several chained
    permutations when ``n_batches * batch_pings`` exceeds the pings: without replacement
    within each); the altimeter points are drawn with replacement from
    ``(seed, epoch, k)``; with ``bin_fraction < 1`` the batch's ``keep`` bins are drawn
    from ``(seed, 2, epoch, k)``, each with probability ``bin_fraction``.
    """

    def __init__(
        self,
        table: PingTable,
        altimeter: torch.Tensor,
        batch_pings: int,
        altimeter_points: int,
        n_batches: int,
        seed: int,
        whole_epochs: bool,
        bin_fraction: float = 1.0,
    ) -> None:
        self.table, self.altimeter = table, altimeter
        self.bin_fraction = float(bin_fraction)
        self.batch_pings, self.altimeter_points = batch_pings, altimeter_points
        self.n_batches, self.seed, self.whole_epochs = n_batches, seed, whole_epochs
        self._order: tuple[int, torch.Tensor] | None = None

    def __len__(self) -> int:
        return self.n_batches

    def order(self, epoch: int) -> torch.Tensor:
        """The epoch's ping order (long, on the table's device)."""
        if self._order is None or self._order[0] != epoch:
            n = self.table.n_pings
            total = n if self.whole_epochs else self.n_batches * self.batch_pings
            gen = torch.Generator().manual_seed(derived_seed(self.seed, epoch))
            perms = [torch.randperm(n, generator=gen) for _ in range(math.ceil(total / n))]
            order = torch.cat(perms)[:total].to(self.table.position.device)
            self._order = (epoch, order)
        return self._order[1]

    def __getitem__(self, key: tuple[int, int]) -> dict[str, torch.Tensor]:
        epoch, k = (int(v) for v in key)
        if not 0 <= k < self.n_batches:
            raise IndexError(f"key: expected a batch index in [0, {self.n_batches}), found {k}")
        index = self.order(epoch)[k * self.batch_pings : (k + 1) * self.batch_pings]
        batch = self.table.gather(index)
        gen = torch.Generator().manual_seed(derived_seed(self.seed, 1, epoch, k))
        pick = torch.randint(self.altimeter.shape[0], (self.altimeter_points,), generator=gen)
        batch["altimeter"] = self.altimeter[pick.to(self.altimeter.device)]
        if self.bin_fraction < 1.0:
            gen = torch.Generator().manual_seed(derived_seed(self.seed, 2, epoch, k))
            keep = torch.rand(tuple(batch["mask"].shape), generator=gen) < self.bin_fraction
            batch["keep"] = keep.to(batch["mask"].device)
        return batch


# ----------------------------------------------------------- held-out altimeter points
HOLDOUT_KEYS = ("fraction", "block_pings", "seed", "folds", "fold", "block_m")


def holdout_config(holdout: Mapping[str, Any] | None, seed: int) -> dict[str, Any]:
    """The ``data.holdout`` settings checked and completed: ``fraction`` (0 = off),
    ``block_pings`` and ``seed`` (``None`` = the datamodule's ``seed``); ``folds`` >= 2
    switches to the K-fold split (:func:`sss2bathy.data.holdout.split_altimeter_fold`:
    fold ``fold`` of blocks of ``block_m`` metres, null = its default length) in place of
    ``fraction`` and ``block_pings``; 0 = off."""
    given = dict(holdout or {})
    unknown = sorted(set(given) - set(HOLDOUT_KEYS))
    if unknown:
        raise ValueError(
            f"data.holdout: expected keys among {list(HOLDOUT_KEYS)}, found unknown {unknown}"
        )
    cfg = {"fraction": 0.0, "block_pings": 50, "seed": seed, "folds": 0, "fold": 0}
    cfg.update({k: v for k, v in given.items() if v is not None})
    try:
        fraction = float(cfg["fraction"])
    except (TypeError, ValueError):
        fraction = float("nan")
    if not 0.0 <= fraction < 1.0:
        raise ValueError(
            f"data.holdout.fraction: expected a number in [0, 1), found {cfg['fraction']!r}"
        )
    if not isinstance(cfg["block_pings"], int) or cfg["block_pings"] < 1:
        raise ValueError(
            f"data.holdout.block_pings: expected a positive integer, found {cfg['block_pings']!r}"
        )
    folds, fold, block_m = cfg["folds"], cfg["fold"], cfg.get("block_m")
    if isinstance(folds, bool) or not isinstance(folds, int) or folds < 0 or folds == 1:
        raise ValueError(
            f"data.holdout.folds: expected 0 (off) or an integer >= 2, found {folds!r}"
        )
    if isinstance(fold, bool) or not isinstance(fold, int) or not 0 <= fold < max(folds, 1):
        raise ValueError(
            f"data.holdout.fold: expected an integer in [0, {max(folds, 1)}), found {fold!r}"
        )
    if block_m is not None:
        require_number("data.holdout.block_m", block_m, lambda v: v > 0, "a positive length (m)")
    return {
        "fraction": fraction,
        "block_pings": int(cfg["block_pings"]),
        "seed": int(cfg["seed"]),
        "folds": int(folds),
        "fold": int(fold),
        "block_m": None if block_m is None else float(block_m),
    }


class PingAltimeterDataModule(pl.LightningDataModule):
    """Batches of random pings (all bins) and random altimeter points for the SIREN fit.

    Args:
        survey: the ``data/survey`` config (``kind`` + its keys).
        data_dir: where surveys live (``paths.data_dir``).
        sidescan_split: split whose lines give the pings (``"all"`` = every line).
        altimeter_split: split whose lines give the altimeter points.
        normals: the normals' source, ``data.normals`` (module docstring;
            :class:`~sss2bathy.data.normal_source.NormalSource`, its fields or ``"gt"`` |
            ``"none"``): for ``cnn`` the checkpoint (a path, ``latest`` = the newest CNN run
            of ``runs_dir`` at ``scale``, or ``pretrained``), the windows, the inference
            precision and overlap. ``latest`` and ``pretrained`` are resolved once, in
            :meth:`setup` (:attr:`normals` then names the file).
        need_intensity: hold normalised intensities (Lambertian sensor model).
        batch_pings: pings per batch (64 in the paper).
        altimeter_points: altimeter points per batch (2000 in the paper), drawn with
            replacement.
        steps_per_epoch: batches per epoch; ``None`` = ``ceil(pings / batch_pings)`` (every
            ping once).
        bin_fraction: the fraction of each batch's bins a step uses, drawn at random per
            batch (batch key ``keep``), in (0, 1]; 1 = every bin (the paper).
        seed: seed of the ping order and of the altimeter draws.
        device_resident: keep the table on the trainer's device (no per-step copies).
        drape: draping config (:class:`~sss2bathy.draping.DrapeConfig` fields) or ``None``.
        sonar_mask: sonar-only mask parameters (:class:`~sss2bathy.data.masks.SonarMaskConfig`
            fields) or ``None`` (defaults); ``normals="cnn"`` and ``"none"``.
        z_margin: fraction of the altimeter height span added on either side of
            :attr:`z_range`; ``z_margin_m`` is the least margin (m).
        holdout: held-out altimeter evaluation (``fraction``, ``block_pings``, ``seed``;
            :func:`holdout_config`); ``None`` or ``fraction: 0`` = every altimeter point is
            fitted. The split is :attr:`holdout_split`.
    """

    def __init__(
        self,
        survey: Mapping[str, Any],
        data_dir: str,
        sidescan_split: str = "test",
        altimeter_split: str = "test",
        normals: NormalSource | Mapping[str, Any] | str = "gt",
        need_intensity: bool = False,
        batch_pings: int = 64,
        altimeter_points: int = 2000,
        steps_per_epoch: int | None = None,
        seed: int = 0,
        device_resident: bool = True,
        drape: Mapping[str, Any] | None = None,
        sonar_mask: Mapping[str, Any] | None = None,
        z_margin: float = 0.25,
        z_margin_m: float = 2.0,
        holdout: Mapping[str, Any] | None = None,
        bin_fraction: float = 1.0,
    ) -> None:
        super().__init__()
        normals = NormalSource.coerce(normals)
        require_int("batch_pings", batch_pings)
        require_int("altimeter_points", altimeter_points)
        require_bool("need_intensity", need_intensity)
        require_number("z_margin", z_margin, lambda v: v >= 0, "a fraction >= 0")
        require_number("z_margin_m", z_margin_m, lambda v: v >= 0, "a number >= 0 (m)")
        require_number(
            "bin_fraction", bin_fraction, lambda v: 0 < v <= 1, "a fraction in (0, 1]"
        )
        if steps_per_epoch is not None and int(steps_per_epoch) < 1:
            raise ValueError(f"steps_per_epoch: expected None or >= 1, found {steps_per_epoch}")
        self.survey_cfg = survey
        self.data_dir = data_dir
        self.sidescan_split = sidescan_split
        self.altimeter_split = altimeter_split
        self.normals = normals
        self.need_intensity = bool(need_intensity)
        self.batch_pings = int(batch_pings)
        self.altimeter_points = int(altimeter_points)
        self.steps_per_epoch = None if steps_per_epoch is None else int(steps_per_epoch)
        self.bin_fraction = float(bin_fraction)
        self.seed = int(seed)
        self.device_resident = bool(device_resident)
        self.drape = drape
        self.sonar_mask = SonarMaskConfig.coerce(
            None if sonar_mask is None else {str(k): v for k, v in dict(sonar_mask).items()}
        ).to_dict()
        self.z_margin = float(z_margin)
        self.z_margin_m = float(z_margin_m)
        self.holdout = holdout_config(holdout, self.seed)
        self.holdout_split: AltimeterSplit | None = None
        self.table: PingTable | None = None
        self.altimeter: torch.Tensor | None = None
        self.grid: BathyGrid | None = None
        self.origin: dict | None = None  # the survey origin {"crs", "easting", "northing"}
        self.sensor: SensorParams | None = None
        self.line_names: list[str] = []
        self.survey_dir: Path | None = None
        self.bounds: tuple[float, float, float, float] | None = None
        self.z_range: tuple[float, float] | None = None
        self.track_xy: np.ndarray | None = None
        self.swath_half_width_m: float | None = None
        self.ping_altitude_m: np.ndarray | None = None  # (N,) the table's pings' altitudes

    # --------------------------------------------------------------- set-up
    def prepare_data(self) -> None:
        """Generate/import the survey once (rank 0); draping/prediction caches fill in setup."""
        survey_folder(self.survey_cfg, self.data_dir)

    def setup(self, stage: str | None = None) -> None:
        if self.table is not None:
            return
        survey, folder = load_survey(self.survey_cfg, self.data_dir)
        self.survey_dir = folder
        for key, split in (
            ("data.sidescan_split", self.sidescan_split),
            ("data.altimeter_split", self.altimeter_split),
        ):
            names = ["all", *sorted(survey.splits)]
            if split not in names:
                raise ValueError(
                    f"{key}: expected a split of survey '{survey.name}', one of {names}, "
                    f"found {split!r}"
                )
            if not survey.split_lines(split):
                raise ValueError(
                    f"{key}: expected a split with lines, found split {split!r} of survey "
                    f"'{survey.name}' empty"
                )
        lines = survey.split_lines(self.sidescan_split)
        self.line_names = [ln.name for ln in lines]
        self.sensor = lines[0].sensor
        self.grid = survey.grid
        self.origin = dict(survey.origin or {})
        if self.normals.source == "cnn":  # latest / pretrained -> the file, once
            self.normals = self.normals.resolve()
            log.info("PingAltimeterDataModule: CNN checkpoint %s", self.normals.checkpoint)
        table = build_ping_table(
            survey,
            folder,
            self.line_names,
            self.normals,
            self.need_intensity,
            self.drape,
            self.sonar_mask,
        )
        alt = self._fit_altimeter(survey)
        if alt.shape[0] == 0:
            raise ValueError(
                f"altimeter_split: expected lines with altitude readings in split "
                f"'{self.altimeter_split}', found no altimeter points"
            )
        self.track_xy = table.position[:, :2].numpy().astype(np.float64)
        altitude = np.concatenate([ln.altitude_m for ln in lines])
        self.ping_altitude_m = altitude.astype(np.float64)
        altitude = float(np.nanmedian(altitude)) if np.isfinite(altitude).any() else 0.0
        r_max = float(table.range_m.max())
        self.swath_half_width_m = math.sqrt(max(r_max**2 - altitude**2, 0.0)) or r_max
        self.bounds = self._bounds(table)
        self.z_range = self._z_range(alt[:, 2])
        device = torch.device("cpu")
        if self.device_resident and self.trainer is not None:
            device = self.trainer.strategy.root_device
        self.table = table.to(device)
        self.altimeter = torch.from_numpy(alt.astype(np.float32)).to(device)

    def _bounds(self, table: PingTable) -> tuple[float, float, float, float]:
        reach = float(table.range_m.max())
        pos = table.position.double()
        lo = (pos[:, :2].amin(0) - reach).tolist()
        hi = (pos[:, :2].amax(0) + reach).tolist()
        return (lo[0], lo[1], hi[0], hi[1])

    def _fit_altimeter(self, survey: Survey) -> np.ndarray:
        """``(M, 3)`` altimeter points of ``altimeter_split`` the fit uses; with a holdout,
        the others go to :attr:`holdout_split` (:func:`sss2bathy.data.holdout.split_altimeter`)."""
        lines = survey.split_lines(self.altimeter_split)
        if self.holdout["folds"] >= 2:
            return self._fold_altimeter(lines)
        if self.holdout["fraction"] == 0.0:
            self.holdout_split = None
            return survey.altimeter(self.altimeter_split).xyz
        split = split_altimeter(
            [ln.position for ln in lines],
            [ln.altitude_m for ln in lines],
            self.holdout["fraction"],
            self.holdout["block_pings"],
            self.holdout["seed"],
        )
        if split.n_held == 0:
            longest = max((ln.n_pings for ln in lines), default=0)
            log.warning(
                "data.holdout: no altimeter point held out (blocks of %d pings, fraction %g, "
                "longest line %d pings); no held-out score — set data.holdout.block_pings "
                "smaller, or data.holdout.fraction=0 to silence this",
                self.holdout["block_pings"],
                self.holdout["fraction"],
                longest,
            )
            self.holdout_split = None
        else:
            self.holdout_split = split
            log.info(
                "data.holdout: %d of %d altimeter points held out (%.1f %%, blocks of %d pings); "
                "along-track interpolation of the rest scores %.3f m MAE on them",
                split.n_held,
                split.n_held + split.fit.shape[0],
                100 * split.fraction,
                self.holdout["block_pings"],
                split.interp_mae,
            )
        return split.fit

    def _fold_altimeter(self, lines: Sequence[Any]) -> np.ndarray:
        """Fold ``holdout.fold`` of the K-fold split held out (:func:`split_altimeter_fold`;
        the default block length from the swath width of the longest slant range)."""
        altitude = np.concatenate([ln.altitude_m for ln in lines])
        h = float(np.nanmedian(altitude)) if np.isfinite(altitude).any() else 0.0
        r_max = float(max(np.max(ln.range_m) for ln in lines))
        split = split_altimeter_fold(
            [ln.position for ln in lines],
            [ln.altitude_m for ln in lines],
            self.holdout["folds"],
            self.holdout["fold"],
            self.holdout["block_m"],
            self.holdout["seed"],
            swath_width_m=2.0 * (math.sqrt(max(r_max**2 - h**2, 0.0)) or r_max),
        )
        self.holdout_split = split
        log.info(
            "data.holdout: fold %d of %d: %d of %d altimeter points held out (%d blocks of "
            "%.1f m, %.0f pings on average); along-track interpolation of the rest scores "
            "%.3f m MAE on them",
            split.fold, split.folds, split.n_held, split.n_held + split.fit.shape[0],
            split.n_blocks, split.block_m, split.block_pings or 0.0, split.interp_mae,
        )  # fmt: skip
        return split.fit

    def _z_range(self, z: np.ndarray) -> tuple[float, float]:
        zmin, zmax = float(np.min(z)), float(np.max(z))
        margin = max(self.z_margin * (zmax - zmin), self.z_margin_m)
        return (zmin - margin, zmax + margin)

    # ----------------------------------------------------------- loaders
    @property
    def n_pings(self) -> int:
        return self.table.n_pings if self.table is not None else 0

    def train_dataloader(self) -> DataLoader:
        """Batches of :class:`PingBatches`, resumable mid-epoch (``ResumableDataLoader``)."""
        if self.table is None:
            raise RuntimeError("PingAltimeterDataModule: call setup() before train_dataloader()")
        steps = self.steps_per_epoch or math.ceil(self.table.n_pings / self.batch_pings)
        batches = PingBatches(
            self.table,
            self.altimeter,
            self.batch_pings,
            self.altimeter_points,
            steps,
            self.seed,
            whole_epochs=self.steps_per_epoch is None,
            bin_fraction=self.bin_fraction,
        )
        # batch_size=None: each key is a whole batch; the loader's own generator keeps the
        # global RNG untouched when an epoch's iterator is created
        return ResumableDataLoader(
            batches,
            batch_size=None,
            sampler=PingBatchSampler(steps),
            num_workers=0,
            generator=torch.Generator().manual_seed(self.seed),
        )

    def val_dataloader(self) -> DataLoader:
        """One dummy batch per validation: the module evaluates the whole map itself."""
        return DataLoader(
            _Indices(1), batch_size=1, generator=torch.Generator().manual_seed(self.seed)
        )
