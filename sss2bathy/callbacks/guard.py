"""Callbacks that keep a long run sound: skip non-finite steps, and carry the global RNG
state through checkpoints so a resumed run continues the same random streams.

Both are in ``conf/callbacks/default.yaml`` and work with any LightningModule that uses
automatic optimisation (the normal CNN, the SIREN fits).
"""

from __future__ import annotations

import logging
import random
from collections.abc import Mapping
from typing import Any

import numpy as np
import pytorch_lightning as pl
import torch
from pytorch_lightning.callbacks import Callback

log = logging.getLogger(__name__)


class NonFiniteTrainingError(RuntimeError):
    """Too many consecutive training steps had a non-finite loss or gradient."""


class NonFiniteGuard(Callback):
    """Skips every optimizer step whose loss or gradient is not finite; aborts after
    ``max_consecutive`` such steps in a row.

    After the backward pass (``on_before_optimizer_step``, i.e. after AMP unscaling and
    before gradient clipping) the guard checks the loss of the step and every gradient.
    If one is NaN or infinite it sets all gradients of the optimizer's parameters to
    ``None``: ``torch.optim`` optimizers (Adam, AdamW, SGD, ...) leave parameters without a
    gradient untouched, moments and step counts included, so the weights are exactly those
    of the previous step (zeroed gradients would not do: Adam's momentum would still move
    them). The skip is counted and logged as ``train/skipped_nonfinite`` (total skips so
    far), with a warning naming the first bad parameter. ``max_consecutive`` skips in a
    row raise :class:`NonFiniteTrainingError`: the run has diverged or its data is broken,
    and going on would only burn compute. The counters are saved in checkpoints.

    Args:
        max_consecutive: consecutive non-finite steps that abort the run (>= 1).
        log_key: metric name of the skip count.
    """

    def __init__(self, max_consecutive: int = 10, log_key: str = "train/skipped_nonfinite") -> None:
        if not (isinstance(max_consecutive, int) and max_consecutive >= 1):
            raise ValueError(
                f"max_consecutive: expected an integer >= 1, found {max_consecutive!r}"
            )
        self.max_consecutive = max_consecutive
        self.log_key = log_key
        self.skipped = 0
        self.consecutive = 0
        self._losses: list[torch.Tensor] = []

    @property
    def state_key(self) -> str:
        return "NonFiniteGuard"

    def on_before_backward(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, loss: torch.Tensor
    ) -> None:
        # several backward passes per step with gradient accumulation: any bad one counts
        self._losses.append(loss.detach())

    def on_before_optimizer_step(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, optimizer: torch.optim.Optimizer
    ) -> None:
        params = [p for group in optimizer.param_groups for p in group["params"]]
        losses, self._losses = self._losses, []
        with_grad = [p for p in params if p.grad is not None]
        tensors = losses + [p.grad for p in with_grad]
        if not tensors:
            return
        # one device sync per step: a flag per tensor, reduced on the device
        flags = torch.stack([torch.isfinite(t).all().to(tensors[0].device) for t in tensors])
        if bool(flags.all()):
            self.consecutive = 0
            return
        for p in params:
            p.grad = None
        self.skipped += 1
        self.consecutive += 1
        first_bad = int((~flags).nonzero()[0, 0])
        if first_bad < len(losses):
            what = f"loss {float(losses[first_bad].float().sum())}"
        else:
            names = {id(p): n for n, p in pl_module.named_parameters()}
            what = f"gradient of '{names.get(id(with_grad[first_bad - len(losses)]), '?')}'"
        log.warning(
            "step %d: non-finite %s; optimizer step skipped (%d in a row, %d in all)",
            trainer.global_step,
            what,
            self.consecutive,
            self.skipped,
        )
        if self.consecutive >= self.max_consecutive:
            raise NonFiniteTrainingError(
                f"{self.consecutive} consecutive training steps had a non-finite loss or "
                f"gradient (guard.max_consecutive_nonfinite={self.max_consecutive}; last: "
                f"step {trainer.global_step}, epoch {trainer.current_epoch}, non-finite {what}); "
                "the weights are those of the last finite step. Check the data for NaN/inf "
                "values, or lower the learning rate"
            )

    def on_train_batch_end(
        self,
        trainer: pl.Trainer,
        pl_module: pl.LightningModule,
        outputs: Any,
        batch: Any,
        batch_idx: int,
    ) -> None:
        pl_module.log(self.log_key, float(self.skipped), on_step=True, on_epoch=False)

    def state_dict(self) -> dict[str, int]:
        return {"skipped": self.skipped, "consecutive": self.consecutive}

    def load_state_dict(self, state_dict: Mapping[str, Any]) -> None:
        self.skipped = int(state_dict["skipped"])
        self.consecutive = int(state_dict["consecutive"])


def global_rng_state() -> dict[str, Any]:
    """The global RNG states of torch (CPU and CUDA), numpy and Python as plain values and
    tensors (loadable with ``torch.load(weights_only=True)``)."""
    kind, keys, pos, has_gauss, gauss = np.random.get_state()  # noqa: NPY002 (the global one)
    version, py_state, py_gauss = random.getstate()
    return {
        "torch": torch.get_rng_state(),
        "torch_cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        "numpy": [str(kind), torch.from_numpy(keys.astype(np.int64)), pos, has_gauss, gauss],
        "python": [version, list(py_state), py_gauss],
    }


def set_global_rng_state(state: Mapping[str, Any]) -> None:
    """Restore states from :func:`global_rng_state`."""
    torch.set_rng_state(state["torch"])
    cuda = state.get("torch_cuda") or []
    if cuda and torch.cuda.is_available() and len(cuda) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(cuda)
    kind, keys, pos, has_gauss, gauss = state["numpy"]
    np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, gauss))  # noqa: NPY002
    version, py_state, py_gauss = state["python"]
    random.setstate((version, tuple(py_state), py_gauss))


class GlobalRNGState(Callback):
    """Saves the global RNG states (torch, CUDA, numpy, Python) in every checkpoint and
    restores them when a run resumes from one.

    Lightning restores the loops, optimizers and schedulers but not the global RNGs, which
    dropout and random draws inside training steps use (the data modules draw from their
    own seeded generators). The state captured when the checkpoint is written is put back
    just before the first training batch after the resume, after set-up and the sanity
    check, so the resumed run draws what the uninterrupted run drew next.
    """

    def __init__(self) -> None:
        self._pending: dict[str, Any] | None = None

    @property
    def state_key(self) -> str:
        return "GlobalRNGState"

    def state_dict(self) -> dict[str, Any]:
        return global_rng_state()

    def load_state_dict(self, state_dict: Mapping[str, Any]) -> None:
        self._pending = dict(state_dict)

    def on_train_batch_start(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch: Any, batch_idx: int
    ) -> None:
        if self._pending is not None:
            set_global_rng_state(self._pending)
            self._pending = None


__all__ = [
    "GlobalRNGState",
    "NonFiniteGuard",
    "NonFiniteTrainingError",
    "global_rng_state",
    "set_global_rng_state",
]
