"""Progress lines with epoch, step, percent, rate and ETA when stdout is not a terminal."""

from __future__ import annotations

import logging
from types import SimpleNamespace

import pytest
import pytorch_lightning as pl
from pytorch_lightning.demos.boring_classes import BoringModel

from sss2bathy.callbacks.progress import ProgressLogger
from sss2bathy.utils.progress import format_duration, log_progress, progress_line


class FakeClock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def fake_trainer(**kw):
    base = dict(
        is_global_zero=True,
        estimated_stepping_batches=1000,
        global_step=0,
        current_epoch=0,
        max_epochs=10,
        sanity_checking=False,
    )
    return SimpleNamespace(**{**base, **kw})


def progress_lines(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "sss2bathy.progress"]


def test_lines_every_interval_with_epoch_step_percent_rate_and_eta(caplog):
    clock = FakeClock()
    cb = ProgressLogger(every_s=30, clock=clock, is_terminal=lambda: False)
    trainer = fake_trainer()
    with caplog.at_level(logging.INFO, logger="sss2bathy.progress"):
        cb.on_train_start(trainer, None)
        for step in range(1, 401):  # 4 steps/s for 100 s
            clock.t += 0.25
            trainer.global_step = step
            trainer.current_epoch = step // 100
            cb.on_train_batch_end(trainer)
        cb.on_train_end(trainer, None)
    lines = progress_lines(caplog)
    assert lines[0].startswith("train: 0/1000 steps (0.0 %)") and "not a terminal" in lines[0]
    assert len(lines) == 1 + 3 + 1  # start, every 30 s of 100 s, end
    assert lines[1] == (
        "train: epoch 2/10: 120/1000 steps (12.0 %), 4 steps/s, 30 s elapsed, ETA 3 min 40 s"
    )
    assert lines[-1].startswith("train done: epoch 5/10: 400/1000 steps (40.0 %)")
    trainer.current_epoch = 10  # a finished fit's counter is past its last epoch
    assert cb._label(trainer, "train done") == "train done: epoch 10/10"


def test_silent_on_a_terminal_and_validation_counts(caplog):
    clock = FakeClock()
    quiet = ProgressLogger(every_s=1, clock=clock, is_terminal=lambda: True)
    trainer = fake_trainer(global_step=50)
    with caplog.at_level(logging.INFO, logger="sss2bathy.progress"):
        quiet.on_train_start(trainer, None)
        clock.t += 5
        quiet.on_train_batch_end(trainer)
        assert progress_lines(caplog) == []
        # a resumed run (step 50): the rate counts this run's steps only
        loud = ProgressLogger(every_s=1, clock=clock, is_terminal=lambda: False)
        loud.on_train_start(trainer, None)
        clock.t += 10
        trainer.global_step = 70
        loud.on_validation_batch_end(trainer)
    (start, val) = progress_lines(caplog)
    assert val.startswith("validating: epoch 1/10: 70/1000 steps (7.0 %), 2 steps/s")
    assert "ETA 7 min 45 s" in val


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="every_s: expected a positive number"):
        ProgressLogger(every_s=0)
    with pytest.raises(ValueError, match="when: expected one of not_tty, always, never"):
        ProgressLogger(when="sometimes")


def test_a_tiny_fit_logs_progress_when_not_a_terminal(caplog, tmp_path):
    model = BoringModel()
    cb = ProgressLogger(every_s=1e-6, when="always")
    trainer = pl.Trainer(
        max_epochs=2,
        limit_train_batches=3,
        limit_val_batches=1,
        callbacks=[cb],
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        default_root_dir=tmp_path,
    )
    with caplog.at_level(logging.INFO, logger="sss2bathy.progress"):
        trainer.fit(model)
    lines = progress_lines(caplog)
    assert any(ln.startswith("train: epoch 2/2: 5/6 steps (83.3 %)") for ln in lines), lines
    assert all("ETA" in ln for ln in lines[1:])


def test_helpers():
    assert format_duration(42.4) == "42 s"
    assert format_duration(3725) == "1 h 02 min"
    assert format_duration(float("nan")) == "?"
    assert progress_line("import", 3, None, 6.0, "files") == (
        "import: 3 files, 0.5 files/s, 6 s elapsed"
    )


def test_log_progress_wraps_a_loop(caplog):
    with caplog.at_level(logging.INFO, logger="sss2bathy.progress"):
        assert list(log_progress(range(3), "draping", every_s=1e-9, unit="lines")) == [0, 1, 2]
        assert list(log_progress(range(3), "quick", every_s=3600)) == [0, 1, 2]
    lines = progress_lines(caplog)
    assert lines[0].startswith("draping: 1/3 lines (33.3 %)") and "ETA" in lines[0]
    assert lines[-1].startswith("draping done: 3/3 lines (100.0 %)")
    assert not any(ln.startswith("quick") for ln in lines)  # short loops stay silent


def test_training_experiments_have_the_progress_callback():
    import os

    from hydra import compose, initialize_config_dir

    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    conf = os.path.join(root, "conf")
    # the CNN (default callbacks + its own), a SIREN with a callbacks list, a tuning run
    names = ["cnn", "siren_lambert", "lambert_tune"]
    with initialize_config_dir(config_dir=conf, version_base="1.3"):
        for name in names:
            cfg = compose("train", overrides=[f"experiment={name}"])
            target = cfg.callbacks.progress._target_
            assert target == "sss2bathy.callbacks.progress.ProgressLogger", name
        # callbacks=progress (the map's fold fits): the progress lines and nothing else
        cfg = compose("train", overrides=["experiment=siren_gt_n2d", "callbacks=progress"])
        assert list(cfg.callbacks) == ["progress"]
        assert cfg.callbacks.progress._target_ == "sss2bathy.callbacks.progress.ProgressLogger"


def test_a_test_pass_logs_its_batches(caplog, tmp_path):
    cb = ProgressLogger(every_s=1e-6, when="always")
    trainer = pl.Trainer(
        limit_test_batches=4,
        callbacks=[cb],
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        default_root_dir=tmp_path,
    )
    with caplog.at_level(logging.INFO, logger="sss2bathy.progress"):
        trainer.test(BoringModel())
    lines = progress_lines(caplog)
    assert lines[0].startswith("test: 1/4 batches (25.0 %)") and "ETA" in lines[0], lines
    assert lines[-1].startswith("test done: 4/4 batches (100.0 %)"), lines
    # on a terminal a test pass is silent
    caplog.clear()
    quiet = ProgressLogger(every_s=1e-6, is_terminal=lambda: True)
    trainer = pl.Trainer(limit_test_batches=2, callbacks=[quiet], logger=False,
                         enable_progress_bar=False, enable_model_summary=False,
                         default_root_dir=tmp_path)  # fmt: skip
    with caplog.at_level(logging.INFO, logger="sss2bathy.progress"):
        trainer.test(BoringModel())
    assert progress_lines(caplog) == []
