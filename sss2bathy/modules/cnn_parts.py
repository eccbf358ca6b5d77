"""Plain parts of the normal CNN's module (no Lightning): the network built from a factory
and its input channels, the batch contract, plain-value descriptions for hparams."""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
from torch import nn

from sss2bathy.data.masks import check_channels

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
    "input_channel_names",
    "net_config",
]
