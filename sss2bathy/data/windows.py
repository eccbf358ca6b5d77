"""Sidescan windows for the normal-estimation CNN (paper section "Training CNN").

Each head of each line's waterfall is cut into windows of ``window_pings x window_bins``
(64 x 512 in the paper), consecutive windows overlapping by ``overlap`` (75%) along pings
and, when a line has more bins than a window, along bins too; the last window of each
axis is flush with the end so every pixel is covered. Both heads are pooled (n_lat means
the same on both by our convention). Windows whose fraction of valid pixels is below
``min_valid_fraction`` are skipped and counted in the log.

Augmentation (training only): an along-track flip (pings reversed), the paper's "other
direction, other side" — a sonar heading the opposite way sees the same seabed from the
other head, with the same n_lat (no sign change). It is drawn per sample per epoch by
:class:`FlipShuffleSampler` from ``seed`` and the epoch number, so it does not depend on
worker seeding.

Batches are dicts (``B`` = batch size, ``H`` = window pings, ``W`` = window bins):

* ``intensity [B,1,H,W] float32`` — normalised (:mod:`sss2bathy.data.normalize`) over the
  bins valid in the **sonar-only** mask (:func:`sss2bathy.data.masks.sonar_mask`, parameters
  ``sonar_mask``), exactly as at inference (:mod:`sss2bathy.data.cnn_normals`): the draped
  (MBES) mask only selects the pixels of the loss;
* ``inputs [B,C,H,W] float32`` — the network's input channels ``input_channels``
  (:func:`sss2bathy.data.masks.input_channels`: ``intensity`` first, then optionally
  ``grazing`` = altitude / r on flat seabed, ``range`` = r / r_max and ``opposite``, the
  other head's intensity at the same pings and bins);
* ``n_lat [B,1,H,W] float32`` — draped head-plane normal, 0 at invalid pixels;
* ``mask [B,1,H,W] bool`` — True = valid (mask 0 in the draping);
* ``line [B] long`` — index into the dataset's ``line_names``; ``side [B] long`` (0 port,
  1 starboard); ``ping_start``, ``bin_start [B] long`` — the window's origin in the
  line's (unflipped) waterfall; ``flipped [B] bool`` — the window's pings are reversed
  (un-reverse a prediction before stitching it back at ``ping_start``).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytorch_lightning as pl
import torch
from torch.utils.data import DataLoader, Dataset, Sampler

from sss2bathy.data.masks import (
    SonarMaskConfig,
    check_channels,
    input_channels,
    relative_channel,
    sonar_normalized_intensity,
)
from sss2bathy.data.sonar_envelope import describe, sonar_envelope
from sss2bathy.draping import DrapeConfig, DrapedLine, drape_survey
from sss2bathy.survey import SidescanLine, Survey
from sss2bathy.utils.checks import require_bool, require_int, require_number

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------- geometry
def window_starts(n: int, size: int, overlap: float = 0.75) -> np.ndarray:
    """Start indices of windows of ``size`` covering ``range(n)``.

    Consecutive windows are ``round(size * (1 - overlap))`` apart (at least 1); a last
    window flush with the end is added when the stride does not land there.

    >>> window_starts(10, 4, 0.5).tolist()
    [0, 2, 4, 6]
    >>> window_starts(11, 4, 0.5).tolist()
    [0, 2, 4, 6, 7]
    """
    if not (isinstance(size, int | np.integer) and size >= 1):
        raise ValueError(f"size: expected a positive integer, found {size!r}")
    if not (isinstance(n, int | np.integer) and n >= size):
        raise ValueError(f"n: expected an integer >= size ({size}), found {n!r}")
    if not (0.0 <= overlap < 1.0):
        raise ValueError(f"overlap: expected a fraction in [0, 1), found {overlap!r}")
    stride = max(1, int(round(size * (1.0 - overlap))))
    starts = np.arange(0, n - size + 1, stride, dtype=np.int64)
    if starts[-1] != n - size:
        starts = np.append(starts, np.int64(n - size))
    return starts


def line_windows(
    n_pings: int,
    n_bins: int,
    window_pings: int,
    window_bins: int,
    overlap: float = 0.75,
    overlap_bins: float | None = None,
) -> np.ndarray:
    """All window origins ``(K, 2)`` int64 ``[ping_start, bin_start]`` covering a waterfall.

    Nothing is skipped, so predictions of these windows can be stitched into a whole
    line (per head). ``overlap_bins``: the overlap across track (None: ``overlap``). Raises
    if the line is smaller than a window.
    """
    if n_pings < window_pings:
        raise ValueError(
            f"n_pings: expected at least window_pings={window_pings} pings, found {n_pings}"
        )
    if n_bins < window_bins:
        raise ValueError(
            f"n_bins: expected at least window_bins={window_bins} bins, found {n_bins}"
        )
    p = window_starts(int(n_pings), int(window_pings), overlap)
    b = window_starts(
        int(n_bins), int(window_bins), overlap if overlap_bins is None else overlap_bins
    )
    return np.stack(np.meshgrid(p, b, indexing="ij"), axis=-1).reshape(-1, 2)


def _window_sums(valid: np.ndarray, origins: np.ndarray, h: int, w: int) -> np.ndarray:
    """``(2, K)`` valid-pixel counts of each window of each head (integral image)."""
    v = np.transpose(valid, (1, 0, 2)).astype(np.int64)  # (2, P, B)
    s = np.zeros((2, v.shape[1] + 1, v.shape[2] + 1), np.int64)
    s[:, 1:, 1:] = v.cumsum(axis=1).cumsum(axis=2)
    p, b = origins[:, 0], origins[:, 1]
    return s[:, p + h, b + w] - s[:, p, b + w] - s[:, p + h, b] + s[:, p, b]


# ----------------------------------------------------------------------------- dataset
@dataclass
class WindowLine:
    """One line ready for windowing.

    Attributes:
        name: line name.
        intensity: ``(P, 2, B)`` float32 intensities normalised over the sonar-only valid bins.
        n_lat: ``(P, 2, B)`` float32 draped n_lat, 0 where invalid.
        valid: ``(P, 2, B)`` bool, True where the draping mask is 0 (the loss's pixels).
        altitude_m: ``(P,)`` altitude (m; NaN where missing), for the geometry channels.
        range_m: ``(B,)`` slant ranges (m).
        channels: the network's input channels (:func:`~sss2bathy.data.masks.input_channels`).
        relative: ``(P, 2, B)`` float32 ``relative`` channel of the whole line
            (:func:`~sss2bathy.data.masks.relative_channel`), when ``channels`` holds it.
    """

    name: str
    intensity: np.ndarray
    n_lat: np.ndarray
    valid: np.ndarray
    altitude_m: np.ndarray | None = None
    range_m: np.ndarray | None = None
    channels: tuple[str, ...] = ("intensity",)
    relative: np.ndarray | None = None

    @classmethod
    def from_draped(
        cls,
        line: SidescanLine,
        draped: DrapedLine,
        sonar_mask: SonarMaskConfig | Mapping[str, Any] | None = None,
        channels: Sequence[str] | None = None,
    ) -> WindowLine:
        """Normalise ``line``'s intensities over its sonar-only valid bins (as at inference)
        and attach the draping (the loss's targets and pixels)."""
        if draped.shape != line.intensity.shape:
            raise ValueError(
                f"draped: expected shape {line.intensity.shape} of line '{line.name}', "
                f"found {draped.shape}"
            )
        valid = draped.valid & np.isfinite(draped.n_lat) & np.isfinite(line.intensity)
        intensity, mask = sonar_normalized_intensity(line, sonar_mask)
        channels = check_channels(channels)
        relative = relative_channel(intensity, mask) if "relative" in channels else None
        return cls(
            name=line.name,
            intensity=intensity,
            n_lat=np.where(valid, draped.n_lat, 0.0).astype(np.float32),
            valid=valid,
            altitude_m=np.asarray(line.altitude_m, np.float32),
            range_m=np.asarray(line.range_m, np.float32),
            channels=channels,
            relative=relative,
        )

    def inputs(self, pings: slice, side: int, bins: slice) -> np.ndarray:
        """``(C, h, w)`` float32 input channels of one window (unflipped)."""
        x = self.intensity[pings, side, bins]
        if self.channels == ("intensity",):
            return x[None]
        rel = None
        if "relative" in self.channels:
            if self.relative is None:
                raise ValueError(
                    f"line '{self.name}': input channels {list(self.channels)} need its "
                    "'relative' channel (build the line with WindowLine.from_draped)"
                )
            rel = self.relative[pings, side, bins]
            if self.channels == ("relative",):
                return rel[None]
        if self.altitude_m is None or self.range_m is None:
            raise ValueError(
                f"line '{self.name}': input channels {list(self.channels)} need altitude_m and "
                "range_m (build the line with WindowLine.from_draped)"
            )
        r_max = float(np.max(self.range_m))
        opp = self.intensity[pings, 1 - side, bins] if "opposite" in self.channels else None
        return input_channels(
            x,
            self.range_m[bins],
            self.altitude_m[pings],
            r_max,
            self.channels,
            relative=rel,
            opposite=opp,
        )


class SidescanWindowDataset(Dataset):
    """Windows of both heads of a list of lines.

    Items ``0 .. len-1`` are the windows as recorded; when ``flip_augment`` is True,
    items ``len .. 2*len-1`` are the same windows flipped along track (what
    :class:`FlipShuffleSampler` draws). Each item is a dict as in the module docstring,
    without the batch dimension.

    Attributes:
        line_names: names of the lines, indexed by the ``line`` key.
        index: ``(N, 4)`` int64 rows ``[line, side, ping_start, bin_start]``.
        window_bins: the resolved window width (``B`` when configured as ``None``).
        skipped: ``{"low_valid_windows": ..., "short_lines": ...}`` counts.
    """

    def __init__(
        self,
        lines: Sequence[WindowLine],
        window_pings: int = 64,
        window_bins: int | None = 512,
        overlap: float = 0.75,
        min_valid_fraction: float = 0.2,
        flip_augment: bool = False,
        name: str = "windows",
        overlap_bins: float | None = None,
    ) -> None:
        if not lines:
            raise ValueError(f"lines: expected at least one line for {name}, found none")
        if not (isinstance(window_pings, int) and window_pings >= 1):
            raise ValueError(f"window_pings: expected a positive integer, found {window_pings!r}")
        if not (0.0 <= min_valid_fraction <= 1.0):
            raise ValueError(
                f"min_valid_fraction: expected a fraction in [0, 1], found {min_valid_fraction}"
            )
        n_bins = {ln.intensity.shape[2] for ln in lines}
        if window_bins is None:
            if len(n_bins) != 1:
                raise ValueError(
                    f"window_bins: None (= the lines' bin count) needs one bin count, "
                    f"found {sorted(n_bins)} in {name}"
                )
            window_bins = n_bins.pop()
        if not (isinstance(window_bins, int) and window_bins >= 1):
            raise ValueError(f"window_bins: expected a positive integer, found {window_bins!r}")
        for ln in lines:
            if ln.intensity.shape[2] < window_bins:
                raise ValueError(
                    f"window_bins: expected at most the {ln.intensity.shape[2]} bins of line "
                    f"'{ln.name}' ({name}), found window_bins={window_bins}; lower "
                    "data.window_bins or set it to null to use the lines' bin count"
                )
        self.lines = list(lines)
        self.line_names = [ln.name for ln in self.lines]
        self.window_pings, self.window_bins = window_pings, window_bins
        self.flip_augment = flip_augment
        self.name = name
        need = int(np.ceil(min_valid_fraction * window_pings * window_bins))
        rows, low, short = [], 0, []
        for li, ln in enumerate(self.lines):
            P, _, B = ln.intensity.shape
            if P < window_pings:
                short.append(ln.name)
                continue
            origins = line_windows(P, B, window_pings, window_bins, overlap, overlap_bins)
            counts = _window_sums(ln.valid, origins, window_pings, window_bins)
            keep = counts >= max(need, 1)
            low += int((~keep).sum())
            for side in (0, 1):
                o = origins[keep[side]]
                rows.append(
                    np.column_stack(
                        [np.full(len(o), li), np.full(len(o), side), o[:, 0], o[:, 1]]
                    ).astype(np.int64)
                )
        self.index = np.concatenate(rows) if rows else np.zeros((0, 4), np.int64)
        self.skipped = {"low_valid_windows": low, "short_lines": len(short)}
        if short:
            log.warning(
                "%s: skipped %d line(s) shorter than window_pings=%d: %s",
                name,
                len(short),
                window_pings,
                short,
            )
        log.info(
            "%s: %d windows of %dx%d from %d lines (skipped %d windows with < %.0f%% valid pixels)",
            name,
            len(self.index),
            window_pings,
            window_bins,
            len(self.lines) - len(short),
            low,
            100 * min_valid_fraction,
        )
        if len(self.index) == 0:
            raise ValueError(
                f"{name}: zero windows of {window_pings}x{window_bins} from lines "
                f"{self.line_names}: {low} windows had fewer than {need} valid pixels "
                f"(min_valid_fraction={min_valid_fraction}) and {len(short)} line(s) were "
                f"shorter than {window_pings} pings; check the draping masks, or lower "
                "min_valid_fraction / the window size"
            )

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, item: int) -> dict[str, torch.Tensor]:
        n = len(self.index)
        flipped = item >= n
        if item < 0 or item >= (2 * n if self.flip_augment else n):
            raise IndexError(f"item: expected an index in [0, {n}) (x2 with flips), found {item}")
        li, side, p0, b0 = (int(v) for v in self.index[item % n])
        ln = self.lines[li]
        win = (slice(p0, p0 + self.window_pings), side, slice(b0, b0 + self.window_bins))
        inputs = ln.inputs(win[0], side, win[2])
        arrays = [ln.intensity[win], ln.n_lat[win], ln.valid[win]]
        if flipped:
            arrays = [a[::-1] for a in arrays]
            inputs = inputs[:, ::-1]
        intensity, n_lat, valid = (torch.from_numpy(np.ascontiguousarray(a)) for a in arrays)
        return {
            "intensity": intensity.unsqueeze(0),
            "inputs": torch.from_numpy(np.ascontiguousarray(inputs)),
            "n_lat": n_lat.unsqueeze(0),
            "mask": valid.unsqueeze(0),
            "line": torch.tensor(li, dtype=torch.long),
            "side": torch.tensor(side, dtype=torch.long),
            "ping_start": torch.tensor(p0, dtype=torch.long),
            "bin_start": torch.tensor(b0, dtype=torch.long),
            "flipped": torch.tensor(flipped, dtype=torch.bool),
        }


class EpochSampler:
    """Epoch counter and resume skip shared by the resumable samplers: the draw of epoch
    ``e`` depends on ``(seed, e)`` only, and :meth:`skip` drops the items a resumed epoch
    has already served (:class:`ResumableDataLoader` calls it)."""

    epoch: int = 0
    _skip: int = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def skip(self, n_items: int) -> None:
        """Leave out the first ``n_items`` of the next iteration (a resumed epoch)."""
        self._skip = int(n_items)


class FlipShuffleSampler(EpochSampler, Sampler[int]):
    """Shuffles ``n`` windows and flips each with probability 1/2 (item ``i + n``).

    The permutation and the flips come from ``seed`` and the epoch number (incremented
    at every ``iter``, or set with :meth:`set_epoch`), so a run is reproducible and
    independent of data-loader workers.
    """

    def __init__(self, n: int, flip: bool = True, shuffle: bool = True, seed: int = 0) -> None:
        if n < 1:
            raise ValueError(f"n: expected at least one item, found {n}")
        self.n, self.flip, self.shuffle, self.seed = n, flip, shuffle, seed
        self.epoch = 0
        self._skip = 0

    def __len__(self) -> int:
        return self.n

    def __iter__(self) -> Iterator[int]:
        rng = np.random.default_rng([self.seed, self.epoch])
        self.epoch += 1
        order = rng.permutation(self.n) if self.shuffle else np.arange(self.n)
        flips = rng.random(self.n) < 0.5 if self.flip else np.zeros(self.n, bool)
        start, self._skip = self._skip, 0
        return iter((order + self.n * flips[order])[start:].tolist())


class ResumableDataLoader(DataLoader):
    """A ``DataLoader`` whose position Lightning checkpoints, for exact mid-epoch resumes.

    Its sampler draws each epoch's order from ``(seed, epoch)`` (``set_epoch``, which Lightning
    calls before every epoch) and has ``skip(n_items)`` (leave out the first items of the next
    iteration), as :class:`FlipShuffleSampler` and
    :class:`~sss2bathy.data.pings.PingBatchSampler`. :meth:`state_dict` holds the epoch and
    the number of batches of it served so far (counted as they leave the loader, so worker
    prefetching does not matter); after :meth:`load_state_dict`, iterating that epoch again
    serves only the remaining batches. Lightning saves and restores the state with the fit
    loop (``loops.fit_loop.state_dict.combined_loader`` in the checkpoint): a run resumed from
    a mid-epoch checkpoint sees the batches the uninterrupted run would have seen.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._epoch = -1
        self._served = 0
        self._resume: tuple[int, int] | None = None

    def state_dict(self) -> dict[str, int]:
        return {"epoch": self._epoch, "batches": self._served}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self._resume = (int(state["epoch"]), int(state["batches"]))

    def __iter__(self) -> Iterator[Any]:
        # a generator: runs at the first next(), after Lightning's set_epoch
        epoch = int(getattr(self.sampler, "epoch", -1))
        skip = 0
        if self._resume is not None and self._resume[0] == epoch and hasattr(self.sampler, "skip"):
            skip = self._resume[1]
            self.sampler.skip(skip * (self.batch_size or 1))
        self._resume = None
        self._epoch, self._served = epoch, skip
        for batch in super().__iter__():
            self._served += 1
            yield batch


# -------------------------------------------------------------------------- datamodule
def union_envelopes(envelopes: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """One sonar envelope spanning several (:func:`~sss2bathy.data.sonar_envelope.
    sonar_envelope` of each training survey): per setting the min of the lows and the max
    of the highs; ``survey`` names them all (``a+b``), ``n_lines`` sums them."""
    if not envelopes:
        raise ValueError("envelopes: expected at least one sonar envelope, found none")
    settings: dict[str, list[float]] = {}
    for env in envelopes:
        for key, (lo, hi) in env["settings"].items():
            old = settings.get(key)
            settings[key] = [float(lo), float(hi)] if old is None else [
                min(old[0], float(lo)), max(old[1], float(hi))
            ]  # fmt: skip
    first = envelopes[0]
    return {
        "version": first["version"],
        "survey": "+".join(str(e["survey"]) for e in envelopes),
        "n_lines": int(sum(int(e["n_lines"]) for e in envelopes)),
        "settings": {k: settings[k] for k in first["settings"]} | settings,
    }


def _to_dict(cfg: Any, name: str) -> dict[str, Any]:
    """A plain dict from a mapping or an OmegaConf DictConfig (interpolations resolved)."""
    try:
        from omegaconf import DictConfig, OmegaConf

        if isinstance(cfg, DictConfig):
            cfg = OmegaConf.to_container(cfg, resolve=True)
    except ImportError:  # pragma: no cover - omegaconf is a dependency
        pass
    if not isinstance(cfg, Mapping):
        raise ValueError(f"{name}: expected a mapping, found {type(cfg).__name__}")
    return dict(cfg)


def _survey_dict(cfg: Any, name: str) -> dict[str, Any]:
    out = _to_dict(cfg, name)
    if "kind" not in out:
        raise ValueError(f"{name}: expected a data/survey config with a 'kind' key, found {out}")
    return out


def prepare_survey(survey_cfg: Mapping[str, Any], data_dir: str, drape: DrapeConfig) -> None:
    """Generate or import one survey and drape it (both cached under ``data_dir``); a plain
    function, so :meth:`SidescanWindowDataModule.prepare_data` can run several at once."""
    from sss2bathy.data.sources import load_survey

    survey, folder = load_survey(survey_cfg, data_dir)
    drape_survey(survey, folder, drape)


class SidescanWindowDataModule(pl.LightningDataModule):
    """Windows for training, validating and testing the normal-estimation CNN.

    Splits are by line: ``train`` = the survey's ``train`` split minus the validation
    lines; ``val`` = ``max(1, round(val_fraction * n_train))`` training lines drawn with
    ``seed``; ``test`` = the survey's ``test`` split. ``test_dataloader`` returns a list:
    index 0 the survey's test split, then one loader per entry of ``test_surveys`` (all
    of its lines), in order; ``test_set_names`` names them.

    Several seabeds (a pretrained CNN): with ``train_surveys`` the training lines are the
    ``train`` splits of those surveys, pooled (line names ``<survey>/<line>``), and the
    survey's own lines serve its ``test`` split only; with ``val_surveys`` the validation
    lines are all lines of those surveys instead of lines carved from the training lines.

    Args:
        survey: the ``data/survey`` config (``kind``: synthetic | folder | xtf, ...).
        data_dir: where surveys are generated/cached (``paths.data_dir``).
        window_pings, window_bins: window size (``window_bins=None``: the lines' bins).
        overlap: overlap of consecutive windows (fraction).
        min_valid_fraction: windows with fewer valid pixels are skipped.
        flip_augment: random along-track flips in training.
        val_fraction: fraction of training lines held out for validation (at least one).
        batch_size, num_workers, pin_memory: data-loader settings.
        drape: :class:`DrapeConfig` fields (``None``: defaults).
        test_surveys: extra ``data/survey`` configs tested on all their lines.
        seed: seed of the validation split and of the training shuffle/flips.
        n_train_lines: use only this many of the survey's training lines (validation lines
            included), the first of a permutation drawn with ``seed`` (a smaller set is part
            of a larger one); None: all. With the survey generated once for the largest
            count the test lines stay the same (``python -m studies.learning_curve``).
        sonar_mask: the sonar-only mask the intensity is normalised over
            (:class:`~sss2bathy.data.masks.SonarMaskConfig` fields; ``None``: defaults).
        input_channels: the network's input channels (``None``: ``[intensity]``); stored in
            the checkpoint with ``sonar_mask`` so prediction builds the same inputs.
        train_surveys: ``data/survey`` configs whose ``train`` splits are the training lines
            (None: the survey's own training lines).
        val_surveys: ``data/survey`` configs whose lines (all of them) validate (None: lines
            carved from the training lines with ``val_fraction``).
        overlap_bins: overlap of consecutive windows across track (None: ``overlap``); with
            lines wider than ``window_bins``.
        prepare_jobs: surveys generated and draped at once by :meth:`prepare_data`, each
            in its own process (1: one after another, in this process). Twelve pretraining
            seabeds took 118 s side by side on 16 cores, ~15 min one after another on one.

    ``setup("fit")`` records the training lines' sonar (over every training survey) in
    :attr:`sonar_envelope`, which
    :class:`~sss2bathy.modules.normal_cnn.NormalCNNModule` stores in its checkpoints (the
    survey the CNN's normals are computed for is compared with it).
    """

    def __init__(
        self,
        survey: Mapping[str, Any],
        data_dir: str,
        window_pings: int = 64,
        window_bins: int | None = 512,
        overlap: float = 0.75,
        min_valid_fraction: float = 0.2,
        flip_augment: bool = True,
        val_fraction: float = 0.1,
        batch_size: int = 64,
        num_workers: int = 0,
        pin_memory: bool = False,
        drape: Mapping[str, Any] | None = None,
        test_surveys: Sequence[Mapping[str, Any]] | None = None,
        seed: int = 0,
        n_train_lines: int | None = None,
        sonar_mask: Mapping[str, Any] | None = None,
        input_channels: Sequence[str] | None = None,
        train_surveys: Sequence[Mapping[str, Any]] | None = None,
        val_surveys: Sequence[Mapping[str, Any]] | None = None,
        overlap_bins: float | None = None,
        prepare_jobs: int = 1,
    ) -> None:
        super().__init__()
        if n_train_lines is not None and not (
            isinstance(n_train_lines, int) and not isinstance(n_train_lines, bool)
            and n_train_lines >= 2
        ):  # fmt: skip
            raise ValueError(
                f"data.n_train_lines: expected null or an integer >= 2, found {n_train_lines!r}"
            )
        self.n_train_lines = n_train_lines
        mask_map = None if sonar_mask is None else _to_dict(sonar_mask, "sonar_mask")
        self.sonar_mask = SonarMaskConfig.coerce(mask_map)
        if input_channels is not None and not isinstance(input_channels, str):
            input_channels = list(input_channels)
        self.input_channels = check_channels(input_channels, "data.input_channels")
        self.survey_cfg = _survey_dict(survey, "survey")
        self.test_survey_cfgs = [
            _survey_dict(c, f"test_surveys[{i}]") for i, c in enumerate(test_surveys or [])
        ]
        self.train_survey_cfgs = [
            _survey_dict(c, f"data.train_surveys[{i}]") for i, c in enumerate(train_surveys or [])
        ]
        self.val_survey_cfgs = [
            _survey_dict(c, f"data.val_surveys[{i}]") for i, c in enumerate(val_surveys or [])
        ]
        if self.train_survey_cfgs and n_train_lines is not None:
            raise ValueError(
                "data.n_train_lines: expected null with data.train_surveys (the subset applies "
                f"to the survey's own training lines), found {n_train_lines}"
            )
        if overlap_bins is not None:
            require_number(
                "overlap_bins", overlap_bins, lambda v: 0 <= v < 1, "a fraction in [0, 1) or null"
            )
        self.overlap_bins = overlap_bins
        drape_map = None if drape is None else _to_dict(drape, "drape")
        self.drape_cfg = DrapeConfig.coerce(drape_map)
        require_int("window_pings", window_pings)
        if window_bins is not None:
            require_int("window_bins", window_bins, expected="a positive integer or null")
        require_number("overlap", overlap, lambda v: 0 <= v < 1, "a fraction in [0, 1)")
        require_number(
            "min_valid_fraction", min_valid_fraction, lambda v: 0 <= v <= 1, "a fraction in [0, 1]"
        )
        require_bool("flip_augment", flip_augment)
        # at least one validation line is drawn whatever the fraction; 0 would read as "none"
        require_number("val_fraction", val_fraction, lambda v: 0 < v < 1, "a fraction in (0, 1)")
        require_int("batch_size", batch_size)
        require_int("num_workers", num_workers, minimum=0)
        require_int("prepare_jobs", prepare_jobs)
        self.prepare_jobs = int(prepare_jobs)
        self.data_dir = str(data_dir)
        self.window_pings, self.window_bins = window_pings, window_bins
        self.overlap, self.min_valid_fraction = overlap, min_valid_fraction
        self.flip_augment, self.val_fraction = flip_augment, val_fraction
        self.batch_size, self.num_workers, self.pin_memory = batch_size, num_workers, pin_memory
        self.seed = int(seed)
        self.save_hyperparameters(
            {
                "survey": self.survey_cfg,
                "window_pings": window_pings,
                "window_bins": window_bins,
                "overlap": overlap,
                "min_valid_fraction": min_valid_fraction,
                "flip_augment": flip_augment,
                "val_fraction": val_fraction,
                "batch_size": batch_size,
                "drape": drape_map,
                "test_surveys": self.test_survey_cfgs,
                "seed": self.seed,
                "n_train_lines": n_train_lines,
                "sonar_mask": self.sonar_mask.to_dict(),
                "input_channels": list(self.input_channels),
                "train_surveys": self.train_survey_cfgs or None,
                "val_surveys": self.val_survey_cfgs or None,
                "overlap_bins": overlap_bins,
            },
            logger=False,
        )
        self.train_set: SidescanWindowDataset | None = None
        self.val_set: SidescanWindowDataset | None = None
        self.test_sets: list[SidescanWindowDataset] | None = None
        self.test_set_names: list[str] = []
        self.train_lines: list[str] = []
        self.val_lines: list[str] = []
        #: the training lines' sonar (:func:`~sss2bathy.data.sonar_envelope.sonar_envelope`),
        #: set by ``setup("fit")``; the CNN module stores it in its checkpoints
        self.sonar_envelope: dict[str, Any] | None = None

    # ------------------------------------------------------------------ data
    def _load(self, survey_cfg: Mapping[str, Any]) -> tuple[Survey, Path]:
        from sss2bathy.data.sources import load_survey

        return load_survey(survey_cfg, self.data_dir)

    def _window_lines(
        self, survey: Survey, folder: Path, names: list[str], prefix: bool = False
    ) -> list[WindowLine]:
        """The lines ``names`` of ``survey``, named ``<survey>/<line>`` when ``prefix``."""
        draped = drape_survey(survey, folder, self.drape_cfg, lines=names)
        lines = [
            WindowLine.from_draped(survey.line(n), draped[n], self.sonar_mask, self.input_channels)
            for n in names
        ]
        if prefix:
            for ln in lines:
                ln.name = f"{survey.name}/{ln.name}"
        return lines

    def _dataset(self, lines: list[WindowLine], name: str, train: bool) -> SidescanWindowDataset:
        return SidescanWindowDataset(
            lines,
            window_pings=self.window_pings,
            window_bins=self.window_bins,
            overlap=self.overlap,
            min_valid_fraction=self.min_valid_fraction,
            flip_augment=train and self.flip_augment,
            name=name,
            overlap_bins=self.overlap_bins,
        )

    def prepare_data(self) -> None:
        """Generate/import the surveys and drape them (both cached on disk), ``prepare_jobs``
        at once."""
        every = [
            self.survey_cfg, *self.train_survey_cfgs, *self.val_survey_cfgs,
            *self.test_survey_cfgs,
        ]  # fmt: skip
        # a survey listed twice (validation and test, say) is prepared once
        cfgs = list({json.dumps(c, sort_keys=True, default=str): c for c in every}.values())
        jobs = min(self.prepare_jobs, len(cfgs))
        if jobs == 1:
            for cfg in cfgs:
                prepare_survey(cfg, self.data_dir, self.drape_cfg)
            return
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        log.info("preparing %d surveys, %d at once", len(cfgs), jobs)
        # spawned workers: no fork of a process that may hold torch's or OpenMP's threads
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=jobs, mp_context=context) as pool:
            futures = [pool.submit(prepare_survey, c, self.data_dir, self.drape_cfg) for c in cfgs]
            for future in futures:
                future.result()  # a failure is raised here, as the serial loop would

    @staticmethod
    def _split(survey: Survey, split: str) -> list[str]:
        if split not in survey.splits:
            raise ValueError(
                f"survey '{survey.name}': expected a '{split}' split, found splits "
                f"{sorted(survey.splits)}"
            )
        names = list(survey.splits[split])
        if not names:
            raise ValueError(f"survey '{survey.name}': split '{split}' has no lines")
        return names

    def setup(self, stage: str | None = None) -> None:
        """Build the datasets of ``stage`` (fit/validate: train+val; test: test sets)."""
        need_fit = stage in (None, "fit", "validate") and self.train_set is None
        need_test = stage in (None, "test") and self.test_sets is None
        if not (need_fit or need_test):
            return
        survey, folder = self._load(self.survey_cfg)
        if need_fit and self.train_survey_cfgs:
            self._setup_pooled()
        elif need_fit:
            train = self._split(survey, "train")
            if self.n_train_lines is not None:
                if self.n_train_lines > len(train):
                    raise ValueError(
                        f"data.n_train_lines: expected at most the {len(train)} training lines "
                        f"of survey '{survey.name}', found {self.n_train_lines}"
                    )
                order = np.random.default_rng([self.seed, 1]).permutation(len(train))
                keep = set(order[: self.n_train_lines].tolist())
                train = [n for i, n in enumerate(train) if i in keep]
            if len(train) < 2:
                raise ValueError(
                    f"survey '{survey.name}': expected at least 2 training lines to carve a "
                    f"validation line from, found {len(train)}"
                )
            if self.val_survey_cfgs:
                self.val_lines, self.train_lines = [], list(train)
            else:
                n_val = min(len(train) - 1, max(1, int(round(self.val_fraction * len(train)))))
                rng = np.random.default_rng(self.seed)
                pick = set(rng.permutation(len(train))[:n_val].tolist())
                self.val_lines = [n for i, n in enumerate(train) if i in pick]
                self.train_lines = [n for i, n in enumerate(train) if i not in pick]
            self.sonar_envelope = sonar_envelope(survey, self.train_lines)
            log.info(
                "training sonar (%d lines of '%s'): %s",
                len(self.train_lines),
                survey.name,
                describe(self.sonar_envelope["settings"]),
            )
            lines = self._window_lines(survey, folder, self.train_lines + self.val_lines)
            by_name = {ln.name: ln for ln in lines}
            self.train_set = self._dataset(
                [by_name[n] for n in self.train_lines], f"{survey.name}:train", train=True
            )
            if self.val_survey_cfgs:
                self._setup_val_surveys()
            else:
                self.val_set = self._dataset(
                    [by_name[n] for n in self.val_lines], f"{survey.name}:val", train=False
                )
        if need_test:
            test = self._split(survey, "test")
            sets = [
                self._dataset(
                    self._window_lines(survey, folder, test), f"{survey.name}:test", False
                )
            ]
            for cfg in self.test_survey_cfgs:
                extra, extra_folder = self._load(cfg)
                names = [ln.name for ln in extra.lines]
                sets.append(
                    self._dataset(
                        self._window_lines(extra, extra_folder, names), f"{extra.name}:all", False
                    )
                )
            self.test_sets = sets
            self.test_set_names = [s.name for s in sets]

    def _setup_val_surveys(self) -> None:
        """The validation set: all lines of ``val_surveys`` (named ``<survey>/<line>``)."""
        lines: list[WindowLine] = []
        for cfg in self.val_survey_cfgs:
            extra, folder = self._load(cfg)
            lines += self._window_lines(extra, folder, [ln.name for ln in extra.lines], True)
        self.val_lines = [ln.name for ln in lines]
        names = "+".join(dict.fromkeys(n.split("/")[0] for n in self.val_lines))
        self.val_set = self._dataset(lines, f"{names}:val", train=False)

    def _setup_pooled(self) -> None:
        """Training lines pooled from the ``train`` splits of ``train_surveys``."""
        lines: list[WindowLine] = []
        envelopes = []
        for cfg in self.train_survey_cfgs:
            survey, folder = self._load(cfg)
            names = self._split(survey, "train")
            envelopes.append(sonar_envelope(survey, names))
            lines += self._window_lines(survey, folder, names, prefix=True)
        if len({ln.name for ln in lines}) != len(lines):
            raise ValueError(
                "data.train_surveys: expected surveys with distinct names, found "
                f"{[e['survey'] for e in envelopes]}"
            )
        self.sonar_envelope = union_envelopes(envelopes)
        log.info(
            "training sonar (%d lines of %s): %s",
            len(lines),
            self.sonar_envelope["survey"],
            describe(self.sonar_envelope["settings"]),
        )
        if self.val_survey_cfgs:
            train = lines
            self._setup_val_surveys()
        else:
            if len(lines) < 2:
                raise ValueError(
                    "data.train_surveys: expected at least 2 training lines to carve a "
                    f"validation line from, found {len(lines)}"
                )
            n_val = min(len(lines) - 1, max(1, int(round(self.val_fraction * len(lines)))))
            pick = set(np.random.default_rng(self.seed).permutation(len(lines))[:n_val].tolist())
            train = [ln for i, ln in enumerate(lines) if i not in pick]
            val = [ln for i, ln in enumerate(lines) if i in pick]
            self.val_lines = [ln.name for ln in val]
            self.val_set = self._dataset(val, "train_surveys:val", train=False)
        self.train_lines = [ln.name for ln in train]
        self.train_set = self._dataset(train, "train_surveys:train", train=True)

    # ----------------------------------------------------------------- loaders
    def _loader(self, ds: Dataset, sampler: Sampler | None = None) -> DataLoader:
        # training: resumable mid-epoch. The loader's own generator seeds the workers, so
        # creating an iterator never draws from the global RNG (a resumed run stays in step)
        cls = DataLoader if sampler is None else ResumableDataLoader
        return cls(
            ds,
            batch_size=self.batch_size,
            sampler=sampler,
            shuffle=False,
            num_workers=self.num_workers,
            pin_memory=self.pin_memory,
            persistent_workers=self.num_workers > 0,
            generator=torch.Generator().manual_seed(self.seed),
        )

    def _require(self, ds: Any, stage: str) -> Any:
        if ds is None:
            raise RuntimeError(f"call setup('{stage}') before asking for its data loader")
        return ds

    def train_dataloader(self) -> DataLoader:
        ds = self._require(self.train_set, "fit")
        sampler = FlipShuffleSampler(len(ds), flip=ds.flip_augment, seed=self.seed)
        return self._loader(ds, sampler)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self._require(self.val_set, "fit"))

    def test_dataloader(self) -> list[DataLoader]:
        """``[survey test split, *test_surveys]`` loaders, named by ``test_set_names``."""
        return [self._loader(ds) for ds in self._require(self.test_sets, "test")]
