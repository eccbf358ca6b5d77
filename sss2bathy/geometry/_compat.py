"""numpy-in/numpy-out adapter for the torch geometry functions."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np
import torch


def numpy_compatible(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Let a torch function take numpy arrays: inputs become tensors, outputs numpy again."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        was_numpy = any(isinstance(a, np.ndarray) for a in (*args, *kwargs.values()))
        if not was_numpy:
            return fn(*args, **kwargs)

        def to_t(a: Any) -> Any:
            return torch.as_tensor(a) if isinstance(a, np.ndarray) else a

        out = fn(*(to_t(a) for a in args), **{k: to_t(v) for k, v in kwargs.items()})
        if isinstance(out, tuple):
            return tuple(o.numpy() if isinstance(o, torch.Tensor) else o for o in out)
        return out.numpy() if isinstance(out, torch.Tensor) else out

    return wrapper


def as_tensor_like(value: Any, ref: torch.Tensor) -> torch.Tensor:
    """A tensor on ``ref``'s device and dtype (scalars and tensors alike)."""
    return torch.as_tensor(value, dtype=ref.dtype, device=ref.device)
