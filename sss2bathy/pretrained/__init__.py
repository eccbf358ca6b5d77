"""The pretrained inverse sensor model shipped with the package, and the command that makes
such a model from a training run.

This folder is package data: ``normal_cnn.safetensors`` (the normal CNN's weights, tensors
only) and ``normal_cnn.json`` (what inference needs to rebuild and feed it, the training
sonar it covers, its recipe, command and metrics; :mod:`sss2bathy.data.cnn_model_file`).
``cnn_checkpoint=pretrained`` (sss2bathy-map, sss2bathy-train, sss2bathy-predict) and
``model.init=pretrained`` (fine-tuning) name it; :mod:`sss2bathy.data.cnn_normals` finds it
by path (``PRETRAINED_DIR``). docs/pretrained_model.md is its model card
(``python -m studies.model_card``).

    python -m sss2bathy.pretrained export outputs/runs/<task>/<run>/checkpoints/last.ckpt
    python -m sss2bathy.pretrained export RUN/checkpoints/last.ckpt --out /tmp/m --name mine
    python -m sss2bathy.pretrained show pretrained

``export`` turns a Lightning checkpoint of ``sss2bathy-train experiment=cnn`` (or any
NormalCNNModule run) into the two files (default: into this package, as ``normal_cnn``;
existing files are kept unless ``--force``), reading the run folder around it for the
command (``.hydra/overrides.yaml``), the composed config, ``run_info.json`` and the run's
``metrics.json`` (``--metrics FILE`` adds more, e.g. an evaluation run on other surveys).
It then rebuilds the network from the written files and from the checkpoint and requires
bit-identical predictions on a test input. ``show`` validates a model and prints a summary.
A wrong file is one line on stderr and exit status 2 (``--trace``: the traceback).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import sss2bathy
from sss2bathy.callbacks.hparams import final_scalars
from sss2bathy.data.cnn_model_file import (
    is_model_file,
    metadata_from_checkpoint,
    model_files,
    net_state,
    read_model_meta,
    sha256,
    write_model,
)
from sss2bathy.data.cnn_normals import PRETRAINED_DIR, PRETRAINED_NAME, load_normal_net
from sss2bathy.utils.checkpoints import KIND_CNN, expect_kind, read_checkpoint

#: Top-level config keys left out of the recorded training config: where the run wrote
#: (machine-specific) and how it logged, not how the model was trained.
UNRECORDED_KEYS = ("hydra", "paths", "extras", "logger")
#: Overrides left out of the card's command (machine-specific folders).
LOCAL_OVERRIDES = ("paths.", "hydra.", "logger=")
#: Metric keys kept from a run's metrics.json: validation and test scores.
METRIC_PREFIXES = ("val/", "test/")


# ----------------------------------------------------------------------- the run folder
def run_folder(ckpt_path: Path) -> Path | None:
    """The Hydra run folder of ``<run>/checkpoints/<file>.ckpt``, else None."""
    run = ckpt_path.resolve().parent.parent
    if ckpt_path.resolve().parent.name == "checkpoints" and (run / ".hydra").is_dir():
        return run
    return None


def _read_json(path: Path, what: str) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: expected {what} (JSON), found unreadable ({err})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected {what} (a JSON object), found {type(data).__name__}")
    return data


def resolved_config(path: Path) -> dict[str, Any]:
    """A run's composed config (``.hydra/config.yaml``) as plain values, each interpolation
    resolved where it can be outside the run (``${hydra:...}`` stays as written), without
    :data:`UNRECORDED_KEYS`."""
    from omegaconf import DictConfig, ListConfig, OmegaConf

    cfg = OmegaConf.load(path)

    def walk(node: Any, key: str) -> Any:
        if isinstance(node, dict):
            return {k: walk(v, f"{key}.{k}" if key else str(k)) for k, v in node.items()}
        if isinstance(node, list):
            return [walk(v, f"{key}[{i}]") for i, v in enumerate(node)]
        if isinstance(node, str) and ("${hydra:" in node or "${paths." in node):
            # the run's own folders: machine-local (and ${hydra:...} resolvable only inside
            # a Hydra run, or wherever one left its global state), so always kept as written
            return node
        if isinstance(node, str) and "${" in node:
            try:
                value = OmegaConf.select(cfg, key, throw_on_resolution_failure=True)
                if isinstance(value, DictConfig | ListConfig):
                    value = OmegaConf.to_container(value, resolve=True)
                return value
            except Exception:  # noqa: BLE001 - a resolver only the run had: keep the text
                return node
        return node

    raw = OmegaConf.to_container(cfg, resolve=False)
    return {k: walk(v, k) for k, v in raw.items() if k not in UNRECORDED_KEYS}


def training_record(ckpt_path: Path, ckpt: Mapping[str, Any]) -> dict[str, Any]:
    """Where a checkpoint came from: the file and its SHA-256, epoch and step, the module's
    loss / optimizer / scheduler, and from its run folder (when there is one) the command,
    the overrides, ``run_info.json`` and the composed config."""
    hparams = ckpt.get("hyper_parameters") or {}
    record: dict[str, Any] = {
        "source_checkpoint": ckpt_path.name,
        "source_sha256": sha256(ckpt_path),
        "epoch": ckpt.get("epoch"),
        "global_step": ckpt.get("global_step"),
        "loss": hparams.get("loss"),
        "optimizer": hparams.get("optimizer"),
        "scheduler": hparams.get("scheduler"),
        "data": {
            k: v
            for k, v in (ckpt.get("datamodule_hyper_parameters") or {}).items()
            if isinstance(v, str | int | float | bool | list | dict | type(None))
        },
    }
    run = run_folder(ckpt_path)
    if run is None:
        record["command"] = None
        return record
    overrides_file = run / ".hydra" / "overrides.yaml"
    overrides: list[str] = []
    if overrides_file.is_file():
        import yaml

        loaded = yaml.safe_load(overrides_file.read_text()) or []
        overrides = [str(o) for o in loaded] if isinstance(loaded, list) else []
    record["overrides"] = overrides
    shared = [o for o in overrides if not o.lstrip("+~").startswith(LOCAL_OVERRIDES)]
    record["command"] = " ".join(["sss2bathy-train", *shared])
    if (run / "run_info.json").is_file():
        record["run_info"] = {
            k: v
            for k, v in _read_json(run / "run_info.json", "a run record").items()
            if k != "data_dir"
        }
    if (run / ".hydra" / "config.yaml").is_file():
        config = resolved_config(run / ".hydra" / "config.yaml")
        if record["data"]:  # the datamodule's own (resolved) arguments say it already:
            # its surveys (and the survey nodes they interpolate, ``*_surveys``, the scale's
            # survey sizes)
            config.pop("data", None)
            for key in [k for k in config if k.endswith("_surveys")]:
                config.pop(key)
            if isinstance(config.get("scale"), dict):
                config["scale"].pop("survey", None)
        record["config"] = config
    return record


def run_metrics(ckpt_path: Path, extra: Sequence[str | Path] = ()) -> dict[str, Any]:
    """``{"values": {key: number}, "sources": [file names]}``: the validation and test scores of
    the checkpoint's run (``<run>/metrics.json``) and of each file of ``extra`` (flat
    metrics JSON; later files win)."""
    files = []
    run = run_folder(ckpt_path)
    if run is not None and (run / "metrics.json").is_file():
        files.append(run / "metrics.json")
    for path in extra:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(
                f"--metrics: expected a metrics JSON file, found no file {path}"
            )
        files.append(path)
    values: dict[str, float] = {}
    for path in files:
        data = final_scalars(_read_json(path, "a flat metrics file"))
        values.update({k: v for k, v in data.items() if k.startswith(METRIC_PREFIXES)})
    # file names only: where they lay is machine-local
    return {"values": values, "sources": [p.name for p in files]}


def software_record() -> dict[str, str]:
    """Versions of what wrote the files."""
    import safetensors
    import torch

    return {
        "sss2bathy": str(sss2bathy.__version__),
        "torch": str(torch.__version__),
        "safetensors": str(safetensors.__version__),
        "python": platform.python_version(),
    }


# ----------------------------------------------------------------------- export
def export_checkpoint(
    ckpt_path: str | Path,
    out_dir: str | Path | None = None,
    name: str = PRETRAINED_NAME,
    metrics: Sequence[str | Path] = (),
    force: bool = False,
) -> tuple[Path, Path]:
    """Write ``<out_dir>/<name>.safetensors`` + ``.json`` from a CNN Lightning checkpoint
    (``out_dir`` None: this package) and check that the written model predicts exactly what
    the checkpoint does; returns ``(weights, metadata)``."""
    path = Path(ckpt_path).expanduser()
    if is_model_file(path):
        raise ValueError(
            f"ckpt: expected a Lightning checkpoint (.ckpt) of sss2bathy-train experiment=cnn, "
            f"found an exported model {path} (it needs no export)"
        )
    ckpt = read_checkpoint(path, "ckpt")
    expect_kind(ckpt, path, "ckpt", KIND_CNN)
    meta = metadata_from_checkpoint(ckpt, f"ckpt {path}")
    state = net_state(ckpt)
    out = Path(PRETRAINED_DIR if out_dir is None else out_dir).expanduser()
    existing = [p for p in model_files(out / name) if p.exists()]
    if existing and not force:
        raise ValueError(
            f"--name: expected a model name not yet in {out}, found {existing[0].name} "
            "(--force replaces it)"
        )
    meta.update(
        training=training_record(path, ckpt),
        metrics=run_metrics(path, metrics),
        software=software_record(),
    )
    weights, json_path = write_model(state, meta, out, name)
    check_same_predictions(path, weights)
    return weights, json_path


def check_same_predictions(ckpt_path: Path, model_path: Path, seed: int = 0) -> None:
    """Both files rebuild networks that give bit-identical predictions on a seeded input
    (``ValueError`` otherwise)."""
    import torch

    from sss2bathy.data.cnn_normals import checkpoint_input_spec, checkpoint_window_config

    a, b = load_normal_net(ckpt_path), load_normal_net(model_path)
    channels = len(checkpoint_input_spec(model_path)["channels"])
    window = checkpoint_window_config(model_path)
    h, w = int(window["window_pings"]), int(window["window_bins"] or 64)
    x = torch.randn(2, channels, h, w, generator=torch.Generator().manual_seed(seed))
    with torch.inference_mode():
        same = torch.equal(a(x), b(x))
    if not same:
        raise ValueError(
            f"{model_path}: expected the predictions of {ckpt_path} bit for bit, found others "
            "(the export is wrong; it was written but must not be used)"
        )


def describe_model(path: str | Path) -> list[str]:
    """A validated model's summary lines (its weights' SHA-256 checked)."""
    from sss2bathy.data.cnn_model_file import read_model_weights
    from sss2bathy.data.cnn_normals import resolve_model_path
    from sss2bathy.data.sonar_envelope import describe

    resolved = resolve_model_path(path, "model")
    meta, tensors = read_model_weights(resolved)
    _, json_path = read_model_meta(resolved)
    net = meta["network"]
    args = ", ".join(f"{k}={v}" for k, v in net.items() if k != "_target_")
    envelope = meta.get("sonar_envelope")
    sonar = describe(envelope["settings"]) if envelope else "not recorded"
    training = meta.get("training") or {}
    return [
        f"{meta['name']}: {json_path.with_suffix('.safetensors')}",
        f"  network: {net['_target_'].rsplit('.', 1)[-1]}({args}), "
        f"{meta['weights']['n_parameters']} parameters in {len(tensors)} tensors",
        f"  inputs: {', '.join(meta['input_channels'])}; windows of "
        f"{meta['windows']['window_pings']} pings x "
        f"{meta['windows']['window_bins'] or 'all'} bins",
        f"  trained on: {sonar}",
        f"  command: {training.get('command') or 'unknown (no run folder)'}",
        f"  sha256: {meta['weights']['sha256']} (checked)",
    ]


def model_overrides(path: str | Path = "pretrained") -> list[str]:
    """The ``sss2bathy-train`` overrides that make a CNN run's network, input channels and
    sonar-only mask those of a model (for ``model.init``: fine-tuning it), e.g.
    ``++model.net.base_width=16``; the network's class included, its ``in_channels`` left
    to the input channels."""
    from sss2bathy.data.cnn_normals import checkpoint_input_spec, model_net_config

    net = model_net_config(path, "model")
    spec = checkpoint_input_spec(path)
    out = [f"++model.net.{k}={_override_value(v)}" for k, v in net.items() if k != "in_channels"]
    out.append(f"data.input_channels={_override_value(list(spec['channels']))}")
    out += [f"data.sonar_mask.{k}={_override_value(v)}" for k, v in spec["sonar_mask"].items()]
    return out


def _override_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "null"
    if isinstance(value, list | tuple):
        return "[" + ",".join(_override_value(v) for v in value) + "]"
    return str(value)


# ----------------------------------------------------------------------- command line
def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m sss2bathy.pretrained",
        description="Export a trained normal CNN to safetensors + JSON, or check one.",
    )
    parser.add_argument("--trace", action="store_true", help="show tracebacks of errors")
    sub = parser.add_subparsers(dest="command", required=True)
    exp = sub.add_parser("export", help="a CNN Lightning checkpoint -> <name>.safetensors + .json")
    exp.add_argument("ckpt", help="a checkpoint of sss2bathy-train experiment=cnn (.ckpt)")
    exp.add_argument("--name", default=PRETRAINED_NAME, help=f"file stem ({PRETRAINED_NAME})")
    exp.add_argument("--out", default=None, help=f"folder (default: the package, {PRETRAINED_DIR})")
    exp.add_argument(
        "--metrics", action="append", default=[], help="more metrics JSON files (repeatable)"
    )
    exp.add_argument("--force", action="store_true", help="replace an existing model")
    exp.add_argument("--trace", action="store_true", help="show tracebacks of errors")
    show = sub.add_parser("show", help="validate a model and print its summary")
    show.add_argument("model", nargs="?", default="pretrained", help="a .safetensors or pretrained")
    show.add_argument("--trace", action="store_true", help="show tracebacks of errors")
    over = sub.add_parser(
        "overrides", help="sss2bathy-train overrides that match a model (model.init)"
    )
    over.add_argument("model", nargs="?", default="pretrained", help="a .safetensors or pretrained")
    over.add_argument("--trace", action="store_true", help="show tracebacks of errors")
    args = parser.parse_args(argv)
    try:
        if args.command == "export":
            weights, json_path = export_checkpoint(
                args.ckpt, args.out, args.name, args.metrics, args.force
            )
            print(f"exported {args.ckpt} -> {weights} + {json_path.name} (predictions identical)")
            print("\n".join(describe_model(weights)[1:]))
        elif args.command == "overrides":
            print(" ".join(model_overrides(args.model)))
        else:
            print("\n".join(describe_model(args.model)))
    except (ValueError, FileNotFoundError) as err:
        if args.trace:
            raise
        print(f"error: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    return 0


__all__ = [
    "check_same_predictions",
    "describe_model",
    "export_checkpoint",
    "main",
    "model_overrides",
    "resolved_config",
    "run_metrics",
    "training_record",
]
