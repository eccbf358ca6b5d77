"""Checkpoints: the one place that knows where Lightning runs keep them, and how to read
one safely and tell what it is.

A Hydra run folder ``<run>/`` holds ``checkpoints/last.ckpt`` (the periodic save of
:class:`sss2bathy.callbacks.LastCheckpoint`), possibly top-k saves beside it (the CNN's
``epoch_NNNN.ckpt``), possibly ``hpc_ckpt_<n>.ckpt`` (what Lightning's SLURM auto-requeue
writes into the trainer's ``default_root_dir``) and ``.hydra/config.yaml`` (the composed
config, whose ``scale.name`` says at which scale the run was trained).

Used by the SIREN's ``data.normals.checkpoint=latest`` and ``sss2bathy-predict ckpt_path=latest``
(:func:`sss2bathy.data.cnn_normals.latest_checkpoint`: the newest CNN run) and by
``sss2bathy-train ckpt_path=last`` (:func:`sss2bathy.cli.instantiate.latest_resume_checkpoint`:
the newest save of one run).

:func:`read_checkpoint` loads with ``weights_only=True`` and turns every failure into one
line naming the file and what it is (empty, truncated, a pickle with code, not a
checkpoint); :func:`checkpoint_kind` tells a CNN, a SIREN and a Lambert checkpoint apart
and :func:`expect_kind` says where a checkpoint of the wrong kind belongs.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

RUN_CHECKPOINT = "checkpoints/last.ckpt"
RUNS_PATTERNS = ("**/" + RUN_CHECKPOINT,)  # every run below a folder of runs
RESUME_PATTERNS = (RUN_CHECKPOINT, "hpc_ckpt_*.ckpt")  # the saves of one run folder
FALLBACK_PATTERNS = ("checkpoints/*.ckpt",)  # a run folder's other saves (top-k files)


def find_checkpoints(folder: str | Path, patterns: Sequence[str] = RUNS_PATTERNS) -> list[Path]:
    """Checkpoint files under ``folder`` matching any of the glob ``patterns``, oldest first
    (by modification time, ties by path); ``[]`` when there are none or no ``folder``."""
    if isinstance(patterns, str):
        raise ValueError(f"patterns: expected a sequence of glob patterns, found {patterns!r}")
    folder = Path(folder)
    found = {p for pattern in patterns for p in folder.glob(pattern) if p.is_file()}
    return sorted(found, key=lambda p: (p.stat().st_mtime, str(p)))


def run_scale(ckpt: str | Path) -> str | None:
    """``scale.name`` of the Hydra run a ``<run>/checkpoints/last.ckpt`` belongs to (from
    ``<run>/.hydra/config.yaml``), or None when the run has no readable config."""
    config = Path(ckpt).parent.parent / ".hydra" / "config.yaml"
    if not config.is_file():
        return None
    try:
        data = yaml.safe_load(config.read_text()) or {}
    except (OSError, yaml.YAMLError):
        return None
    scale = data.get("scale") if isinstance(data, dict) else None
    name = scale.get("name") if isinstance(scale, dict) else None
    return str(name) if name is not None else None


# ----------------------------------------------------------------------------- reading
#: What :func:`checkpoint_kind` calls the checkpoints of this project's modules.
KIND_CNN = "CNN"
KIND_SIREN = "SIREN"
KIND_LAMBERT = "Lambert"
KIND_TITLES = {
    KIND_CNN: "a CNN checkpoint (NormalCNNModule, sss2bathy-train experiment=cnn)",
    KIND_SIREN: "a SIREN checkpoint (SirenModule)",
    KIND_LAMBERT: "a Lambert checkpoint (SirenModule with the Lambertian sensor model)",
}
#: Where each kind of checkpoint is used: the keys that take it.
KIND_USES = {
    KIND_CNN: "a CNN checkpoint goes to data.normals.checkpoint (sss2bathy-map: cnn_checkpoint; "
    "sss2bathy-predict: ckpt_path)",
    KIND_SIREN: "a SIREN checkpoint goes to ckpt_path of its own experiment (resume) or of "
    "sss2bathy-eval",
    KIND_LAMBERT: "a Lambert checkpoint goes to ckpt_path of its own SIREN-Lambert experiment "
    "(resume) or of sss2bathy-eval",
}
ZIP_MAGIC = b"PK\x03\x04"  # torch.save's format since PyTorch 1.6: a zip archive


def checkpoint_kind(ckpt: Any) -> str | None:
    """:data:`KIND_CNN`, :data:`KIND_LAMBERT` or :data:`KIND_SIREN` from a loaded
    checkpoint's contents (hyper-parameters and state-dict names); None for any other
    Lightning checkpoint or object."""
    if not isinstance(ckpt, Mapping) or not isinstance(ckpt.get("state_dict"), Mapping):
        return None
    names = [str(k) for k in ckpt["state_dict"]]
    hparams = ckpt.get("hyper_parameters")
    if (isinstance(hparams, Mapping) and "net_config" in hparams) or any(
        n.startswith("net.") for n in names
    ):
        return KIND_CNN
    if any(n.startswith("siren.") for n in names):
        lambert = any(n.startswith(("sensor.beam_", "sensor.gain_")) for n in names)
        return KIND_LAMBERT if lambert else KIND_SIREN
    return None


def _pickle_imports(path: Path) -> bool | None:
    """Whether the pickle in ``path`` imports or calls anything (its opcodes, read without
    running them); None when it is no whole pickle."""
    import pickletools

    calls = {"GLOBAL", "STACK_GLOBAL", "REDUCE", "INST", "OBJ", "NEWOBJ", "NEWOBJ_EX", "EXT1"}
    try:
        with open(path, "rb") as f:
            return any(op.name in calls for op, _, _ in pickletools.genops(f))
    except Exception:  # noqa: BLE001 - a damaged pickle, whatever the opcode reader says
        return None


def _unreadable(path: Path, err: BaseException) -> str:
    """Why ``torch.load(path, weights_only=True)`` failed, in words, from the file itself
    (never torch's own message: it suggests turning the safe loading off)."""
    import pickle
    import zipfile

    size = path.stat().st_size
    if size == 0:
        return "is an empty file (0 bytes): not a checkpoint"
    with open(path, "rb") as f:
        head = f.read(4)
    if head == ZIP_MAGIC:
        try:
            with zipfile.ZipFile(path) as archive:
                archive.infolist()
        except (zipfile.BadZipFile, OSError):
            return (
                f"is truncated: a zip archive of {size} bytes without its end (an interrupted "
                "copy or write, or a full disk)"
            )
        if isinstance(err, pickle.UnpicklingError):
            return (
                "holds pickled Python objects besides tensors and plain values: refused "
                "unread (loading it could run code)"
            )
        return f"is a damaged checkpoint archive ({size} bytes; {type(err).__name__})"
    if head[:1] == b"\x80":
        imports = _pickle_imports(path)
        if imports is None:
            return f"is a damaged Python pickle ({size} bytes), not a PyTorch checkpoint"
        if imports:
            return (
                "is a Python pickle that holds Python objects besides tensors and plain "
                "values: refused unread (loading it could run code)"
            )
        return "is a Python pickle, not a PyTorch checkpoint"
    return f"is not a checkpoint (neither a PyTorch archive nor a pickle; starts {head.hex()})"


def read_checkpoint(path: str | Path, key: str) -> dict[str, Any]:
    """A checkpoint loaded safely (``torch.load(weights_only=True)``, on the CPU).

    A missing file, an empty, truncated or foreign file, a checkpoint holding pickled
    objects, or a file that is no Lightning checkpoint raises a one-line error starting
    with ``key`` and naming the file (``ValueError``; ``FileNotFoundError`` when missing).
    """
    import warnings

    import torch

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{key}: expected a checkpoint file, found no file {path}")
    try:
        with warnings.catch_warnings():  # torch's own words on a foreign pickle: ours follow
            warnings.simplefilter("ignore")
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - every failure is the file's: one line
        raise ValueError(f"{key}: {path} {_unreadable(path, err)}") from None
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("state_dict"), Mapping):
        found = sorted(map(str, ckpt))[:8] if isinstance(ckpt, dict) else type(ckpt).__name__
        raise ValueError(
            f"{key}: {path} is not a Lightning checkpoint (a PyTorch file without a "
            f"state_dict; found {found})"
        )
    return ckpt


def expect_kind(ckpt: Mapping[str, Any], path: str | Path, key: str, expected: str) -> str:
    """The :func:`checkpoint_kind` of ``ckpt``; a one-line ``ValueError`` naming ``key``,
    the file, its kind and where that kind belongs when it is not ``expected``."""
    kind = checkpoint_kind(ckpt)
    if kind == expected:
        return kind
    want = KIND_TITLES[expected].split(" (")[0]
    if kind is None:
        names = sorted({str(k).split(".")[0] for k in ckpt.get("state_dict", {})})[:6]
        raise ValueError(
            f"{key}: {path} is a Lightning checkpoint of another model (weights {names}); "
            f"expected {want}"
        )
    raise ValueError(f"{key}: {path} is {KIND_TITLES[kind]}; expected {want}: {KIND_USES[kind]}")


def resume_position(ckpt: Mapping[str, Any]) -> tuple[int, int]:
    """``(epoch, global step)`` a fit resumed from ``ckpt`` starts at: the epoch in
    progress for a mid-epoch save, the next one for an epoch-end save (Lightning's fit-loop
    progress: epochs whose training part ended), from ``ckpt["epoch"]`` without it."""
    step = int(ckpt.get("global_step", 0) or 0)
    try:
        progress = ckpt["loops"]["fit_loop"]["epoch_progress"]["current"]
        return int(progress["processed"]), step
    except (KeyError, TypeError, ValueError):
        return int(ckpt.get("epoch", 0) or 0), step
