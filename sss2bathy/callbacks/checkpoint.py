"""The run's resumable ``last.ckpt``: written at every epoch end, every N steps and on
SIGTERM / SIGINT, always atomically.

* :class:`LastCheckpoint` (``conf/callbacks/default.yaml``: ``epoch_checkpoint`` and
  ``step_checkpoint``): a ``ModelCheckpoint`` that keeps only ``last.ckpt`` and writes it
  whatever ``save_top_k`` is (Lightning's own writes "last" at an epoch end only when it
  also saved a top-k checkpoint there, so ``save_top_k: 0`` never did). The epoch save
  happens at the train-epoch end, after that epoch's validation, so every epoch is saved
  also when validation runs only every few epochs.
* Signals: Lightning's own SIGTERM handler sets ``trainer.received_sigterm`` and its loops
  stop with ``SIGTERMException`` at the next batch end. ``LastCheckpoint`` saves
  ``last.ckpt`` at that batch end (the same state as a periodic mid-epoch save) and routes
  a first SIGINT (Ctrl+C) the same way instead of a ``KeyboardInterrupt`` in the middle of
  an optimizer step; a second SIGINT interrupts at once. With several processes (DDP) the
  save waits for the step at which Lightning stops every rank together (``on_exception``),
  so no rank waits in a barrier for another. Lightning's SLURM auto-requeue
  (SIGUSR1, ``hpc_ckpt_<n>.ckpt``) is left as it is. A signal during the fit's validation
  saves nothing new (a mid-validation state): the newest save stands.
  :func:`interruption` tells the entry point what happened, for its exit status (143 /
  130) and its one-line resume hint.
* :class:`AtomicCheckpointIO`: every checkpoint of the trainer (``last.ckpt``, top-k
  files, SLURM saves) goes to a temporary name in its folder, is flushed to disk and renamed
  over the final name; a write that fails (full disk, read-only folder) leaves the previous
  file untouched, removes the partial one and raises a one-line
  :class:`~sss2bathy.utils.atomic.WriteError` with the free space.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytorch_lightning as pl
import torch
from lightning_fabric.plugins.io.torch_io import TorchCheckpointIO
from lightning_fabric.utilities.cloud_io import _is_local_file_protocol
from pytorch_lightning.callbacks import ModelCheckpoint
from pytorch_lightning.utilities.exceptions import SIGTERMException

from sss2bathy.utils.atomic import atomic_path, write_error

log = logging.getLogger(__name__)


class AtomicCheckpointIO(TorchCheckpointIO):
    """``TorchCheckpointIO`` whose saves are atomic on a local disk (module docstring).

    Remote paths (``s3://`` ...) go to Lightning's own save.
    """

    def save_checkpoint(
        self, checkpoint: dict[str, Any], path: Any, storage_options: Any = None
    ) -> None:
        if storage_options is not None or not _is_local_file_protocol(path):
            return super().save_checkpoint(checkpoint, path, storage_options)
        path = Path(path)
        try:
            with atomic_path(path) as tmp, open(tmp, "wb") as f:
                torch.save(checkpoint, f)
                f.flush()
                os.fsync(f.fileno())
        except OSError as err:
            raise write_error(path, err, "checkpoint") from None
        _fsync_folder(path.parent)


def _fsync_folder(folder: Path) -> None:
    """Make a rename in ``folder`` durable (best effort: not every OS or file system can)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def use_atomic_checkpoints(trainer: pl.Trainer) -> None:
    """Give ``trainer`` an :class:`AtomicCheckpointIO` in place of Lightning's default
    ``TorchCheckpointIO`` (a custom checkpoint IO of the config is kept as it is)."""
    if type(trainer.strategy.checkpoint_io) is TorchCheckpointIO:
        trainer.strategy.checkpoint_io = AtomicCheckpointIO()


@dataclass
class Interruption:
    """A fit stopped by a signal: which, where, and the checkpoint that resumes it."""

    signal: str
    epoch: int
    step: int
    checkpoint: Path | None  # the newest save (None: none was ever written)
    saved_now: bool  # holds the state the fit stopped at (False: an earlier save)

    @property
    def exit_code(self) -> int:
        """The shell's status of a process ended by the signal: 128 + its number."""
        return 128 + int(getattr(signal, self.signal, signal.SIGTERM))


class LastCheckpoint(ModelCheckpoint):
    """``last.ckpt`` every ``every_n_epochs`` epochs or every ``every_n_train_steps`` steps
    (one trigger per instance, as in ``ModelCheckpoint``), whatever ``save_top_k``, and on
    SIGTERM / SIGINT (module docstring). Several instances writing the same folder share
    the work: one save per step, the signal save by the first.

    Args:
        dirpath: the folder of ``last.ckpt`` (None: Lightning's default).
        every_n_epochs: save at the end of every this many epochs (0: never).
        every_n_train_steps: save after every this many optimizer steps (0: never).
        save_on_signal: save on SIGTERM / SIGINT and take over SIGINT during the fit.
    """

    def __init__(
        self,
        dirpath: str | Path | None = None,
        every_n_epochs: int | None = None,
        every_n_train_steps: int | None = None,
        save_on_signal: bool = True,
    ) -> None:
        for name, value in (
            ("every_n_epochs", every_n_epochs),
            ("every_n_train_steps", every_n_train_steps),
        ):
            if value is not None and (
                not isinstance(value, int) or isinstance(value, bool) or value < 0
            ):
                raise ValueError(f"{name}: expected an integer >= 0, found {value!r}")
        super().__init__(
            dirpath=dirpath,
            save_last=True,
            save_top_k=0,
            every_n_epochs=every_n_epochs,
            every_n_train_steps=every_n_train_steps,
            save_on_train_epoch_end=True,
            enable_version_counter=False,  # always last.ckpt, never last-v1.ckpt
        )
        self.save_on_signal = bool(save_on_signal)
        self.interruption: Interruption | None = None
        self._sigint_seen = False
        self._previous_sigint: Any = None

    # ------------------------------------------------------------------ peers
    def _peers(self, trainer: pl.Trainer) -> list[LastCheckpoint]:
        return [
            cb
            for cb in trainer.checkpoint_callbacks
            if isinstance(cb, LastCheckpoint) and cb.dirpath == self.dirpath
        ]

    def _saved_at_this_step(self, trainer: pl.Trainer) -> bool:
        return any(p._last_global_step_saved == trainer.global_step for p in self._peers(trainer))

    def _signal_owner(self, trainer: pl.Trainer) -> bool:
        owners = [p for p in self._peers(trainer) if p.save_on_signal]
        return bool(owners) and owners[0] is self

    @property
    def last_path(self) -> Path | None:
        return (
            Path(self.dirpath) / f"{self.CHECKPOINT_NAME_LAST}{self.FILE_EXTENSION}"
            if (self.dirpath)
            else None
        )

    def _save_last(self, trainer: pl.Trainer) -> None:
        self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))

    # ------------------------------------------------------------------ periodic saves
    def on_train_batch_end(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs, batch, batch_idx
    ) -> None:
        if (
            trainer.received_sigterm
            and trainer.world_size == 1  # ranks stop together later (on_exception)
            and self._signal_owner(trainer)
            and not self._saved_at_this_step(trainer)
            and not self._should_skip_saving_checkpoint(trainer)
        ):
            # the loop stops after this batch: save the state a periodic save would have
            self._save_last(trainer)
            self._record(trainer, saved_now=True)
            return
        if self._saved_at_this_step(trainer) or self._epoch_save_follows(trainer):
            return
        super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)

    def _epoch_due(self, trainer: pl.Trainer) -> bool:
        return self._every_n_epochs >= 1 and (trainer.current_epoch + 1) % self._every_n_epochs == 0

    def _epoch_save_follows(self, trainer: pl.Trainer) -> bool:
        """This is the epoch's last batch and a peer saves at its end (after validation):
        a step save now would be overwritten at once."""
        last_batch = trainer.fit_loop.epoch_loop.batch_progress.is_last_batch
        return last_batch and any(p._epoch_due(trainer) for p in self._peers(trainer))

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        # also after a step save at this step: the epoch end's state (validation done,
        # epoch counted) is what a resume should continue from
        if self._epoch_due(trainer) and not self._should_skip_saving_checkpoint(trainer):
            self._save_last(trainer)

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        pass  # epoch saves happen at the train-epoch end, after the epoch's validation

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        # the final state (also a fit stopped by max_steps or early stopping mid-epoch)
        if self._every_n_epochs >= 1 and not self._saved_at_this_step(trainer):
            if trainer.global_step > 0:
                self._save_last(trainer)

    # ------------------------------------------------------------------ signals
    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        super().on_train_start(trainer, pl_module)
        self.interruption = None
        if (
            self.save_on_signal
            and self._signal_owner(trainer)
            and trainer.world_size == 1
            and threading.current_thread() is threading.main_thread()
        ):
            self._sigint_seen = False
            self._previous_sigint = signal.getsignal(signal.SIGINT)
            signal.signal(signal.SIGINT, self._on_sigint(trainer))

    def _on_sigint(self, trainer: pl.Trainer):
        def handler(signum, frame) -> None:
            if self._sigint_seen:
                self._restore_sigint()
                raise KeyboardInterrupt
            self._sigint_seen = True
            log.warning(
                "SIGINT: saving last.ckpt and stopping after this step (Ctrl+C again stops "
                "at once, without a save)"
            )
            connector = getattr(trainer, "_signal_connector", None)
            if connector is None:  # a Lightning without it: interrupt as Python would
                raise KeyboardInterrupt
            # Lightning's own graceful stop: the loops end at the next batch end
            connector.received_sigterm = True

        return handler

    def _restore_sigint(self) -> None:
        if self._previous_sigint is not None and (
            threading.current_thread() is threading.main_thread()
        ):
            signal.signal(signal.SIGINT, self._previous_sigint)
        self._previous_sigint = None

    def on_exception(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, exception: BaseException
    ) -> None:
        self._restore_sigint()
        if not isinstance(exception, SIGTERMException) or not self._signal_owner(trainer):
            return
        if self.interruption is not None:  # saved at the batch end already
            return
        mid_validation = trainer.validating and not trainer.sanity_checking
        if (
            self.save_on_signal
            and trainer.state.fn == "fit"
            and not mid_validation
            and not trainer.sanity_checking
            and trainer.global_step > 0
            and not self._saved_at_this_step(trainer)
        ):
            self._save_last(trainer)
        # "saved" when last.ckpt holds the state the fit stopped at (this save or a
        # periodic one at this step, e.g. the epoch end the signal waited for)
        self._record(trainer, saved_now=self._saved_at_this_step(trainer))

    def teardown(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        self._restore_sigint()

    def _record(self, trainer: pl.Trainer, saved_now: bool) -> None:
        last = self.last_path
        self.interruption = Interruption(
            signal="SIGINT" if self._sigint_seen else "SIGTERM",
            epoch=trainer.current_epoch,
            step=trainer.global_step,
            checkpoint=last if last is not None and last.is_file() else None,
            saved_now=saved_now,
        )


def interruption(trainer: pl.Trainer) -> Interruption:
    """What stopped ``trainer``'s fit with a ``SIGTERMException``: the record of its signal
    owner :class:`LastCheckpoint`, else (no such callback) a SIGTERM without a save."""
    for cb in trainer.callbacks:
        if isinstance(cb, LastCheckpoint) and cb.interruption is not None:
            return cb.interruption
    return Interruption("SIGTERM", trainer.current_epoch, trainer.global_step, None, False)
