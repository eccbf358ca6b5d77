"""LastCheckpoint writes last.ckpt at every epoch end and every N steps whatever else is
configured (once per step when two instances share the folder); AtomicCheckpointIO never
leaves a partial file under a checkpoint's name."""

from __future__ import annotations

import errno
import os

import pytest
import pytorch_lightning as pl
import torch
from pytorch_lightning.callbacks import ModelCheckpoint
from pytorch_lightning.demos.boring_classes import BoringModel

import sss2bathy.callbacks.checkpoint as checkpoint_module
from sss2bathy.callbacks import AtomicCheckpointIO, LastCheckpoint, use_atomic_checkpoints
from sss2bathy.utils.atomic import WriteError, default_file_mode


class RecordingIO(AtomicCheckpointIO):
    """Records (file name, epoch, global step) of every save."""

    def __init__(self) -> None:
        super().__init__()
        self.saves: list[tuple[str, int, int]] = []

    def save_checkpoint(self, checkpoint, path, storage_options=None):
        self.saves.append((os.path.basename(path), checkpoint["epoch"], checkpoint["global_step"]))
        super().save_checkpoint(checkpoint, path, storage_options)


def _fit(tmp_path, callbacks, **trainer_kwargs) -> RecordingIO:
    torch.manual_seed(0)
    trainer = pl.Trainer(
        default_root_dir=tmp_path,
        accelerator="cpu",
        max_epochs=3,
        limit_train_batches=4,
        limit_val_batches=2,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        callbacks=callbacks,
        **trainer_kwargs,
    )
    io = RecordingIO()
    trainer.strategy.checkpoint_io = io
    trainer.fit(BoringModel())
    return io


@pytest.mark.parametrize("val_every", [1, 2])
def test_last_ckpt_every_epoch_whatever_top_k_and_validation_cadence(tmp_path, val_every):
    ckpts = tmp_path / "checkpoints"
    callbacks = [
        LastCheckpoint(dirpath=ckpts, every_n_epochs=1),
        LastCheckpoint(dirpath=ckpts, every_n_train_steps=3),
        # a top-k checkpoint beside them changes nothing of last.ckpt
        ModelCheckpoint(dirpath=ckpts, filename="best", save_top_k=1),
    ]
    io = _fit(tmp_path, callbacks, check_val_every_n_epoch=val_every)
    lasts = [(epoch, step) for name, epoch, step in io.saves if name == "last.ckpt"]
    # steps 3, 6, 9, 12 and the epoch ends at 4, 8, 12: one save per step
    assert lasts == [(0, 3), (0, 4), (1, 6), (1, 8), (2, 9), (2, 12)]
    assert sorted(p.name for p in ckpts.iterdir()) == ["best.ckpt", "last.ckpt"]


def test_lightnings_own_last_with_save_top_k_0_skips_the_epoch_ends(tmp_path):
    # what conf/callbacks/default.yaml had: last.ckpt only at the end of the fit, so a run
    # killed mid-way left none
    callbacks = [ModelCheckpoint(dirpath=tmp_path, save_last=True, save_top_k=0, every_n_epochs=1)]
    assert _fit(tmp_path, callbacks).saves == [("last.ckpt", 3, 12)]  # at train end


def test_every_n_epochs_and_the_final_state(tmp_path):
    io = _fit(tmp_path, [LastCheckpoint(dirpath=tmp_path, every_n_epochs=2)])
    # epoch 1's end, then the final state at train end (epoch 2 is not a multiple of 2;
    # Lightning counts the finished epochs there: 3)
    assert io.saves == [("last.ckpt", 1, 8), ("last.ckpt", 3, 12)]


def test_last_checkpoint_checks_its_arguments():
    with pytest.raises(ValueError, match="every_n_epochs: expected an integer >= 0, found -1"):
        LastCheckpoint(every_n_epochs=-1)
    with pytest.raises(ValueError, match="every_n_train_steps: expected an integer >= 0"):
        LastCheckpoint(every_n_train_steps=1.5)


def test_atomic_save_replaces_whole_files_with_the_default_mode(tmp_path):
    path = tmp_path / "sub" / "last.ckpt"
    io = AtomicCheckpointIO()
    io.save_checkpoint({"state_dict": {"w": torch.ones(3)}}, path)
    io.save_checkpoint({"state_dict": {"w": torch.zeros(3)}}, path)
    assert os.listdir(path.parent) == ["last.ckpt"]
    assert torch.equal(torch.load(path, weights_only=True)["state_dict"]["w"], torch.zeros(3))
    assert path.stat().st_mode & 0o777 == default_file_mode()


def test_a_failed_save_leaves_the_previous_file_and_no_partial_one(tmp_path, monkeypatch):
    path = tmp_path / "last.ckpt"
    io = AtomicCheckpointIO()
    io.save_checkpoint({"state_dict": {"w": torch.ones(3)}}, path)
    before = path.read_bytes()

    def disk_full(obj, f):
        f.write(b"PK\x03\x04 half a checkpoint")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(checkpoint_module.torch, "save", disk_full)
    with pytest.raises(WriteError) as err:
        io.save_checkpoint({"state_dict": {"w": torch.zeros(3)}}, path)
    assert os.listdir(tmp_path) == ["last.ckpt"] and path.read_bytes() == before
    assert err.value.errno == errno.ENOSPC and err.value.filename == str(path)
    assert str(err.value).startswith(f"checkpoint {path}: not written (No space left on device); ")
    assert " free in " in str(err.value) and "the previous file is unchanged" in str(err.value)


def test_use_atomic_checkpoints_keeps_a_custom_checkpoint_io(tmp_path):
    trainer = pl.Trainer(default_root_dir=tmp_path, accelerator="cpu", logger=False)
    use_atomic_checkpoints(trainer)
    assert type(trainer.strategy.checkpoint_io) is AtomicCheckpointIO
    custom = RecordingIO()
    trainer.strategy.checkpoint_io = custom
    use_atomic_checkpoints(trainer)
    assert trainer.strategy.checkpoint_io is custom
