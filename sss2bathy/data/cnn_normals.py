"""The CNN's normals for whole lines, the input of the SIREN's ``normals=cnn``.

What the SIREN stage needs of a trained :class:`~sss2bathy.modules.normal_cnn.NormalCNNModule`
lives here, in the data layer, so that ``data/`` never imports ``modules/``: finding the
checkpoint (:func:`latest_checkpoint`, :func:`resolve_cnn_checkpoint`), rebuilding its plain
network from the checkpoint alone (:func:`load_normal_net`, classes of ``sss2bathy.models``),
predicting and stitching (:func:`predict_normals`) and caching the predictions.

Each head of each line is cut into windows of ``window_pings x window_bins`` with the
training overlap, or the inference ``overlap`` when one is given (origins from
:func:`sss2bathy.data.windows.line_windows`: a regular stride, the last window flush with
the end), the windows run through the network in batches, and overlapping predictions are
averaged back into the ``(P, 2, B)`` waterfall (one ``bincount`` per head, no loop over
windows). Lines shorter than a window are zero-padded (and the padding cropped off).
Inference overlap 0.5 instead of the training 0.75 halves the windows (the cost); bf16
``precision`` (a bfloat16 copy of the network, channels-last with per-channel group norms
on a CPU, :func:`inference_net`) divides each window's cost by ~4.3 (batches of 8, 2
threads) on a CPU with AMX but multiplies it ~170x on an AVX2-only CPU (emulated;
:func:`cpu_has_native_bf16`, a warning) (``python -m benchmarks.cnn_inference``; accuracy:
``python -m benchmarks.cnn_inference_accuracy``).

Inputs come from the sidescan alone, exactly as in training
(:class:`sss2bathy.data.windows.WindowLine`): the intensity is normalised over the bins
valid in the sonar-only mask (:func:`sss2bathy.data.masks.sonar_mask`, with the
``sonar_mask`` parameters the checkpoint was trained with), and the input channels
(``input_channels`` of the checkpoint; old checkpoints: intensity only) are stacked by
:func:`sss2bathy.data.masks.input_channels`. The MBES grid is never looked at: the result
is the same with or without one.

Masks: the result's mask is the sonar-only mask; ``draped`` lines (optional, for display
and scoring only) are OR-ed into the returned mask and never change a prediction.
Invalid bins hold NaN in ``n_lat``.

The survey's sonar is compared with the one the checkpoint was trained on (its
``sonar_envelope``, :mod:`sss2bathy.data.sonar_envelope`): one WARNING names each setting
outside the trained range (or says a checkpoint records none); the normals are computed all
the same.

Besides Lightning checkpoints (``.ckpt``), every function here takes an exported model: a
``<name>.safetensors`` with its ``<name>.json`` (:mod:`sss2bathy.data.cnn_model_file`;
``python -m sss2bathy.pretrained export``), and ``"pretrained"``: the model shipped in the
package (:data:`PRETRAINED_DIR`, :func:`shipped_model`), resolved by
:func:`resolve_model_path`.

Results are cached per line under ``survey_dir/predictions/<key>/<line>.npz`` where ``key``
hashes the checkpoint file's content, the window size and overlap (the one used), the input
channels, the sonar-mask parameters and the precision (only when not fp32, so older float32
caches stay valid); a cached file whose key, shape or mask does not match is
recomputed with a warning.
"""

from __future__ import annotations

import copy
import importlib
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from sss2bathy.data.cnn_model_file import NET_PACKAGE, as_checkpoint, is_model_file
from sss2bathy.data.masks import (
    DEFAULT_CHANNELS,
    SonarMaskConfig,
    check_channels,
    input_channels,
    relative_channel,
    sonar_normalized_intensity,
    sonar_only_mask,
)
from sss2bathy.data.sonar_envelope import CHECKPOINT_KEY as SONAR_ENVELOPE_KEY
from sss2bathy.data.sonar_envelope import envelope_warning
from sss2bathy.data.windows import line_windows
from sss2bathy.models.normal_cnn import channel_norm_copy
from sss2bathy.survey import MASK_VALID, Survey
from sss2bathy.utils.atomic import atomic_path, file_sha256, stable_hash
from sss2bathy.utils.checkpoints import (
    KIND_CNN,
    RUNS_PATTERNS,
    expect_kind,
    find_checkpoints,
    read_checkpoint,
    run_scale,
)
from sss2bathy.utils.progress import log_progress

log = logging.getLogger(__name__)

#: ``cnn_checkpoint=pretrained``: the model shipped in the package, its folder and file stem
#: (``<PRETRAINED_DIR>/<PRETRAINED_NAME>.safetensors`` + ``.json``). The folder is the package
#: ``sss2bathy.pretrained`` (which exports models); found by path, not imported.
PRETRAINED = "pretrained"
PRETRAINED_DIR = Path(__file__).resolve().parents[1] / "pretrained"
PRETRAINED_NAME = "normal_cnn"
COMPILED_PREFIX = "_orig_mod."
#: Windows per forward pass on a CPU unless asked otherwise (``predict_normals(batch_size=)``):
#: the paper network ran at 8.9 windows/s in bf16 with batches of 8 against 7.1 (4), 5.9
#: (16) and 5.4 (64, its training batch), fp32 3.07 against 2.39 at 64 (2-core Xeon with
#: AMX, ``python -m benchmarks.cnn_inference --batch N``): a batch's full-resolution
#: activations must stay in the caches. Results do not depend on it.
CPU_INFERENCE_BATCH = 8
CACHE_VERSION = 2  # 2: sonar-only input normalisation, input channels in the key
#: Inference precisions (``predict_normals(precision=...)``): the network's dtype, if not fp32.
PRECISIONS: dict[str, torch.dtype | None] = {"fp32": None, "bf16": torch.bfloat16}
#: Sonar warnings already given in this process, so one survey's several calls (splits) warn once.
_SONAR_WARNED: set[str] = set()


# --------------------------------------------------------------------- checkpoints
def latest_checkpoint(
    runs_dir: str | Path, scale: str | None = None, key: str = "data.normals.checkpoint"
) -> Path:
    """Newest ``**/checkpoints/last.ckpt`` under ``runs_dir`` (by modification time).

    With ``scale``, only runs whose Hydra config has that ``scale.name`` count, so a
    tiny-scale test run never stands in for the demo's CNN. ``key`` names the setting in
    errors.
    """
    found = find_checkpoints(runs_dir, RUNS_PATTERNS)
    if not found:
        raise ValueError(
            f"{key}: expected a trained CNN ('latest' = newest "
            f"**/checkpoints/last.ckpt under {runs_dir}), found none; train it first "
            "(make cnn) or give a checkpoint path"
        )
    if scale is not None:
        matching = [p for p in found if run_scale(p) == scale]
        if not matching:
            raise ValueError(
                f"{key}: expected a CNN run of scale={scale} ('latest' under "
                f"{runs_dir}), found {len(found)} run(s) of other scales "
                f"({sorted({str(run_scale(p)) for p in found})}); train it at this scale "
                "(make cnn SCALE=...) or give a checkpoint path"
            )
        found = matching
    return found[-1]


def shipped_model(folder: str | Path | None = None, name: str = PRETRAINED_NAME) -> Path | None:
    """The weights file of the model shipped in the package (``folder``: another folder laid
    out the same way), or None when this install ships none (no ``<name>.safetensors``)."""
    path = Path(PRETRAINED_DIR if folder is None else folder) / f"{name}.safetensors"
    return path if path.is_file() else None


def resolve_model_path(ckpt_path: str | Path, key: str = "cnn_checkpoint") -> Path:
    """``"pretrained"`` = :func:`shipped_model` (one line naming ``key`` when none is
    shipped), else ``ckpt_path`` as a path (``~`` expanded; not checked)."""
    if str(ckpt_path) == PRETRAINED:
        shipped = shipped_model()
        if shipped is None:
            raise ValueError(
                f"{key}: expected '{PRETRAINED}' to name the CNN shipped in the package "
                f"({PRETRAINED_DIR / PRETRAINED_NAME}.safetensors), found none in this "
                "install; give a checkpoint path (sss2bathy-train experiment=cnn) instead"
            )
        return shipped
    return Path(str(ckpt_path)).expanduser()


def resolve_cnn_checkpoint(
    ckpt_path: str | Path, runs_dir: str | Path | None, scale: str | None = None, key: str = ""
) -> Path:
    """A CNN checkpoint file: ``"latest"`` = :func:`latest_checkpoint` of ``runs_dir`` (runs
    of ``scale`` only, when given), ``"pretrained"`` = the shipped model
    (:func:`resolve_model_path`), otherwise ``ckpt_path`` (a ``.ckpt``, or an exported
    ``.safetensors`` / ``.json``), which must be a file. ``key`` names the setting in errors
    (``cnn_checkpoint``, ``ckpt_path``)."""
    key = key or "cnn_checkpoint"
    if str(ckpt_path) == PRETRAINED:
        return resolve_model_path(ckpt_path, key)
    if str(ckpt_path) == "latest":
        if runs_dir is None:
            raise ValueError(f"{key}: 'latest' needs the folder of the CNN runs, found none")
        return latest_checkpoint(runs_dir, scale, key)
    path = Path(ckpt_path)
    if not path.is_file():
        raise FileNotFoundError(f"{key}: expected a CNN checkpoint file or 'latest', found {path}")
    return path


# --------------------------------------------------------------------- windows
def stitch_windows(
    windows: np.ndarray, origins: np.ndarray | Sequence[tuple[int, int]], shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Average overlapping windows back into a waterfall.

    Args:
        windows: ``(N, h, w)`` values.
        origins: ``(N, 2)`` ``(ping0, bin0)`` of each window's first pixel.
        shape: ``(P, B)`` waterfall shape; every window must lie inside it.

    Returns:
        ``(mean (P, B) float32, count (P, B) int32)``: the mean of all windows covering each
        pixel (NaN where none does) and the number of windows that cover it.
    """
    windows = np.asarray(windows)
    origins = np.asarray(origins, dtype=np.int64)
    if origins.size == 0:
        origins = origins.reshape(0, 2)
    if windows.ndim != 3:
        raise ValueError(f"windows: expected shape (N, h, w), found {windows.shape}")
    if origins.shape != (windows.shape[0], 2):
        raise ValueError(f"origins: expected shape ({windows.shape[0]}, 2), found {origins.shape}")
    if len(shape) != 2 or min(shape) < 1:
        raise ValueError(f"shape: expected (P, B) with P, B >= 1, found {shape}")
    n_pings, n_bins = int(shape[0]), int(shape[1])
    h, w = windows.shape[1:]
    outside = (
        (origins[:, 0] < 0)
        | (origins[:, 1] < 0)
        | (origins[:, 0] + h > n_pings)
        | (origins[:, 1] + w > n_bins)
    )
    if outside.any():
        bad = int(np.argmax(outside))
        raise ValueError(
            f"origins: expected windows of {h}x{w} inside {shape}, found origin "
            f"{tuple(origins[bad])} (window {bad})"
        )
    rows = origins[:, 0, None, None] + np.arange(h)[None, :, None]
    cols = origins[:, 1, None, None] + np.arange(w)[None, None, :]
    flat = (rows * n_bins + cols).ravel()
    size = n_pings * n_bins
    total = np.bincount(flat, weights=windows.astype(np.float64).ravel(), minlength=size)
    count = np.bincount(flat, minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return mean.reshape(shape).astype(np.float32), count.reshape(shape).astype(np.int32)


# --------------------------------------------------------------------- network
def load_normal_net(ckpt_path: str | Path, map_location: str | torch.device = "cpu") -> nn.Module:
    """Rebuild the network of a :class:`~sss2bathy.modules.normal_cnn.NormalCNNModule`
    checkpoint (safe loading, ``weights_only=True``) or of an exported model (its
    ``.safetensors`` + ``.json``; ``"pretrained"``: the shipped one) and return it in eval
    mode.

    The class comes from ``hyper_parameters.net_config._target_``, which must name a class
    in ``sss2bathy.models`` (a checkpoint can not make us import anything else, and the
    LightningModule is never needed: only its plain network).
    """
    path = resolve_model_path(ckpt_path, "ckpt_path")
    if not path.is_file():
        raise ValueError(f"ckpt_path: expected an existing checkpoint file, found {path}")
    ckpt = _checkpoint(path)
    config = (ckpt.get("hyper_parameters") or {}).get("net_config")
    if not isinstance(config, Mapping) or "_target_" not in config:
        raise ValueError(
            f"ckpt_path: expected a NormalCNNModule checkpoint with hyper_parameters.net_config, "
            f"found keys {sorted(ckpt.get('hyper_parameters') or {})} in {path}"
        )
    target = str(config["_target_"])
    if not target.startswith(NET_PACKAGE):
        raise ValueError(
            f"ckpt_path: net_config._target_ must name a class in {NET_PACKAGE}*, found {target!r}"
        )
    module_name, _, class_name = target.rpartition(".")
    cls = getattr(importlib.import_module(module_name), class_name, None)
    if not (isinstance(cls, type) and issubclass(cls, nn.Module)):
        raise ValueError(f"ckpt_path: net_config._target_ {target!r} is not an nn.Module class")
    net = cls(**{k: v for k, v in config.items() if k != "_target_"})
    state = {
        k[len("net.") :].replace(COMPILED_PREFIX, ""): v
        for k, v in ckpt["state_dict"].items()
        if k.startswith("net.")
    }
    net.load_state_dict(state, strict=True)
    return net.to(map_location).eval()


def check_precision(precision: str, key: str = "precision") -> str:
    """``precision`` if it is one of :data:`PRECISIONS`, else a ``ValueError`` naming ``key``."""
    if precision not in PRECISIONS:
        raise ValueError(f"{key}: expected one of {list(PRECISIONS)}, found {precision!r}")
    return precision


def check_overlap(overlap: Any, key: str = "overlap") -> float | None:
    """``overlap`` as a float if it is ``None`` (the training overlap) or a fraction in
    [0, 1), else a ``ValueError`` naming ``key``."""
    if overlap is None:
        return None
    if not isinstance(overlap, int | float) or isinstance(overlap, bool) or not 0 <= overlap < 1:
        raise ValueError(
            f"{key}: expected null (the training overlap) or a fraction in [0, 1), "
            f"found {overlap!r}"
        )
    return float(overlap)


def predict_waterfall(
    net: nn.Module,
    intensity: np.ndarray,
    window: tuple[int, int],
    overlap: float,
    batch_size: int = 64,
    device: str | torch.device = "cpu",
    precision: str = "fp32",
) -> np.ndarray:
    """Run ``net`` over both heads of a normalised waterfall and stitch by averaging.

    Args:
        net: ``[B, C, h, w]`` -> ``[B, 1, h, w]``.
        intensity: ``(P, 2, B)`` normalised intensity, or ``(P, 2, C, B)`` input channels
            (:func:`sss2bathy.data.masks.input_channels`), finite.
        window: ``(window_pings, window_bins)``.
        overlap: fraction of a window shared with the next, in [0, 1).
        batch_size: windows per forward pass.
        precision: ``"fp32"`` or ``"bf16"`` (a bfloat16 copy of ``net`` on bfloat16
            windows, :func:`inference_net`: ~4.3x the windows/s of float32 for the paper
            network on an AMX CPU, but ~170x slower on an AVX2-only CPU, where it is
            emulated: a warning says so; ``benchmarks/cnn_inference.py``; n_lat changes by
            ~4e-4 on average, at most ~3e-3, on the trained demo net: README).

    Returns:
        ``(P, 2, B)`` float32 prediction for every bin (masking is the caller's).
    """
    check_precision(precision)
    intensity = np.asarray(intensity, dtype=np.float32)
    if intensity.ndim == 3:
        intensity = intensity[:, :, None]
    if intensity.ndim != 4 or intensity.shape[1] != 2:
        raise ValueError(
            f"intensity: expected shape (P, 2, B) or (P, 2, C, B), found {intensity.shape}"
        )
    if not isinstance(batch_size, int) or batch_size < 1:
        raise ValueError(f"batch_size: expected an integer >= 1, found {batch_size!r}")
    h, w = window
    n_pings, _, n_channels, n_bins = intensity.shape
    padded_shape = (max(n_pings, h), max(n_bins, w))
    origins = line_windows(padded_shape[0], padded_shape[1], h, w, overlap)
    out = np.empty((n_pings, 2, n_bins), dtype=np.float32)
    run, dtype = inference_net(net, device, precision)
    for side in range(2):
        waterfall = np.zeros((n_channels, *padded_shape), dtype=np.float32)
        waterfall[:, :n_pings, :n_bins] = np.moveaxis(intensity[:, side], 1, 0)
        view = np.lib.stride_tricks.sliding_window_view(waterfall, (h, w), axis=(1, 2))
        preds = np.empty((len(origins), h, w), dtype=np.float32)
        for start in range(0, len(origins), batch_size):
            o = origins[start : start + batch_size]
            windows = np.moveaxis(view[:, o[:, 0], o[:, 1]], 0, 1)  # (N, C, h, w)
            batch = torch.from_numpy(np.ascontiguousarray(windows)).to(device, dtype)
            with torch.inference_mode():
                pred = run(batch)
            preds[start : start + len(o)] = pred[:, 0].float().cpu().numpy()
        mean, _ = stitch_windows(preds, origins, padded_shape)
        out[:, side] = mean[:n_pings, :n_bins]
    return out


def inference_net(
    net: nn.Module, device: str | torch.device, precision: str
) -> tuple[nn.Module, torch.dtype]:
    """The network ``predict_waterfall`` runs for ``precision`` and the dtype of its
    input windows: ``net`` itself for fp32; for bf16 a copy of ``net`` with bfloat16
    parameters and buffers (``net`` is left as it is), run on bfloat16 windows.

    A bfloat16 copy rather than ``torch.autocast``: autocast casts every convolution's
    input and weights to bfloat16 on each call and leaves the normalisations' outputs in
    float32, so a third of the paper network's time went to those casts (``aten::copy_``
    in a profile); the copy gives the same convolutions in bfloat16 without them
    (``benchmarks/cnn_inference.py``: variants ``bf16`` (autocast) and ``bf16_net_in``).
    On a CPU the copy is also channels-last with its instance norms computed as per-channel
    group norms (:func:`~sss2bathy.models.normal_cnn.channel_norm_copy`: the same function):
    oneDNN runs bfloat16 convolutions channels-last, and ``InstanceNorm2d`` copied each such
    output back to contiguous (variant ``bf16_net``, the one run here, against
    ``bf16_net_in``). On a CPU without native bfloat16 a warning says it is emulated and
    far slower."""
    check_precision(precision)
    dtype = PRECISIONS[precision]
    if dtype is None:
        return net, torch.float32
    params = list(net.parameters())
    if params and all(q.dtype == dtype for q in params):
        return net, dtype  # already the copy (predict_normals makes it once per call)
    dev = torch.device(device)
    if dev.type == "cpu" and not cpu_has_native_bf16():
        log.warning(
            "precision=bf16 on a CPU without native bfloat16 (oneDNN: no AVX512-BF16/AMX; "
            "capability %s): emulated, ~170x SLOWER than fp32 for the paper network "
            "(benchmarks/cnn_inference.py); use fp32 on this machine",
            torch.backends.cpu.get_cpu_capability(),
        )
    if dev.type == "cpu":
        low = channel_norm_copy(net).to(device=dev, dtype=dtype)
        low = low.to(memory_format=torch.channels_last).eval()
    else:
        low = copy.deepcopy(net).to(device=dev, dtype=dtype).eval()
    return low, dtype


def cpu_has_native_bf16() -> bool:
    """Whether oneDNN runs bfloat16 convolutions natively on this CPU (AVX512-BF16 / AMX);
    without, CPU autocast to bf16 is emulated and far slower than float32."""
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # a torch without the op: assume native
        return True


# --------------------------------------------------------------------- masks
def _draped_mask(draped: Any, name: str) -> np.ndarray:
    mask = draped.get("mask") if isinstance(draped, Mapping) else getattr(draped, "mask", None)
    if mask is None:
        raise ValueError(f"draped['{name}']: expected a DrapedLine with a 'mask', found {draped!r}")
    return np.asarray(mask, dtype=np.uint8)


# --------------------------------------------------------------------- cache
def _load_cached(path: Path, key: str, mask: np.ndarray) -> np.ndarray | None:
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            ok = (
                str(data["key"]) == key
                and data["n_lat"].shape == mask.shape
                and np.array_equal(data["mask"], mask)
            )
            if ok:
                return data["n_lat"].astype(np.float32)
    except Exception as exc:  # truncated / corrupt archive: rebuild it
        log.warning("prediction cache %s unreadable (%s); recomputing", path, exc)
        return None
    log.warning("prediction cache %s is stale (key, shape or mask changed); recomputing", path)
    return None


def _save_cached(path: Path, key: str, n_lat: np.ndarray, mask: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, n_lat=n_lat, mask=mask, key=np.array(key))


def _checkpoint(
    ckpt_path: str | Path, key: str = "cnn_checkpoint", weights: bool = True
) -> dict[str, Any]:
    """A CNN checkpoint, loaded safely (``weights_only=True``, on the CPU). Anything else
    (a SIREN or Lambert checkpoint, a truncated, foreign or code-carrying file) is one line
    naming ``key``, the file and what it is
    (:func:`~sss2bathy.utils.checkpoints.read_checkpoint`,
    :func:`~sss2bathy.utils.checkpoints.expect_kind`).

    An exported model (``.safetensors`` / ``.json``, ``"pretrained"``) comes in the same
    shape (:func:`~sss2bathy.data.cnn_model_file.as_checkpoint`: its JSON validated, its
    weights' SHA-256 checked; without ``weights`` only the JSON is read)."""
    ckpt_path = resolve_model_path(ckpt_path, key)
    if is_model_file(ckpt_path):
        try:
            return as_checkpoint(ckpt_path, weights=weights)
        except (ValueError, FileNotFoundError) as err:
            raise type(err)(f"{key}: {err}") from None
    ckpt = read_checkpoint(ckpt_path, key)
    expect_kind(ckpt, ckpt_path, key, KIND_CNN)
    return ckpt


def check_cnn_model(ckpt_path: str | Path, key: str = "cnn_checkpoint") -> Path:
    """The file ``ckpt_path`` names (``"pretrained"`` resolved) once it reads as a CNN: a
    Lightning CNN checkpoint (its kind checked) or an exported model (its JSON validated
    and its weights' SHA-256 checked); else one line naming ``key``."""
    path = resolve_model_path(ckpt_path, key)
    if not path.is_file():
        raise FileNotFoundError(
            f"{key}: expected a CNN checkpoint (.ckpt), an exported model (.safetensors) or "
            f"'{PRETRAINED}', found no file {path}"
        )
    _checkpoint(path, key)
    return path


def model_net_config(ckpt_path: str | Path, key: str = "cnn_checkpoint") -> dict[str, Any]:
    """The network's class path and constructor arguments a checkpoint or exported model
    records (``net_config``)."""
    config = (_checkpoint(ckpt_path, key, weights=False).get("hyper_parameters") or {}).get(
        "net_config"
    )
    if not isinstance(config, Mapping):
        raise ValueError(f"{key}: {ckpt_path} records no network (hyper_parameters.net_config)")
    return dict(config)


def checkpoint_window_config(ckpt_path: str | Path) -> dict[str, Any]:
    """``window_pings``, ``window_bins``, ``overlap`` of the windows a checkpoint was trained
    on, from the datamodule hyper-parameters Lightning stores in it (safe loading)."""
    ckpt = _checkpoint(ckpt_path, weights=False)
    data = ckpt.get("datamodule_hyper_parameters") or {}
    keys = ("window_pings", "window_bins", "overlap")
    missing = [k for k in keys if k not in data]
    if missing:
        raise ValueError(
            f"window_cfg: none given and checkpoint {ckpt_path} stores no datamodule "
            f"hyper-parameters {missing}; pass the training windows' config"
        )
    return {k: data[k] for k in keys}


def checkpoint_input_spec(ckpt_path: str | Path) -> dict[str, Any]:
    """How a checkpoint's inputs were built: ``{"channels": (...), "sonar_mask": {...}}``.

    ``channels``: the module's ``input_channels`` hyper-parameter, else the datamodule's,
    else intensity only (checkpoints from before input channels). ``sonar_mask``: the
    training datamodule's ``sonar_mask`` parameters, else the defaults of
    :class:`~sss2bathy.data.masks.SonarMaskConfig`. Both are validated.
    """
    ckpt = _checkpoint(ckpt_path, weights=False)
    model = ckpt.get("hyper_parameters") or {}
    data = ckpt.get("datamodule_hyper_parameters") or {}
    channels = model.get("input_channels", data.get("input_channels"))
    channels = check_channels(
        DEFAULT_CHANNELS if channels is None else list(channels),
        f"checkpoint {ckpt_path}: input_channels",
    )
    try:
        mask = SonarMaskConfig.coerce(data.get("sonar_mask"))
    except ValueError as err:
        raise ValueError(f"checkpoint {ckpt_path}: {err}") from None
    return {"channels": channels, "sonar_mask": mask.to_dict()}


def checkpoint_sonar_envelope(ckpt_path: str | Path) -> Any:
    """The training sonar a checkpoint stores (``sonar_envelope``), or None (older ones)."""
    return _checkpoint(ckpt_path, weights=False).get(SONAR_ENVELOPE_KEY)


def warn_sonar_outside(ckpt_path: str | Path, survey: Survey, line_names: Sequence[str]) -> None:
    """Log one WARNING when the lines' sonar lies outside the checkpoint's training sonar
    (:func:`~sss2bathy.data.sonar_envelope.envelope_warning`) or the checkpoint records
    none; the same warning is given once per process."""
    message = envelope_warning(
        checkpoint_sonar_envelope(ckpt_path), survey, line_names, str(ckpt_path)
    )
    if message is not None and message not in _SONAR_WARNED:
        _SONAR_WARNED.add(message)
        log.warning("%s", message)


def _window_params(window_cfg: Mapping[str, Any]) -> tuple[int, int | None, float, int]:
    if not isinstance(window_cfg, Mapping):
        raise ValueError(f"window_cfg: expected a mapping, found {type(window_cfg).__name__}")
    for key in ("window_pings", "window_bins", "overlap"):
        if key not in window_cfg:
            raise ValueError(f"window_cfg: missing key '{key}'; found {sorted(window_cfg)}")
    h, w, overlap = window_cfg["window_pings"], window_cfg["window_bins"], window_cfg["overlap"]
    batch = window_cfg.get("batch_size", 64)
    checks = [("window_pings", h), ("batch_size", batch)] + (
        [] if w is None else [("window_bins", w)]
    )
    for name, value in checks:
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise ValueError(f"window_cfg.{name}: expected an integer >= 1, found {value!r}")
    if not isinstance(overlap, int | float) or isinstance(overlap, bool) or not 0 <= overlap < 1:
        raise ValueError(f"window_cfg.overlap: expected a fraction in [0, 1), found {overlap!r}")
    return h, w, float(overlap), batch


# --------------------------------------------------------------------- API
def line_inputs(
    line: Any, channels: Sequence[str] | None, sonar_mask: SonarMaskConfig | Mapping | None
) -> tuple[np.ndarray, np.ndarray]:
    """A line's CNN inputs from its sidescan alone: ``(inputs (P, 2, C, B) float32, sonar mask
    (P, 2, B) uint8)`` (intensity normalised over the sonar-only valid bins, then the
    channels of :func:`sss2bathy.data.masks.input_channels`)."""
    intensity, mask = sonar_normalized_intensity(line, sonar_mask)
    channels = check_channels(channels)
    relative = None
    if "relative" in channels:
        relative = np.transpose(relative_channel(intensity, mask), (1, 0, 2))
    r_max = float(np.max(line.range_m))
    heads = np.transpose(intensity, (1, 0, 2))
    inputs = input_channels(
        heads,
        line.range_m,
        line.altitude_m,
        r_max,
        channels,
        relative=relative,
        opposite=heads[::-1] if "opposite" in channels else None,
    )
    return np.ascontiguousarray(np.transpose(inputs, (2, 0, 1, 3))), mask  # (2,C,P,B)->(P,2,C,B)


def predict_normals(
    ckpt_path: str | Path,
    survey: Survey,
    survey_dir: str | Path,
    line_names: Sequence[str],
    draped: Mapping[str, Any] | None = None,
    window_cfg: Mapping[str, Any] | None = None,
    device: str | torch.device | None = None,
    precision: str = "fp32",
    overlap: float | None = None,
    batch_size: int | None = None,
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Predicted n_lat waterfalls of whole lines, cached under ``survey_dir/predictions/``.

    Args:
        ckpt_path: a ``NormalCNNModule`` checkpoint, an exported model (``.safetensors``)
            or ``"pretrained"`` (the shipped model).
        survey: the survey holding the lines.
        survey_dir: the survey's folder (cache root).
        line_names: lines to predict.
        draped: ``{line name: DrapedLine}`` (uses ``.mask (P, 2, B) uint8``), or None. Only
            OR-ed into the returned mask (display, scoring); predictions never depend on it.
        window_cfg: ``window_pings``, ``window_bins`` (None: a line's bins), ``overlap``: the
            training windows (the windows DataModule config works as is); optional
            ``batch_size`` (64). None: read from the checkpoint
            (:func:`checkpoint_window_config`).
        device: torch device; default CUDA if available, else CPU.
        precision: ``"fp32"`` | ``"bf16"`` (:func:`predict_waterfall`); bf16 predictions
            are cached under their own key.
        overlap: inference overlap in [0, 1) instead of ``window_cfg``'s (the training
            overlap); None: the training overlap. Fewer windows, fewer forward passes (0.5
            instead of 0.75: half); cached under the overlap used.
        batch_size: windows per forward pass; ``None``: :data:`CPU_INFERENCE_BATCH` on a
            CPU, ``window_cfg``'s ``batch_size`` (the training batch) elsewhere. Does not
            change the predictions (nor the cache key).

    Returns:
        ``{line: (n_lat (P, 2, B) float32, NaN at invalid bins, mask (P, 2, B) uint8)}``; the
        mask is the sonar-only mask of the checkpoint's ``sonar_mask`` parameters (OR the
        draped mask when given).
    """
    if isinstance(line_names, str) or not all(isinstance(n, str) for n in line_names):
        raise ValueError(f"line_names: expected a list of line names, found {line_names!r}")
    known = {ln.name for ln in survey.lines}
    missing = [n for n in line_names if n not in known]
    if missing:
        raise ValueError(f"line_names: expected lines of survey '{survey.name}', unknown {missing}")
    if draped is not None:
        absent = [n for n in line_names if n not in draped]
        if absent:
            raise ValueError(f"draped: expected an entry for every line, missing {absent}")
    ckpt_path = resolve_model_path(ckpt_path, "ckpt_path")
    if not ckpt_path.is_file():
        raise ValueError(f"ckpt_path: expected an existing checkpoint file, found {ckpt_path}")
    if window_cfg is None:
        window_cfg = checkpoint_window_config(ckpt_path)
    h, w, train_overlap, train_batch = _window_params(window_cfg)
    check_precision(precision)
    overlap = check_overlap(overlap)
    if overlap is None:
        overlap = train_overlap
    if batch_size is not None and (
        not isinstance(batch_size, int) or isinstance(batch_size, bool) or batch_size < 1
    ):
        raise ValueError(f"batch_size: expected null or an integer >= 1, found {batch_size!r}")
    spec = checkpoint_input_spec(ckpt_path)
    warn_sonar_outside(ckpt_path, survey, line_names)
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    if batch_size is None:
        batch_size = CPU_INFERENCE_BATCH if torch.device(device).type == "cpu" else train_batch
    key_fields = {
        "version": CACHE_VERSION,
        "ckpt": file_sha256(ckpt_path),
        "window": [h, w, overlap],
        "channels": list(spec["channels"]),
        "sonar_mask": spec["sonar_mask"],
    }
    if precision != "fp32":  # float32 keys stay those of earlier caches
        key_fields["precision"] = precision
        # inference_net's network (earlier bf16 caches: "cast copy" with InstanceNorm2d,
        # before that autocast)
        key_fields["run"] = (
            "cast copy, channels-last channel norm"
            if torch.device(device).type == "cpu"
            else "cast copy"
        )
    key = stable_hash(key_fields)
    cache_dir = Path(survey_dir) / "predictions" / key
    net: nn.Module | None = None
    results: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name in log_progress(line_names, "CNN inference", unit="lines"):
        line = survey.line(name)
        sonar = sonar_only_mask(line, spec["sonar_mask"])
        path = cache_dir / f"{name}.npz"
        n_lat = _load_cached(path, key, sonar)
        if n_lat is None:
            if net is None:  # the precision's network once, for every line
                net = inference_net(load_normal_net(ckpt_path).to(device), device, precision)[0]
            n_in = getattr(net, "in_channels", len(spec["channels"]))
            if n_in != len(spec["channels"]):
                raise ValueError(
                    f"ckpt_path: network has in_channels={n_in}, expected "
                    f"{len(spec['channels'])} for input_channels {list(spec['channels'])}"
                )
            inputs, _ = line_inputs(line, spec["channels"], spec["sonar_mask"])
            window = (h, line.n_bins if w is None else w)
            n_lat = predict_waterfall(net, inputs, window, overlap, batch_size, device, precision)
            n_lat[sonar != MASK_VALID] = np.nan
            _save_cached(path, key, n_lat, sonar)
        mask = sonar.copy()
        if draped is not None:
            extra = _draped_mask(draped[name], name)
            if extra.shape != mask.shape:
                raise ValueError(
                    f"draped['{name}'].mask: expected shape {mask.shape}, found {extra.shape}"
                )
            mask |= extra
            n_lat = np.where(mask == MASK_VALID, n_lat, np.nan).astype(np.float32)
        results[name] = (n_lat, mask)
    return results
