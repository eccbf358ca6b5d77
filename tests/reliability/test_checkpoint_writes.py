"""Checkpoint writes that fail leave nothing partial: a full disk or a read-only checkpoint
folder stops the fit with one line naming the file and the free space, the previous
last.ckpt intact; a run folder another live fit is writing is refused, a stale lock taken
over with a warning."""

from __future__ import annotations

import errno
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from reliability_helpers import ROOT, compose_run, siren_overrides

from sss2bathy.cli._common import error_message, is_user_error
from sss2bathy.cli.train import train
from sss2bathy.utils.atomic import LOCK_NAME, FolderLockedError, WriteError, folder_lock


@pytest.fixture
def mount_tmpfs():
    """Mount a tmpfs with the given options on a folder (root only); unmounted after."""
    mounted: list[Path] = []

    def mount(folder: Path, options: str) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        proc = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)],
            capture_output=True,
            text=True,
        )
        if proc.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here (root and mount rights needed): {proc.stderr}")
        mounted.append(folder)

    yield mount
    for folder in reversed(mounted):
        subprocess.run(["umount", "-l", str(folder)], capture_output=True)


def _siren(plane_survey: Path, tmp: Path, epochs: int) -> list[str]:
    return siren_overrides(plane_survey, tmp) + [
        f"trainer.max_epochs={epochs}",
        f"model.output_dir={tmp / 'map'}",
    ]


def test_a_full_disk_keeps_the_previous_last_ckpt_and_says_how_much_is_free(
    tmp_path, plane_survey, mount_tmpfs
):
    # a tiny SIREN checkpoint is ~52 KB: the first fits in 64 KiB, the second (beside it
    # until the rename) does not
    run = tmp_path / "run"
    checkpoints = run / "checkpoints"
    mount_tmpfs(checkpoints, "size=64k")
    with pytest.raises(WriteError) as err:
        train(compose_run(_siren(plane_survey, tmp_path, 3), run), run)
    last = checkpoints / "last.ckpt"
    assert err.value.errno == errno.ENOSPC and err.value.filename == str(last)
    text = str(err.value)
    assert text.startswith(f"checkpoint {last}: not written (No space left on device); ")
    assert "KiB free in" in text and "the previous file is unchanged" in text
    assert sorted(p.name for p in checkpoints.iterdir()) == ["last.ckpt"]  # no partial file
    assert torch.load(last, weights_only=True)["epoch"] == 0  # the previous save, whole
    # the entry points' one line: the file and the free space
    assert is_user_error(err.value)
    line = error_message(err.value)
    assert line.startswith(f"{last}: no space left on its disk (") and "free there" in line
    assert not (run / LOCK_NAME).exists()


def test_a_read_only_checkpoint_folder_is_one_line_and_leaves_nothing(
    tmp_path, plane_survey, mount_tmpfs
):
    run = tmp_path / "run"
    checkpoints = run / "checkpoints"
    mount_tmpfs(checkpoints, "ro,size=64k")
    with pytest.raises(WriteError) as err:
        train(compose_run(_siren(plane_survey, tmp_path, 1), run), run)
    assert err.value.errno == errno.EROFS
    assert str(err.value).startswith(
        f"checkpoint {checkpoints / 'last.ckpt'}: not written (Read-only file system); "
    )
    assert is_user_error(err.value) and "read-only file system" in error_message(err.value)
    assert not list(checkpoints.iterdir())


# ------------------------------------------------------------------ run folder lock
def test_a_run_folder_a_live_fit_is_writing_is_refused_in_one_line(tmp_path, plane_survey):
    run = tmp_path / "run"
    data = tmp_path / "data"
    with folder_lock(run) as lock:
        with pytest.raises(FolderLockedError) as err:
            train(compose_run(_siren(plane_survey, data, 1), run), run)
        assert lock.is_file()
    text = str(err.value)
    assert "\n" not in text and text.startswith(f"{run}: another run is writing this folder")
    assert f"pid {os.getpid()} on {socket.gethostname()}" in text and str(lock) in text
    assert not data.exists()  # refused before any data was made
    assert not (run / LOCK_NAME).exists()  # released by its holder


def test_a_stale_lock_is_taken_over_with_a_warning(tmp_path, plane_survey, caplog):
    run = tmp_path / "run"
    run.mkdir()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True).stdout.strip()  # fmt: skip
    holder = {"pid": int(dead), "host": socket.gethostname(), "started": "2020-01-01T00:00:00"}
    (run / LOCK_NAME).write_text(json.dumps(holder))
    with caplog.at_level("WARNING", logger="sss2bathy.utils.atomic"):
        train(compose_run(_siren(plane_survey, tmp_path, 1), run), run)
    assert f"taking over the stale lock of pid {dead} on {socket.gethostname()}" in caplog.text
    assert (run / "checkpoints" / "last.ckpt").is_file()
    assert not (run / LOCK_NAME).exists()


@pytest.mark.slow
def test_cli_into_a_locked_run_folder_is_one_stderr_line_and_exit_2(tmp_path, plane_survey):
    env = {**os.environ, "SSS2BATHY_ROOT": str(ROOT), "OMP_NUM_THREADS": "1"}
    env.pop("HYDRA_FULL_ERROR", None)
    run = tmp_path / "run"
    args = _siren(plane_survey, tmp_path / "data", 1) + [f"hydra.run.dir={run}"]
    with folder_lock(run):
        proc = subprocess.run(
            [sys.executable, "-m", "sss2bathy.cli.train", *args],
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
        )
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(
        f"error: {run}: another run is writing this folder (pid {os.getpid()} on "
    ), lines
    assert "Traceback" not in proc.stdout + proc.stderr
    assert run.is_dir()  # the folder of the run holding the lock is left alone
