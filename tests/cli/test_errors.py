"""User errors end an entry point with ONE line on stderr and exit status 2; ``--trace``
shows the traceback; the data folder is left as it was."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

from sss2bathy.cli._common import USER_ERROR_EXIT, one_line, user_errors
from sss2bathy.io.xtf import write_xtf

ROOT = Path(__file__).resolve().parents[2]


def run(args: list[str], tmp_path: Path, entry: str = "prepare") -> subprocess.CompletedProcess:
    env = {**os.environ, "SSS2BATHY_ROOT": str(ROOT), "OMP_NUM_THREADS": "1"}
    env.pop("HYDRA_FULL_ERROR", None)
    return subprocess.run(
        [sys.executable, "-m", f"sss2bathy.cli.{entry}", *args, f"hydra.run.dir={tmp_path / 'o'}"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def tree(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


@pytest.fixture
def corrupt_xtf(tmp_path):
    spec = importlib.util.spec_from_file_location("io_fixtures", ROOT / "tests/io/conftest.py")
    fixtures = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fixtures)
    ORIGIN, ping_offsets, synthetic_line = (
        fixtures.ORIGIN,
        fixtures.ping_offsets,
        fixtures.synthetic_line,
    )

    raw = tmp_path / "raw"
    path = raw / "L0.xtf"
    write_xtf(synthetic_line(n_pings=20, n_bins=32), path, ORIGIN)
    with open(path, "r+b") as f:
        f.seek(ping_offsets(path)[5])
        f.write(b"\x00\x00")
    data = tmp_path / "data"
    (data / "keep").mkdir(parents=True)
    return path, data


def stderr_lines(proc: subprocess.CompletedProcess) -> list[str]:
    return [ln for ln in proc.stderr.splitlines() if ln.strip()]


def test_typo_in_a_key_is_one_line_with_did_you_mean(tmp_path):
    proc = run(["data.survey.nam=x"], tmp_path)
    assert proc.returncode == USER_ERROR_EXIT, proc.stderr
    assert stderr_lines(proc) == [
        "error: unknown config key 'data.survey.nam'; did you mean 'name'? "
        "(to add a new key: +data.survey.nam=...)"
    ]


def test_bad_file_and_bad_value_are_one_line_before_any_config_dump(tmp_path, corrupt_xtf):
    path, data = corrupt_xtf
    before = tree(data)
    base = ["data/survey=xtf", f"data.survey.files={path}", f"paths.data_dir={data}"]
    proc = run([*base, "data.survey.max_jump_m=-1"], tmp_path)
    assert proc.returncode == USER_ERROR_EXIT
    assert "composed config" not in proc.stdout + proc.stderr
    assert stderr_lines(proc) == [
        "error: config key 'data.survey.max_jump_m': expected a positive distance (m), found -1"
    ]
    proc = run(base, tmp_path)
    assert proc.returncode == USER_ERROR_EXIT
    (line,) = stderr_lines(proc)
    # what the import refuses first (the damaged packet, or the altimeter check) is the
    # reader's business; the command's is one line naming the file
    assert line.startswith("error: ") and "L0.xtf" in line
    assert "Traceback" not in proc.stdout + proc.stderr
    assert tree(data) == before


@pytest.mark.parametrize(
    "override, message",
    [
        # checked by the data module's constructor (no table rule): still before the dump
        ("data.batch_pings=0", "config key 'data.batch_pings': expected a positive integer"),
        ("model.sensor.shadow_threshold=-0.1", "config key 'model.sensor.shadow_threshold'"),
    ],
)
def test_train_reports_a_constructor_error_in_one_line_before_the_config_dump(
    tmp_path, override, message
):
    data = tmp_path / "data"
    args = ["experiment=siren_lambert", "scale=tiny", f"paths.data_dir={data}", override]
    proc = run(args, tmp_path, entry="train")
    assert proc.returncode == USER_ERROR_EXIT, proc.stderr[-3000:]
    (line,) = stderr_lines(proc)
    assert line.startswith(f"error: {message}") and line.endswith(override.split("=")[1])
    assert "composed config" not in proc.stdout + proc.stderr
    assert not data.exists()  # no survey was made


def test_trace_flag_is_taken_off_the_command_line(monkeypatch):
    from sss2bathy.cli._common import setup_environment, show_traceback

    for var in ("HYDRA_FULL_ERROR", "SSS2BATHY_TRACE"):  # setenv first: restored afterwards
        monkeypatch.setenv(var, "0")
        monkeypatch.delenv(var)
    monkeypatch.setattr(sys, "argv", ["sss2bathy-prepare", "--trace", "seed=1"])
    assert not show_traceback()
    setup_environment()
    assert sys.argv == ["sss2bathy-prepare", "seed=1"] and show_traceback()
    assert os.environ["HYDRA_FULL_ERROR"] == "1"


def test_user_errors_wrapper_reraises_other_errors(monkeypatch, capsys):
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    monkeypatch.delenv("SSS2BATHY_TRACE", raising=False)

    @user_errors
    def bad_value():
        raise ValueError("x: expected 1,\n found 2")

    with pytest.raises(SystemExit) as exit_:
        bad_value()
    assert exit_.value.code == USER_ERROR_EXIT
    assert capsys.readouterr().err == "error: x: expected 1, found 2\n"

    @user_errors
    def bug():
        raise KeyError("a bug keeps its traceback")

    with pytest.raises(KeyError):
        bug()
    monkeypatch.setenv("HYDRA_FULL_ERROR", "1")
    with pytest.raises(ValueError):
        bad_value()
    assert one_line(" a\n\n b ") == "a b"
