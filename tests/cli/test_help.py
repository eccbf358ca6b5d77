"""Every entry point's ``--help`` is short (a usage line, the main keys, examples); the full
Hydra help stays behind ``--hydra-help``; ``sss2bathy-map``'s start-up refusals are one line
(exit 2) before any run folder is made, naming keys as the map command spells them."""

from __future__ import annotations

import errno
import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from sss2bathy.cli._common import (
    USER_ERROR_EXIT,
    RenameKeys,
    check_crs_keys,
    collapse_series,
    log_config,
    os_error_message,
    rename_keys,
    user_errors,
)

ROOT = Path(__file__).resolve().parents[2]

# (module, how its usage line starts)
ENTRY_POINTS = [
    ("prepare", "usage: sss2bathy-prepare"),
    ("train", "usage: sss2bathy-train"),
    ("evaluate", "usage: sss2bathy-eval"),
    ("predict", "usage: sss2bathy-predict"),
    ("map", "usage: sss2bathy-map"),
    ("render", "usage: sss2bathy-render"),
    ("report", "usage: sss2bathy-report"),
    ("pipeline", "usage: python -m sss2bathy.cli.pipeline"),
]


def run_cli(args: list[str], cwd: Path, entry: str = "map") -> subprocess.CompletedProcess:
    env = {**os.environ, "SSS2BATHY_ROOT": str(ROOT), "OMP_NUM_THREADS": "1"}
    env.pop("HYDRA_FULL_ERROR", None)
    return subprocess.run(
        [sys.executable, "-m", f"sss2bathy.cli.{entry}", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=180,
    )


def stderr_lines(proc: subprocess.CompletedProcess) -> list[str]:
    return [ln for ln in proc.stderr.splitlines() if ln.strip()]


@pytest.mark.parametrize("module, usage", ENTRY_POINTS)
def test_help_is_short_with_a_usage_line_and_examples(module, usage, monkeypatch, capsys):
    cli = importlib.import_module(f"sss2bathy.cli.{module}")
    monkeypatch.setattr(sys, "argv", [f"sss2bathy-{module}", "--help"])
    code = 0
    try:
        returned = cli.main() if module != "render" else cli.main(["--help"])
        code = returned or 0
    except SystemExit as done:
        code = done.code or 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert code == 0
    assert lines[0].startswith(usage), lines[0]
    assert len(lines) < 40, out
    examples = [ln for ln in lines if ln.strip().startswith(("sss2bathy-", "python -m sss2bathy"))]
    assert len(examples) >= 2, out
    assert "_target_" not in out and "defaults:" not in out  # no config dump


def test_map_help_lists_its_three_methods_not_every_experiment(monkeypatch, capsys):
    from sss2bathy.cli import map as cli

    monkeypatch.setattr(sys, "argv", ["sss2bathy-map", "-h"])
    with pytest.raises(SystemExit) as done:
        cli.main()
    assert done.value.code == 0
    out = capsys.readouterr().out
    for method in cli.MAP_METHODS:
        assert method in out
    assert "d2_siren_lambert" not in out and "cnn_checkpoint=" in out and "files=" in out


def test_hydra_help_still_prints_the_full_help(tmp_path):
    proc = run_cli(["--hydra-help"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "== Configuration groups ==" in proc.stdout and "== Config ==" in proc.stdout
    assert "== Flags ==" in proc.stdout  # Hydra's own options follow
    assert len(proc.stdout.splitlines()) > 100


def refusal(args: list[str], monkeypatch, capsys) -> list[str]:
    """``sss2bathy-map args`` in this process: its exit status must be 2; its stderr lines.
    (The refusals come before Hydra runs, so no Hydra state is left behind.)"""
    from sss2bathy.cli import map as cli

    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    monkeypatch.delenv("SSS2BATHY_TRACE", raising=False)
    monkeypatch.setattr(sys, "argv", ["sss2bathy-map", *args])
    with pytest.raises(SystemExit) as done:
        cli.main()
    assert done.value.code == USER_ERROR_EXIT
    captured = capsys.readouterr()
    assert "Traceback" not in captured.out + captured.err
    return [ln for ln in captured.err.splitlines() if ln.strip()]


def test_misspelt_method_is_one_line_with_did_you_mean(tmp_path, monkeypatch, capsys):
    run_dir = tmp_path / "run"
    args = ["files=x.xtf", "method=siren_lambret", f"hydra.run.dir={run_dir}"]
    (line,) = refusal(args, monkeypatch, capsys)
    assert line.startswith("error: method: expected one of siren_lambert, siren_heights_only, ")
    assert "did you mean siren_lambert?" in line
    assert not run_dir.exists()


@pytest.mark.parametrize("key", ["survey.crs", "survey.mbes_crs"])
def test_bad_crs_is_one_line_before_any_run_folder(tmp_path, monkeypatch, capsys, key):
    run_dir = tmp_path / "run"
    args = ["files=x.xtf", f"{key}=EPSG:99999", f"paths.output_dir={tmp_path / 'out'}"]
    assert refusal([*args, f"hydra.run.dir={run_dir}"], monkeypatch, capsys) == [
        f"error: config key '{key}': expected a coordinate reference system pyproj knows "
        "(e.g. EPSG:32633, or null to take the file's), found 'EPSG:99999'"
    ]
    assert not run_dir.exists() and not (tmp_path / "out").exists()


def test_a_key_at_the_wrong_level_is_pointed_to(tmp_path, monkeypatch, capsys):
    args = ["files=x.xtf", "crs=EPSG:32633", f"hydra.run.dir={tmp_path / 'r'}"]
    (line,) = refusal(args, monkeypatch, capsys)
    assert "unknown config key 'crs'; did you mean 'survey.crs'?" in line


def test_map_names_keys_as_it_spells_them_and_leaves_no_run_folder(tmp_path):
    """An error from the import (``data.survey.<key>`` of the train config) reads
    ``survey.<key>`` in sss2bathy-map; the run folder Hydra made is removed."""
    run_dir = tmp_path / "run"
    script = (
        "import sys\n"
        "import sss2bathy.cli.map as m\n"
        "def refuse(*a, **k):\n"
        "    raise ValueError(\"config key 'data.survey.altitude_tolerance_m': expected the \"\n"
        "        'altimeter within 0.5 m of the bottom, found 3.2 m; data.holdout.fraction '\n"
        "        'and data.normals.checkpoint untouched; paths.data.survey.x stays')\n"
        "m.run_map = refuse\n"
        f"sys.argv = ['sss2bathy-map', 'files=x.xtf', 'hydra.run.dir={run_dir}']\n"
        "m.main()\n"
    )
    env = {**os.environ, "SSS2BATHY_ROOT": str(ROOT), "OMP_NUM_THREADS": "1"}
    env.pop("HYDRA_FULL_ERROR", None)
    proc = subprocess.run(
        [sys.executable, "-c", script],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert proc.returncode == USER_ERROR_EXIT, proc.stderr[-2000:]
    (line,) = stderr_lines(proc)
    assert line == (
        "error: config key 'survey.altitude_tolerance_m': expected the altimeter within 0.5 m "
        "of the bottom, found 3.2 m; holdout.fraction and cnn_checkpoint untouched; "
        "paths.data.survey.x stays"
    )
    assert not run_dir.exists()


def test_rename_keys_renames_whole_key_prefixes_only():
    aliases = {"data.survey.": "survey.", "data.normals.checkpoint": "cnn_checkpoint"}
    assert (
        rename_keys("data.survey.crs and 'data.survey.x'", aliases) == "survey.crs and 'survey.x'"
    )
    assert rename_keys("paths.data.survey.x", aliases) == "paths.data.survey.x"
    assert rename_keys("data.normals.checkpoint: none", aliases) == "cnn_checkpoint: none"
    assert rename_keys("data.survey.x", None) == "data.survey.x"


def test_full_disk_and_read_only_folders_are_one_line_naming_the_path(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    monkeypatch.delenv("SSS2BATHY_TRACE", raising=False)
    target = tmp_path / "out" / "map.tif"
    full = OSError(errno.ENOSPC, "No space left on device", str(target))
    text = os_error_message(full)
    assert text.startswith(f"{target}: no space left on its disk (") and " free there)" in text
    denied = PermissionError(errno.EACCES, "Permission denied", "/ro/data/survey")
    assert os_error_message(denied).startswith("/ro/data/survey: permission denied")
    unnamed = os_error_message(OSError(errno.ENOSPC, "No space left on device"), [tmp_path])
    assert (
        unnamed.startswith("no space left on the disk while writing (") and str(tmp_path) in unnamed
    )
    ro = OSError(errno.EROFS, "Read-only file system", "/mnt/ro/x")
    assert os_error_message(ro).startswith("/mnt/ro/x: read-only file system")

    for err, start in ((full, f"error: {target}: no space left"), (denied, "error: /ro/data")):

        @user_errors
        def write(err=err):
            raise err

        with pytest.raises(SystemExit) as done:
            write()
        assert done.value.code == USER_ERROR_EXIT
        (line,) = capsys.readouterr().err.splitlines()
        assert line.startswith(start)

    @user_errors
    def gdal_full(cfg):  # rasterio's error: no errno, GDAL's text names the file
        import rasterio.errors

        raise rasterio.errors.RasterioIOError(f"{target}: Write error: No space left on device")

    with pytest.raises(SystemExit):
        gdal_full(OmegaConf.create({"paths": {"data_dir": str(tmp_path)}}))
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"error: {target}: Write error: No space left on device (")
    assert f"free at {tmp_path}" in line

    @user_errors
    def broken_pipe():
        raise OSError(errno.EIO, "Input/output error")  # not the user's: keeps its trace

    with pytest.raises(OSError):
        broken_pipe()


def test_check_crs_keys_names_the_key():
    good = OmegaConf.create({"survey": {"crs": "EPSG:32633", "mbes_crs": None}})
    check_crs_keys(good)
    bad = OmegaConf.create({"data": {"survey": {"crs": "EPSG:32633", "mbes_crs": "nonsense"}}})
    with pytest.raises(ValueError, match=r"config key 'data.survey.mbes_crs': .*'nonsense'"):
        check_crs_keys(bad)


def test_config_goes_to_the_run_folder_not_the_console(tmp_path, caplog):
    cfg = OmegaConf.create({"extras": {"print_config": True}, "seed": 3})
    with caplog.at_level("INFO", logger="sss2bathy"):
        path = log_config(cfg, tmp_path)
    assert path == tmp_path / "config.yaml" and OmegaConf.load(path).seed == 3
    messages = [r.getMessage() for r in caplog.records if r.levelname == "INFO"]
    assert messages == [f"config: {path}"]
    assert log_config(OmegaConf.create({"extras": {"print_config": False}}), tmp_path) is None


def test_log_messages_spell_keys_as_the_entry_point_does(caplog):
    import logging

    logger = logging.getLogger("sss2bathy.test_rename")
    rename = RenameKeys({"data.survey.": "survey."})
    caplog.handler.addFilter(rename)
    try:
        with caplog.at_level(logging.WARNING):
            logger.warning("resampled to %d bins (data.survey.n_bins)", 512)
            logger.warning("paths.data.survey.x stays")
    finally:
        caplog.handler.removeFilter(rename)
    assert caplog.messages == ["resampled to 512 bins (survey.n_bins)", "paths.data.survey.x stays"]


def test_collapse_series_shortens_lettered_runs_only():
    """Runs of three or more names differing in a last letter read as one ``x_<a-l>``; shorter
    runs, gaps and other names stay as they are, in sorted order."""
    names = [f"synthetic_pretrain_{c}" for c in "abcdefghijkl"] + ["synthetic_pretrain_base"]
    assert collapse_series(names + ["xtf", "synthetic_d1"]) == [
        "synthetic_d1",
        "synthetic_pretrain_<a-l>",
        "synthetic_pretrain_base",
        "xtf",
    ]
    assert collapse_series(["s_a", "s_b", "s_d", "s_e", "s_f"]) == ["s_a", "s_b", "s_<d-f>"]
    assert collapse_series(["s_a", "s_b"]) == ["s_a", "s_b"]
    assert collapse_series([]) == []
