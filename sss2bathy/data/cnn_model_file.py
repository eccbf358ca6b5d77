"""A trained normal CNN as two plain files: its weights and what inference needs to use them.

``<name>.safetensors`` holds the network's tensors only (no pickle: nothing in it can run
code); ``<name>.json`` beside it (:data:`FORMAT`) holds everything else:

* ``network``: the network's class path (a class of ``sss2bathy.models``) and its
  constructor arguments, from which :func:`sss2bathy.data.cnn_normals.load_normal_net`
  rebuilds it;
* ``input_channels``, ``sonar_mask``, ``windows``: how the windows the network was trained
  on were built (the intensity normalised over the sonar-only mask of those ``sonar_mask``
  parameters, those channels, windows of ``window_pings x window_bins`` with ``overlap``),
  so inference builds the same inputs;
* ``sonar_envelope``: the training lines' sonar (:mod:`sss2bathy.data.sonar_envelope`), or
  null, so a survey recorded with another sonar is warned about;
* ``weights``: the weights file's name, SHA-256 (of its bytes), tensor and parameter counts;
* ``training``, ``metrics``, ``software``: where it came from (the source checkpoint and its
  SHA-256, epoch and step, the run's command and composed config), its scores, and the
  versions that wrote it. Plain values, free-form: for the model card.

:func:`metadata_from_checkpoint` takes the inference fields out of a Lightning checkpoint of
:class:`~sss2bathy.modules.normal_cnn.NormalCNNModule`; :func:`write_model` writes both
files; :func:`read_model_meta` validates a JSON file (a problem is one line naming the file,
the field, the expected and the found value) and :func:`read_model_weights` checks the
weights' SHA-256 before loading them. :func:`as_checkpoint` gives the pair the shape of a
Lightning checkpoint (``hyper_parameters``, ``datamodule_hyper_parameters``, ``state_dict``,
``sonar_envelope``), so everything that reads a CNN checkpoint reads these files too.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from sss2bathy.data.masks import SonarMaskConfig, check_channels
from sss2bathy.data.sonar_envelope import CHECKPOINT_KEY as SONAR_ENVELOPE_KEY
from sss2bathy.data.sonar_envelope import check_envelope
from sss2bathy.utils.atomic import atomic_path, atomic_write_text, file_sha256

#: The ``format`` field of the JSON file, and its version.
FORMAT = "sss2bathy-normal-cnn"
FORMAT_VERSION = 1
WEIGHTS_SUFFIX = ".safetensors"
META_SUFFIX = ".json"
#: Suffixes that name such a model (either file of the pair).
MODEL_SUFFIXES = (WEIGHTS_SUFFIX, META_SUFFIX)
NET_PACKAGE = "sss2bathy.models."
COMPILED_PREFIX = "_orig_mod."
#: The ``windows`` fields and the fields of the whole file every reader needs.
WINDOW_FIELDS = ("window_pings", "window_bins", "overlap", "batch_size")
REQUIRED = (
    "format",
    "format_version",
    "name",
    "weights",
    "network",
    "input_channels",
    "sonar_mask",
    "windows",
    "sonar_envelope",
)


def is_model_file(path: str | Path) -> bool:
    """Whether ``path`` names an exported model (its ``.safetensors`` or its ``.json``)."""
    return Path(str(path)).suffix.lower() in MODEL_SUFFIXES


def model_files(path: str | Path) -> tuple[Path, Path]:
    """``(weights, metadata)`` of the model ``path`` names (either file of the pair)."""
    path = Path(str(path))
    stem = path.with_suffix("")
    return stem.with_suffix(WEIGHTS_SUFFIX), stem.with_suffix(META_SUFFIX)


def sha256(path: str | Path) -> str:
    """The SHA-256 hex digest of a file's bytes (all 64 digits)."""
    return file_sha256(path, length=64)


# ----------------------------------------------------------------------- from a checkpoint
def net_state(ckpt: Mapping[str, Any]) -> dict[str, torch.Tensor]:
    """The network's tensors of a CNN checkpoint (``state_dict`` keys ``net.*``, a compiled
    network's ``_orig_mod.`` dropped), contiguous, on the CPU."""
    state = ckpt.get("state_dict")
    if not isinstance(state, Mapping):
        raise ValueError(f"checkpoint: expected a state_dict, found {type(state).__name__}")
    out = {
        k[len("net.") :].replace(COMPILED_PREFIX, ""): v.detach().cpu().contiguous()
        for k, v in state.items()
        if k.startswith("net.") and isinstance(v, torch.Tensor)
    }
    if not out:
        raise ValueError("checkpoint: expected the network's weights (net.*), found none")
    return out


def metadata_from_checkpoint(ckpt: Mapping[str, Any], where: str) -> dict[str, Any]:
    """The inference fields of the JSON (``network``, ``input_channels``, ``sonar_mask``,
    ``windows``, ``sonar_envelope``) from a loaded NormalCNNModule checkpoint; ``where``
    names the checkpoint in errors."""
    model = ckpt.get("hyper_parameters") or {}
    data = ckpt.get("datamodule_hyper_parameters") or {}
    network = model.get("net_config")
    if not isinstance(network, Mapping) or "_target_" not in network:
        raise ValueError(
            f"{where}: hyper_parameters.net_config: expected the network's class and "
            f"arguments (a NormalCNNModule checkpoint), found {network!r}"
        )
    missing = [k for k in WINDOW_FIELDS[:3] if k not in data]
    if missing:
        raise ValueError(
            f"{where}: datamodule_hyper_parameters: expected the training windows "
            f"{list(WINDOW_FIELDS[:3])}, missing {missing}"
        )
    channels = model.get("input_channels", data.get("input_channels"))
    channels = check_channels(
        None if channels is None else list(channels), f"{where}: input_channels"
    )
    try:
        mask = SonarMaskConfig.coerce(data.get("sonar_mask")).to_dict()
    except ValueError as err:
        raise ValueError(f"{where}: {err}") from None
    envelope = ckpt.get(SONAR_ENVELOPE_KEY)
    check_envelope(envelope, f"{where}: {SONAR_ENVELOPE_KEY}")
    return {
        "network": _plain(dict(network)),
        "input_channels": list(channels),
        "sonar_mask": _plain(mask),
        "windows": {
            "window_pings": data["window_pings"],
            "window_bins": data["window_bins"],
            "overlap": data["overlap"],
            "batch_size": data.get("batch_size", 64),
            # the training windows' overlap across track (null: overlap), for the record
            "overlap_bins": data.get("overlap_bins"),
        },
        "sonar_envelope": _plain(envelope),
    }


def _plain(value: Any) -> Any:
    """``value`` with tuples as lists and mappings as dicts (JSON's shapes)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def write_model(
    state: Mapping[str, torch.Tensor], meta: Mapping[str, Any], out_dir: str | Path, name: str
) -> tuple[Path, Path]:
    """Write ``out_dir/<name>.safetensors`` (``state``) and ``out_dir/<name>.json`` (``meta``
    completed with ``format``, ``name`` and the ``weights`` record), each atomically; the
    JSON is checked with :func:`read_model_meta` before it is written."""
    from safetensors.torch import save_file

    if not name or Path(name).name != name or name.startswith(".") or is_model_file(name):
        raise ValueError(f"name: expected a plain file stem such as normal_cnn, found {name!r}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    weights, json_path = model_files(out_dir / name)
    tensors = {k: v.detach().cpu().contiguous() for k, v in state.items()}
    with atomic_path(weights) as tmp:
        # one metadata key: safetensors writes a map's keys in no fixed order, and the same
        # weights must give the same bytes (and SHA-256) at every export
        save_file(tensors, str(tmp), metadata={"format": FORMAT})
    record = {
        "file": weights.name,
        "sha256": sha256(weights),
        "bytes": weights.stat().st_size,
        "n_tensors": len(tensors),
        "n_parameters": int(sum(t.numel() for t in tensors.values())),
        "dtypes": sorted({str(t.dtype).removeprefix("torch.") for t in tensors.values()}),
    }
    full = {"format": FORMAT, "format_version": FORMAT_VERSION, "name": name, **meta}
    full["weights"] = record
    text = json.dumps(_plain(full), indent=2, sort_keys=False, allow_nan=False) + "\n"
    check_meta(json.loads(text), json_path)
    atomic_write_text(json_path, text)
    return weights, json_path


# ----------------------------------------------------------------------- reading
def _field_error(path: Path, field: str, expected: str, found: Any) -> ValueError:
    shown = repr(found)
    if len(shown) > 120:
        shown = shown[:117] + "..."
    return ValueError(f"{path}: {field}: expected {expected}, found {shown}")


def _positive_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 1


def check_meta(meta: Any, path: Path) -> dict[str, Any]:
    """``meta`` (a parsed JSON file at ``path``) if it is a model file this version reads;
    else a one-line ``ValueError``: ``<file>: <field>: expected ..., found ...``."""
    if not isinstance(meta, dict):
        raise _field_error(path, "(top level)", "a JSON object", type(meta).__name__)
    missing = [k for k in REQUIRED if k not in meta]
    if missing:
        raise _field_error(path, missing[0], f"a field (the fields {list(REQUIRED)})", "none")
    if meta["format"] != FORMAT:
        raise _field_error(path, "format", repr(FORMAT), meta["format"])
    if meta["format_version"] != FORMAT_VERSION:
        raise _field_error(
            path, "format_version", f"{FORMAT_VERSION} (what this sss2bathy reads)",
            meta["format_version"],
        )  # fmt: skip
    weights = meta["weights"]
    if not isinstance(weights, dict):
        raise _field_error(path, "weights", "an object with file and sha256", weights)
    file = weights.get("file")
    if not isinstance(file, str) or Path(file).name != file or not file.endswith(WEIGHTS_SUFFIX):
        raise _field_error(path, "weights.file", f"a *{WEIGHTS_SUFFIX} file name", file)
    digest = weights.get("sha256")
    if not (isinstance(digest, str) and len(digest) == 64 and _is_hex(digest)):
        raise _field_error(path, "weights.sha256", "64 hex digits", digest)
    network = meta["network"]
    target = network.get("_target_") if isinstance(network, dict) else None
    if not (isinstance(target, str) and target.startswith(NET_PACKAGE)):
        raise _field_error(path, "network._target_", f"a class path in {NET_PACKAGE}*", target)
    try:
        check_channels(meta["input_channels"], "input_channels")
    except ValueError:
        raise _field_error(
            path, "input_channels", "a list of channel names starting with intensity",
            meta["input_channels"],
        ) from None  # fmt: skip
    try:
        SonarMaskConfig.coerce(meta["sonar_mask"])
    except (ValueError, TypeError) as err:
        raise _field_error(path, "sonar_mask", f"sonar-mask parameters ({err})", "others") from None
    windows = meta["windows"]
    if not isinstance(windows, dict):
        raise _field_error(path, "windows", f"an object with {list(WINDOW_FIELDS)}", windows)
    for key in ("window_pings", "batch_size"):
        if not _positive_int(windows.get(key)):
            raise _field_error(path, f"windows.{key}", "an integer >= 1", windows.get(key))
    if windows.get("window_bins") is not None and not _positive_int(windows.get("window_bins")):
        raise _field_error(
            path, "windows.window_bins", "null or an integer >= 1", windows.get("window_bins")
        )
    overlap = windows.get("overlap")
    if not (
        isinstance(overlap, int | float) and not isinstance(overlap, bool) and 0 <= overlap < 1
    ):
        raise _field_error(path, "windows.overlap", "a fraction in [0, 1)", overlap)
    try:
        check_envelope(meta["sonar_envelope"], "sonar_envelope")
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None
    return meta


def _is_hex(text: str) -> bool:
    return all(c in "0123456789abcdef" for c in text)


def read_model_meta(path: str | Path) -> tuple[dict[str, Any], Path]:
    """The validated metadata of the model ``path`` names (either file of the pair) and the
    weights file it belongs to (:func:`check_meta`; a missing or unreadable file is one line
    too)."""
    _, json_path = model_files(path)
    if not json_path.is_file():
        raise FileNotFoundError(
            f"{json_path}: expected the model's metadata beside its weights "
            f"(python -m sss2bathy.pretrained export writes both), found no file"
        )
    try:
        meta = json.loads(json_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise _field_error(json_path, "(file)", "JSON text", f"unreadable ({err})") from None
    meta = check_meta(meta, json_path)
    return meta, json_path.with_name(meta["weights"]["file"])


def read_model_weights(path: str | Path) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """``(metadata, tensors)`` of the model ``path`` names; the weights file must exist and
    match the SHA-256 its metadata records (one line otherwise)."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    meta, weights = read_model_meta(path)
    if not weights.is_file():
        raise FileNotFoundError(
            f"{weights}: expected the weights its metadata names (weights.file), found no file"
        )
    digest = sha256(weights)
    if digest != meta["weights"]["sha256"]:
        raise ValueError(
            f"{weights}: weights.sha256: expected {meta['weights']['sha256']} (recorded in "
            f"{model_files(path)[1].name}), found {digest} (a changed or damaged file)"
        )
    try:
        tensors = load_file(str(weights), device="cpu")
    except (SafetensorError, OSError, ValueError) as err:
        raise ValueError(
            f"{weights}: expected a safetensors file, found unreadable ({err})"
        ) from None
    return meta, tensors


def as_checkpoint(path: str | Path, weights: bool = True) -> dict[str, Any]:
    """The model ``path`` names in the shape of a NormalCNNModule checkpoint
    (``hyper_parameters.net_config`` / ``input_channels``, ``datamodule_hyper_parameters``,
    ``sonar_envelope``, ``state_dict`` with ``net.`` keys when ``weights``) plus its
    ``model_file`` metadata."""
    if weights:
        meta, tensors = read_model_weights(path)
        state = {f"net.{k}": v for k, v in tensors.items()}
    else:
        meta, _ = read_model_meta(path)
        state = {}
    return {
        "hyper_parameters": {
            "net_config": dict(meta["network"]),
            "input_channels": list(meta["input_channels"]),
        },
        "datamodule_hyper_parameters": {
            **meta["windows"],
            "sonar_mask": meta["sonar_mask"],
            "input_channels": list(meta["input_channels"]),
        },
        SONAR_ENVELOPE_KEY: meta["sonar_envelope"],
        "state_dict": state,
        "model_file": meta,
    }


__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "META_SUFFIX",
    "MODEL_SUFFIXES",
    "WEIGHTS_SUFFIX",
    "as_checkpoint",
    "check_meta",
    "is_model_file",
    "metadata_from_checkpoint",
    "model_files",
    "net_state",
    "read_model_meta",
    "read_model_weights",
    "sha256",
    "write_model",
]
