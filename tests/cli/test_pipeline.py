"""``python -m sss2bathy.cli.pipeline``: --help runs nothing; arguments; the Makefile's help."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from sss2bathy.cli.pipeline import STAGE_NAMES, parse_args

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("flag", ["--help", "-h"])
def test_help_prints_usage_and_runs_nothing(tmp_path, flag):
    (tmp_path / "conf").symlink_to(ROOT / "conf")
    env = dict(os.environ, SSS2BATHY_ROOT=str(tmp_path), OMP_NUM_THREADS="1")
    proc = subprocess.run(
        [sys.executable, "-m", "sss2bathy.cli.pipeline", flag, "scale=tiny"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("usage: python -m sss2bathy.cli.pipeline")
    assert "stages, in order: " + ", ".join(STAGE_NAMES) in proc.stdout
    assert "===" not in proc.stdout  # no stage started
    assert sorted(p.name for p in tmp_path.iterdir()) == ["conf"]  # nothing written


def test_parse_args_splits_scale_stages_and_overrides():
    scale, stages, rest = parse_args(["scale=tiny", "stages=[cnn, report]", "seed=2"])
    assert (scale, stages, rest) == ("tiny", ["cnn", "report"], ["seed=2"])
    with pytest.raises(SystemExit, match="unknown stage"):
        parse_args(["stages=[cnn,nope]"])


@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_make_help_has_no_colour_codes_in_a_pipe_and_lists_every_experiment():
    proc = subprocess.run(
        ["make", "--no-print-directory", "help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    assert "\033[" not in proc.stdout
    targets = {line.split()[0] for line in proc.stdout.splitlines() if line.strip()}
    assert {"siren-heights-only", "siren-gt-n2d", "sweep-siren", "report", "demo"} <= targets
