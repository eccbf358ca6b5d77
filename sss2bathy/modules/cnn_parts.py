"""Plain parts of the normal CNN's module (no Lightning): the network built from a factory
and its input channels, its start from a trained CNN's weights (``model.init``: fine-tuning),
the batch contract, plain-value descriptions for hparams."""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from sss2bathy.data.masks import SonarMaskConfig, check_channels

BATCH_KEYS = ("intensity", "n_lat", "mask")
COMPILED_PREFIX = "_orig_mod."


def describe_factory(factory: Callable[..., Any] | None) -> dict[str, Any] | None:
    """Plain-value description of an optimizer / scheduler factory (a ``functools.partial``
    from Hydra's ``_partial_: true``) for hparams: ``{"name": ..., **keywords}``."""
    if factory is None:
        return None
    if isinstance(factory, functools.partial):
        func = factory.func
        out: dict[str, Any] = {"name": f"{func.__module__}.{func.__qualname__}"}
        for key, value in factory.keywords.items():
            out[key] = list(value) if isinstance(value, tuple) else value
        return out
    return {"name": getattr(factory, "__qualname__", type(factory).__name__)}


def net_config(net: nn.Module) -> dict[str, Any] | None:
    """``net.config()`` if the network can describe itself (e.g. ``NormalResNet``), else None."""
    config = getattr(net, "config", None)
    return dict(config()) if callable(config) else None


def input_channel_names(input_channels: Sequence[str] | None) -> list[str]:
    """The network's input channels (``model.input_channels``; None = ``[intensity]``),
    checked against :data:`sss2bathy.data.masks.CHANNELS`."""
    if input_channels is not None and not isinstance(input_channels, str):
        input_channels = list(input_channels)
    return list(check_channels(input_channels, "model.input_channels"))


def build_net(net: nn.Module | Callable[..., nn.Module], channels: Sequence[str]) -> nn.Module:
    """The network: ``net`` itself, or ``net(in_channels=len(channels))`` for a factory
    (Hydra ``_partial_: true``); its ``in_channels`` must equal the number of channels.

    Raises:
        ValueError: naming ``model.net.in_channels`` or ``net``, expected and found.
    """
    if not isinstance(net, nn.Module) and callable(net):
        given = getattr(net, "keywords", {}).get("in_channels")
        if given is not None and given != len(channels):
            raise ValueError(
                f"model.net.in_channels: expected null or {len(channels)} (one per input "
                f"channel {list(channels)}), found {given}"
            )
        net = net(in_channels=len(channels))
    if not isinstance(net, nn.Module):
        raise ValueError(f"net: expected a torch.nn.Module, found {type(net).__name__}")
    n_in = getattr(net, "in_channels", None)
    if n_in is not None and n_in != len(channels):
        raise ValueError(
            f"model.net.in_channels: expected {len(channels)} (one per input channel "
            f"{list(channels)}), found {n_in}"
        )
    return net


def init_from_model(
    net: nn.Module, source: str, channels: Sequence[str], key: str = "model.init"
) -> dict[str, Any]:
    """Load a trained CNN's weights into ``net`` (fine-tuning): ``source`` is
    ``"pretrained"`` (the CNN shipped in the package), a ``.ckpt`` of a CNN run or an
    exported ``.safetensors``. Its input channels and its network (class and every argument)
    must be this run's; each mismatch is one line naming ``key``, the file, this run's
    values and the file's (``python -m sss2bathy.pretrained overrides`` prints the overrides
    that make a run match a model). Returns a plain record of what was loaded (``source``,
    ``path``, ``sha256``, ``sonar_mask``: the file's, which the run's data should share)."""
    from sss2bathy.data.cnn_normals import (
        check_cnn_model,
        checkpoint_input_spec,
        load_normal_net,
        model_net_config,
    )
    from sss2bathy.utils.atomic import file_sha256

    if not isinstance(source, str | Path) or not str(source):
        raise ValueError(
            f"{key}: expected null, pretrained or the path of a CNN (.ckpt / .safetensors), "
            f"found {source!r}"
        )
    path = check_cnn_model(source, key)
    spec = checkpoint_input_spec(path)
    if list(spec["channels"]) != list(channels):
        raise ValueError(
            f"{key}: {path} was trained on input channels {list(spec['channels'])}, expected "
            f"this run's {list(channels)} (data.input_channels)"
        )
    ours, theirs = net_config(net), model_net_config(path, key)
    if ours is None:
        raise ValueError(
            f"{key}: expected a network that describes itself (config()), found "
            f"{type(net).__name__}"
        )
    differ = [k for k in sorted(set(ours) | set(theirs)) if ours.get(k) != theirs.get(k)]
    if differ:
        found = ", ".join(f"{k}={ours.get(k)!r} (file: {theirs.get(k)!r})" for k in differ)
        raise ValueError(
            f"{key}: expected this run's network (model.net) to be the one of {path}, found "
            f"{found}; set model.net.<key> to the file's"
        )
    trained = load_normal_net(path)
    net.load_state_dict(trained.state_dict(), strict=True)
    return {
        "source": str(source),
        "path": str(path),
        "sha256": file_sha256(path, length=64),
        "sonar_mask": dict(spec["sonar_mask"]),
    }


def sonar_mask_mismatch(record: Mapping[str, Any] | None, data_mask: Any) -> str | None:
    """A warning when the data's ``sonar_mask`` (a datamodule's hparam) differs from the one
    the weights in ``record`` (:func:`init_from_model`) were trained with, else None."""
    if not record or data_mask is None:
        return None
    ours = SonarMaskConfig.coerce(data_mask).to_dict()
    theirs = SonarMaskConfig.coerce(record.get("sonar_mask")).to_dict()
    differ = [k for k in sorted(ours) if ours[k] != theirs.get(k)]
    if not differ:
        return None
    found = ", ".join(f"{k}={ours[k]!r} (weights: {theirs.get(k)!r})" for k in differ)
    return (
        f"model.init: the data's sonar_mask differs from the one {record.get('path')} was "
        f"trained with: {found}; the intensity is normalised differently from its training"
    )


def check_batch(batch: Mapping[str, torch.Tensor], n_inputs: int = 1) -> None:
    """Raise ``ValueError`` naming the key if ``batch`` lacks or mis-shapes a field
    (``n_inputs``: the network's input channels; ``inputs`` is required when > 1)."""
    if not isinstance(batch, Mapping):
        raise ValueError(f"batch: expected a dict with keys {BATCH_KEYS}, found {type(batch)}")
    for key in BATCH_KEYS:
        if key not in batch:
            raise ValueError(f"batch: missing key '{key}'; found keys {sorted(batch)}")
    shape = tuple(batch["intensity"].shape)
    if len(shape) != 4 or shape[1] != 1:
        raise ValueError(f"batch['intensity']: expected shape [B, 1, H, W], found {shape}")
    for key in ("n_lat", "mask"):
        if tuple(batch[key].shape) != shape:
            raise ValueError(
                f"batch['{key}']: expected intensity's shape {shape}, "
                f"found {tuple(batch[key].shape)}"
            )
    if "inputs" in batch:
        got = tuple(batch["inputs"].shape)
        n_in = n_inputs
        if len(got) != 4 or got[0] != shape[0] or got[2:] != shape[2:] or got[1] != n_in:
            raise ValueError(
                f"batch['inputs']: expected shape [{shape[0]}, {n_in}, {shape[2]}, "
                f"{shape[3]}] (one plane per input channel), found {got}"
            )
    elif n_inputs != 1:
        raise ValueError(
            f"batch: missing key 'inputs' for {n_inputs} input channels; found keys {sorted(batch)}"
        )
    if batch["mask"].dtype != torch.bool:
        raise ValueError(f"batch['mask']: expected dtype torch.bool, found {batch['mask'].dtype}")


__all__ = [
    "BATCH_KEYS",
    "COMPILED_PREFIX",
    "build_net",
    "check_batch",
    "describe_factory",
    "init_from_model",
    "input_channel_names",
    "net_config",
    "sonar_mask_mismatch",
]
