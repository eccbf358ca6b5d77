"""The SIREN's settings for a survey's scale: what the map route fits a survey with.

The SIREN reads ``(x, y)`` normalised to ``[-1, 1]`` over its bounds (the tracks' box grown by
the largest slant range), so the ground wavelengths its first sine layer places are set by
``omega0`` *and* the survey's extent: the first layer's weights are ``U(+-1/2)``, so its
finest wavelength is ``lambda_0 = 4 pi E / omega0`` for a half-extent ``E`` (m). The scale
presets keep ``lambda_0`` near 94 m (demo: ``omega0`` 10 over ~150 m; paper: 30 over
~450 m): right for the hills of a 100-m survey, far too coarse for a wreck a few metres wide
seen by a 30-m sidescan. Here ``omega0`` is chosen so that ``lambda_0`` follows the sonar's
range instead (:data:`WAVELENGTH_PER_RANGE`), never below the scale's own ``omega0``, and a
higher ``omega0`` gets at least the fast schedule's steps per epoch (a finer SIREN needs more
steps to settle). Decided on the synthetic wreck survey (``data/survey=synthetic_wrecks``,
``studies/wreck_study.py``, scale=demo), never on a real line: with the scale's omega0 10
no object rises even with the true normals (SIREN-GT-N2d: 0.2 m of a 2.6 m hull); omega0
63 (lambda_0 = range / 2) raises SIREN-Lambert's objects to 0.6-0.8 m (object height MAE
2.06 -> 1.43 m) and locates their outlines, omega0 125 did no better (1.55 m), twice the
steps changed nothing and lr 1e-3 flattened the map. The price: the seabed gets texture,
map MAE 0.253 -> 0.312 m (Lambert), 0.123 -> 0.217 m (GT-N2d). What still capped the
height is in the shadow an object casts, which the masks drop and no sensor model predicts:
a finer SIREN therefore also gets the occlusion term (``model.w_shadow``,
:mod:`sss2bathy.losses.shadow`, :data:`SURVEY_W_SHADOW`), which makes the bins masked as
shadow hidden by what is closer along their ping. On the same survey it raised SIREN-Lambert's
objects to 0.6-1.9 m (object height MAE 1.43 -> 0.89 m, visible 20 -> 80 %) at map MAE
0.319 m (0.312 without it); weights 10 and 100 changed little, 1000 raised the objects as
much at map MAE 0.342 m. On the real Iver2 line the finer SIREN's held-out altimeter error is
0.30 m against the scale's 0.065 m (heights-only alike: it does not bridge 7-m gaps in the
altimeter), which is why these settings (``map_settings=survey``) are an option for seeing
objects, not the default.

The default, ``map_settings=detail``, keeps the scale's SIREN (the *base*, which bridges the
altimeter's gaps) and adds a detail network at the survey's ``omega0``
(:class:`~sss2bathy.models.siren.TwoScaleSiren`, :attr:`MapSettings.detail`): the altimeter
moves the base only, the occlusion term the detail only, and the detail's mean square
(:data:`DETAIL_W`) over the map and under every ping (the nadir, which no bin images) keeps
it at zero wherever the sidescan asks for no relief, with the scale's steps. On the wreck
survey (one fit each) SIREN-Lambert's map MAE 0.253 -> 0.211 m, held-out altimeter 0.118 m
either way, 4 of 5 objects visible (object height MAE 2.06 -> 0.84 m); SIREN-CNN-N2d
0.165 -> 0.141 m (held-out 0.057 -> 0.089 m), 80 % visible. On the real line the K-fold
held-out altimeter error stays within the folds' spread of the scale's (Lambert 0.065 +-
0.007 -> 0.076 +- 0.012 m; CNN-N2d 0.083 +- 0.029 -> 0.088 +- 0.037 m) and the wreck's top
rises 1.0 m above its surroundings in the CNN-N2d map (the scale's: 0.6 m, a smooth hill).
A fit without a sidescan sensor model (heights only) keeps the scale's settings: its detail
would see no data.

Pure functions of numbers (:func:`choose_map_settings`); :func:`survey_scale` measures the
numbers on lines, :func:`scale_of_survey` on an imported survey folder, and
:func:`apply_map_settings` writes the settings into a composed ``train`` config, leaving
every key the user set.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

log = logging.getLogger("sss2bathy.map")

#: the first sine layer's finest ground wavelength per metre of sonar range (lambda_0 =
#: WAVELENGTH_PER_RANGE * range): 0.5 puts 15 m at a 30 m range (studies/wreck_study.py)
WAVELENGTH_PER_RANGE = 0.5
#: the largest omega0 chosen (beyond it the SIREN's initial field is noise at the bin scale)
MAX_OMEGA0 = 200.0
#: the occlusion term's weight with a finer SIREN (``model.w_shadow``; studies/wreck_study.py)
SURVEY_W_SHADOW = 1.0e4
#: ``map_settings=detail``: the weight of the detail network's mean square height
#: (``model.w_detail``, m^-2; studies/wreck_study.py: 10 kept the scale's map error, 30 cost
#: object height)
DETAIL_W = 10.0
#: the settings a map can be fitted with (``map_settings``): the scale preset's own, the
#: finer one-scale SIREN, or the scale's SIREN plus a detail network at the finer omega0
MODES = ("scale", "survey", "detail")


@dataclass(frozen=True)
class SurveyScale:
    """What the SIREN's settings depend on, measured on a survey's lines (metres).

    Attributes:
        range_m: the largest slant range of any bin.
        bin_m: the slant-range bin size (median spacing of the bins' ranges).
        track_m: the tracks' total length.
        half_extent_m: the half-widths ``(E_x, E_y)`` of the SIREN's input box (the tracks'
            bounding box grown by ``range_m``, as ``data.pings`` sets the bounds).
        n_pings: pings over all lines.
    """

    range_m: float
    bin_m: float
    track_m: float
    half_extent_m: tuple[float, float]
    n_pings: int

    def __post_init__(self) -> None:
        for name in ("range_m", "bin_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name}: expected a positive number of metres, found {value!r}")
        if not all(math.isfinite(e) and e > 0 for e in self.half_extent_m):
            raise ValueError(
                f"half_extent_m: expected two positive numbers, found {self.half_extent_m!r}"
            )


def survey_scale(positions: Iterable[np.ndarray], ranges: Iterable[np.ndarray]) -> SurveyScale:
    """The :class:`SurveyScale` of lines given by their ``(P, >=2)`` positions (m) and
    ``(B,)`` bin slant ranges (m)."""
    positions = [np.asarray(p, dtype=np.float64) for p in positions]
    ranges = [np.asarray(r, dtype=np.float64) for r in ranges]
    if not positions or len(positions) != len(ranges):
        raise ValueError(
            f"positions, ranges: expected one of each per line, found {len(positions)} and "
            f"{len(ranges)}"
        )
    r_max = max(float(np.nanmax(r)) for r in ranges)
    steps = np.concatenate([np.diff(r) for r in ranges if r.size > 1])
    bin_m = float(np.median(steps)) if steps.size else float("nan")
    xy = np.concatenate([p[:, :2] for p in positions])
    xy = xy[np.isfinite(xy).all(axis=1)]
    if xy.size == 0:
        raise ValueError("positions: expected finite positions, found none")
    track = sum(
        float(np.nansum(np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1))) for p in positions
    )
    span = xy.max(axis=0) - xy.min(axis=0)
    half = (float(span[0] / 2 + r_max), float(span[1] / 2 + r_max))
    return SurveyScale(r_max, bin_m, track, half, int(sum(len(p) for p in positions)))


@dataclass(frozen=True)
class MapSettings:
    """The SIREN settings chosen for a survey (:func:`choose_map_settings`).

    Attributes:
        omega0: the SIREN's ``omega0`` (``model.siren.omega0``).
        steps_per_epoch: batches per epoch (``data.steps_per_epoch``); None: the scale's.
        wavelength_m: the first layer's finest ground wavelength ``lambda_0`` it gives (m).
        w_shadow: the occlusion term's weight (``model.w_shadow``; 0: off, the scale's).
        detail: the finer ``omega0`` goes to a detail network beside the scale's SIREN
            (:class:`~sss2bathy.models.siren.TwoScaleSiren`: ``model.siren.detail_omega0``,
            the base keeps the scale's ``omega0``), held near zero wherever the sidescan does
            not ask for relief and under the pings (``model.w_detail``,
            ``model.detail_nadir``); the altimeter moves the base only
            (``model.heights_on_base``), the occlusion term the detail only
            (``model.shadow_on_detail``).
    """

    omega0: float
    steps_per_epoch: int | None
    wavelength_m: float
    w_shadow: float = 0.0
    detail: bool = False

    def overrides(self) -> dict[str, Any]:
        """The ``train`` config keys and values these settings stand for."""
        out: dict[str, Any] = {}
        if self.detail:
            out["model.siren._target_"] = "sss2bathy.models.siren.TwoScaleSiren"
            out["model.siren.detail_omega0"] = round(self.omega0, 3)
            out["model.w_detail"] = DETAIL_W
            out["model.detail_nadir"] = out["model.heights_on_base"] = True
            if self.w_shadow > 0:
                out["model.shadow_on_detail"] = True
        else:
            out["model.siren.omega0"] = round(self.omega0, 3)
        if self.steps_per_epoch is not None:
            out["data.steps_per_epoch"] = int(self.steps_per_epoch)
        if self.w_shadow > 0:
            out["model.w_shadow"] = float(self.w_shadow)
        return out


def choose_map_settings(
    scale: SurveyScale,
    base_omega0: float,
    base_steps_per_epoch: int | None,
    fast_steps_per_epoch: int | None,
    batch_pings: int,
    wavelength_per_range: float = WAVELENGTH_PER_RANGE,
    detail: bool = False,
) -> MapSettings:
    """The SIREN's settings for a survey of ``scale`` (module docstring).

    ``omega0 = 4 pi max(E) / lambda_0`` with ``lambda_0 = wavelength_per_range * range``,
    at least ``base_omega0`` (the scale's) and at most :data:`MAX_OMEGA0`. When that raises
    ``omega0``, an epoch gets at least ``fast_steps_per_epoch`` batches (the scale's
    ``siren_schedule=fast`` count; None: no minimum); otherwise the scale's steps stand.
    ``base_steps_per_epoch`` None means every ping once per epoch (``batch_pings`` each).
    A finer SIREN than the scale's also gets the occlusion term (:data:`SURVEY_W_SHADOW`).
    ``detail``: that finer ``omega0`` is a detail network's beside the scale's SIREN
    (:attr:`MapSettings.detail`) with the scale's steps; where it is no finer than the
    scale's there is no detail.
    """
    if not (math.isfinite(base_omega0) and base_omega0 > 0):
        raise ValueError(f"base_omega0: expected a positive number, found {base_omega0!r}")
    if not (math.isfinite(wavelength_per_range) and wavelength_per_range > 0):
        raise ValueError(
            f"wavelength_per_range: expected a positive number, found {wavelength_per_range!r}"
        )
    if int(batch_pings) < 1:
        raise ValueError(f"batch_pings: expected a positive integer, found {batch_pings!r}")
    wavelength = wavelength_per_range * scale.range_m
    omega0 = 4 * math.pi * max(scale.half_extent_m) / wavelength
    omega0 = min(max(omega0, float(base_omega0)), MAX_OMEGA0)
    steps = None
    # a finer one-scale SIREN needs the steps; the detail network settles within the
    # scale's (more steps there cost the base its held-out altimeter error: 0.118 -> 0.191 m)
    if omega0 > base_omega0 and fast_steps_per_epoch is not None and not detail:
        current = base_steps_per_epoch or math.ceil(scale.n_pings / int(batch_pings))
        if current < fast_steps_per_epoch:
            steps = int(fast_steps_per_epoch)
    finest = 4 * math.pi * max(scale.half_extent_m) / omega0
    finer = omega0 > base_omega0
    return MapSettings(
        omega0, steps, finest, SURVEY_W_SHADOW if finer else 0.0, detail=bool(detail) and finer
    )


#: the sensor models the occlusion term applies to (model.sensor._target_)
SIDESCAN_SENSORS = (
    "sss2bathy.models.normal_sensor.NormalSensorModel",
    "sss2bathy.models.lambertian.LambertianSensorModel",
)


def scale_of_survey(folder: Any) -> SurveyScale:
    """The :class:`SurveyScale` of an imported survey folder: all its lines (a tile job's
    folder holds the runs of pings its SIREN spans), of which only the positions and bin
    ranges are read (not the intensities)."""
    from pathlib import Path

    from sss2bathy.survey import Survey

    folder = Path(folder)
    positions, ranges = [], []
    for name in Survey.read_manifest(folder).get("lines") or []:
        with np.load(folder / "lines" / f"{name}.npz", allow_pickle=False) as line:
            positions.append(line["position"])
            ranges.append(line["range_m"])
    return survey_scale(positions, ranges)


#: a user's key that stands for a settings key (the model's value interpolates the scale's)
_ALIASES = {
    "scale.siren.omega0": "model.siren.omega0",
    "scale.siren.steps_per_epoch": "data.steps_per_epoch",
}


def _user_keys(overrides: Sequence[str]) -> set[str]:
    keys = set()
    for item in overrides:
        key = str(item).split("=", 1)[0].lstrip("+~")
        keys.add(_ALIASES.get(key, key))
    return keys


def apply_map_settings(
    train_cfg: Any, scale: SurveyScale, user_overrides: Sequence[str], mode: str = "survey"
) -> dict:
    """Write :func:`choose_map_settings` for ``scale`` into the composed ``train_cfg`` (in
    place, an open OmegaConf config), except the keys in ``user_overrides`` (``key=value``
    strings; ``scale.siren.omega0`` / ``scale.siren.steps_per_epoch`` count as the model's
    and the data's); returns what was set. The base values are the composed config's own
    (its scale's; a ``siren_schedule`` already at the fast step count keeps its steps).

    ``mode`` (:data:`MODES`): ``scale`` sets nothing; ``survey`` the finer one-scale SIREN,
    with the occlusion term for a sidescan sensor model unless the user chose ``omega0``;
    ``detail`` the scale's SIREN plus a detail network at the finer ``omega0``
    (:attr:`MapSettings.detail`) for a sidescan sensor model, unless the user chose
    ``model.siren._target_``; without a sidescan (heights only) the detail would see no
    data, so that fit keeps the scale's settings.
    """
    from omegaconf import OmegaConf

    if mode not in MODES:
        raise ValueError(f"map_settings: expected one of {', '.join(MODES)}, found {mode!r}")
    user = _user_keys(user_overrides)
    # the occlusion term and the detail network need a sidescan sensor model
    sensor = OmegaConf.select(train_cfg, "model.sensor._target_", default=None)
    sidescan = sensor in SIDESCAN_SENSORS
    detail = mode == "detail" and sidescan and "model.siren._target_" not in user
    if mode == "scale" or (mode == "detail" and not detail):
        return {}
    siren = train_cfg.scale.siren
    settings = choose_map_settings(
        scale,
        base_omega0=float(train_cfg.model.siren.omega0),
        base_steps_per_epoch=train_cfg.data.get("steps_per_epoch"),
        fast_steps_per_epoch=siren.get("fast_steps_per_epoch"),
        batch_pings=int(train_cfg.data.batch_pings),
        detail=detail,
    )
    # the occlusion term goes with the finer SIREN: not where the user chose a one-scale
    # SIREN's omega0 (a detail network's omega0 is the map route's either way)
    shadow = sidescan and (detail or "model.siren.omega0" not in user)
    applied = {}
    for key, value in settings.overrides().items():
        if key in user or (key == "model.w_shadow" and not shadow):
            continue
        OmegaConf.update(train_cfg, key, value, merge=False, force_add=True)
        applied[key] = value
    log.info(
        "map settings (%s) for a %.0f m range, %.3f m bins, %.0f m of track (half-extent "
        "%.0f m): %s (finest first-layer wavelength %.1f m)",
        mode,
        scale.range_m,
        scale.bin_m,
        scale.track_m,
        max(scale.half_extent_m),
        applied or "the scale's own",
        settings.wavelength_m,
    )
    return applied
