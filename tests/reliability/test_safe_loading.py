"""Safe loading: checkpoints of every module hold only tensors and plain values and load
with ``weights_only=True``; a checkpoint carrying code is refused, its code never runs;
every ``torch.load`` / ``np.load`` in the package is a safe one.

A checkpoint that is truncated, not a checkpoint, or of the wrong kind (a CNN's as the
SIREN's ``ckpt_path``, a SIREN's as ``data.normals.checkpoint``) is one line naming the key, the
file and what it is, before any data is made; never torch's advice to load unsafely."""

from __future__ import annotations

import ast
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from reliability_helpers import ROOT, cnn_overrides, compose_run, siren_overrides

from sss2bathy.cli.train import train

PLAIN = (str, int, float, bool, type(None))


def _assert_plain(value, where: str) -> None:
    if isinstance(value, dict):
        for k, v in value.items():
            assert isinstance(k, str), f"{where}: key {k!r}"
            _assert_plain(v, f"{where}.{k}")
    elif isinstance(value, list | tuple):
        for i, v in enumerate(value):
            _assert_plain(v, f"{where}[{i}]")
    else:
        assert isinstance(value, PLAIN), f"{where}: {type(value).__name__}"


@pytest.mark.parametrize(
    "experiment", ["cnn", "siren_gt_n2d", "siren_direct_fit", "siren_lambert", "heights"]
)
def test_checkpoints_load_weights_only_with_plain_hparams(
    tmp_path, plane_survey, hills_survey, experiment
):
    if experiment == "cnn":
        overrides = cnn_overrides(hills_survey, tmp_path)
    else:
        overrides = siren_overrides(plane_survey, tmp_path) + [
            f"model.output_dir={tmp_path / 'map'}",
            "trainer.max_epochs=1",
        ]
        if experiment == "heights":
            overrides.append("model.sensor=null")
        else:
            overrides[0] = f"experiment={experiment}"
    run = tmp_path / "run"
    train(compose_run(overrides, run), run)
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    _assert_plain(ckpt["hyper_parameters"], "hyper_parameters")
    _assert_plain(ckpt.get("datamodule_hyper_parameters", {}), "datamodule_hyper_parameters")
    assert ckpt["state_dict"] and all(torch.is_tensor(v) for v in ckpt["state_dict"].values())
    assert {"NonFiniteGuard", "GlobalRNGState"} <= set(ckpt["callbacks"])


class _Payload:
    """Unpickling this runs code: it would create the marker file."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_a_checkpoint_with_code_is_refused_and_its_code_never_runs(tmp_path, plane_survey):
    marker = tmp_path / "pwned"
    evil = tmp_path / "evil.ckpt"
    torch.save({"state_dict": {}, "payload": _Payload(marker)}, evil)
    run = tmp_path / "run"
    cfg = compose_run(siren_overrides(plane_survey, tmp_path) + [f"ckpt_path={evil}"], run)
    with pytest.raises(ValueError, match="holds pickled Python objects") as err:
        train(cfg, run)
    assert str(err.value).startswith(f"ckpt_path: {evil} ")
    assert "weights_only" not in str(err.value)
    assert not marker.exists()


# ------------------------------------------------------------------ wrong or damaged files
@pytest.fixture(scope="module")
def kinds(tmp_path_factory, plane_survey, hills_survey) -> dict[str, Path]:
    """A checkpoint of each module kind, saved by the trainer of its real config (no fit)."""
    from sss2bathy.cli.train import instantiate_run

    tmp = tmp_path_factory.mktemp("kinds")
    overrides = {
        "CNN": cnn_overrides(hills_survey, tmp),
        "SIREN": siren_overrides(plane_survey, tmp),
        "Lambert": siren_overrides(plane_survey, tmp)[1:] + ["experiment=siren_lambert"],
    }
    paths = {}
    for kind, ovr in overrides.items():
        run = instantiate_run(compose_run(ovr, tmp / kind), tmp / kind)
        run.trainer.strategy.connect(run.model)
        paths[kind] = tmp / f"{kind}.ckpt"
        run.trainer.save_checkpoint(paths[kind])
    return paths


def _damaged(kinds: dict[str, Path], tmp: Path) -> dict[str, Path]:
    """Files that are no usable checkpoint, by what they are."""
    blob = kinds["CNN"].read_bytes()
    files = {
        "truncated": blob[: len(blob) // 3],  # a zip archive cut short (full disk)
        "random": np.random.default_rng(0).bytes(4096),
        "empty": b"",
        "pickle": pickle.dumps({"state_dict": {"net.w": [1.0]}}),
        "code pickle": pickle.dumps({"payload": _Payload(tmp / "pwned")}),
    }
    paths = {}
    for name, data in files.items():
        paths[name] = tmp / f"{name.replace(' ', '_')}.ckpt"
        paths[name].write_bytes(data)
    return paths


DAMAGE = {
    "truncated": "is truncated: a zip archive of",
    "random": "is not a checkpoint",
    "empty": "is an empty file",
    "pickle": "is a Python pickle, not a PyTorch checkpoint",
    "code pickle": "a Python pickle that holds Python objects besides tensors and plain "
    "values: refused unread",
}


def _assert_one_line(err: BaseException, key: str, path: Path, expected: str) -> None:
    text = str(err)
    assert "\n" not in text and text.startswith(f"{key}: {path} "), text
    assert expected in text, text
    assert "weights_only" not in text and "Traceback" not in text


@pytest.mark.parametrize("name", list(DAMAGE))
def test_a_damaged_or_foreign_file_is_one_line_naming_it_and_what_it_is(kinds, tmp_path, name):
    from sss2bathy.data.cnn_normals import load_normal_net
    from sss2bathy.utils.checkpoints import read_checkpoint

    path = _damaged(kinds, tmp_path)[name]
    with pytest.raises(ValueError) as err:
        read_checkpoint(path, "ckpt_path")
    _assert_one_line(err.value, "ckpt_path", path, DAMAGE[name])
    with pytest.raises(ValueError) as err:  # the SIREN-CNN stage's and predict's loader
        load_normal_net(path)
    _assert_one_line(err.value, "cnn_checkpoint", path, DAMAGE[name])
    assert not (tmp_path / "pwned").exists()


def test_checkpoint_kinds_are_told_apart(kinds):
    from sss2bathy.utils.checkpoints import checkpoint_kind, read_checkpoint

    assert {k: checkpoint_kind(read_checkpoint(p, "x")) for k, p in kinds.items()} == {
        "CNN": "CNN",
        "SIREN": "SIREN",
        "Lambert": "Lambert",
    }


@pytest.mark.parametrize(
    "given, experiment, key, expected",
    [
        ("CNN", "siren_gt_n2d", "ckpt_path", "is a CNN checkpoint (NormalCNNModule"),
        ("Lambert", "siren_gt_n2d", "ckpt_path", "is a Lambert checkpoint"),
        ("SIREN", "cnn", "ckpt_path", "is a SIREN checkpoint"),
        ("SIREN", "siren_cnn_n2d", "data.normals.checkpoint", "is a SIREN checkpoint"),
        ("Lambert", "siren_cnn_n2d", "data.normals.checkpoint", "is a Lambert checkpoint"),
        ("truncated", "siren_gt_n2d", "ckpt_path", DAMAGE["truncated"]),
        ("truncated", "siren_cnn_n2d", "data.normals.checkpoint", DAMAGE["truncated"]),
        ("random", "siren_cnn_n2d", "data.normals.checkpoint", DAMAGE["random"]),
        ("code pickle", "siren_cnn_n2d", "data.normals.checkpoint", DAMAGE["code pickle"]),
    ],
)
def test_a_wrong_checkpoint_stops_the_run_before_any_data_is_made(
    tmp_path, plane_survey, hills_survey, kinds, given, experiment, key, expected
):
    path = kinds.get(given) or _damaged(kinds, tmp_path)[given]
    data = tmp_path / "data"
    if experiment == "cnn":
        overrides = cnn_overrides(hills_survey, data)
    else:
        overrides = siren_overrides(plane_survey, data)
        overrides[0] = f"experiment={experiment}"
    setting = f"{key}={path}" if key == "ckpt_path" else f"data.normals.checkpoint={path}"
    run = tmp_path / "run"
    with pytest.raises(ValueError) as err:
        train(compose_run(overrides + [setting], run), run)
    _assert_one_line(err.value, key, path, expected)
    if given in kinds:  # says where a checkpoint of that kind belongs
        assert ("data.normals.checkpoint" if given == "CNN" else "ckpt_path of") in str(err.value)
    assert not data.exists()  # failed before the data module made anything


def test_a_truncated_last_ckpt_stops_ckpt_path_last_in_one_line(tmp_path, plane_survey, kinds):
    run = tmp_path / "run"
    last = run / "checkpoints" / "last.ckpt"
    last.parent.mkdir(parents=True)
    blob = kinds["SIREN"].read_bytes()
    last.write_bytes(blob[: len(blob) // 3])
    cfg = compose_run(siren_overrides(plane_survey, tmp_path) + ["ckpt_path=last"], run)
    with pytest.raises(ValueError) as err:
        train(cfg, run)
    _assert_one_line(err.value, "ckpt_path", last, DAMAGE["truncated"])


@pytest.mark.slow
def test_cli_wrong_checkpoints_are_one_stderr_line_and_exit_2(tmp_path, plane_survey, kinds):
    env = {**os.environ, "SSS2BATHY_ROOT": str(ROOT), "OMP_NUM_THREADS": "1"}
    env.pop("HYDRA_FULL_ERROR", None)
    base = siren_overrides(plane_survey, tmp_path / "data")
    truncated = _damaged(kinds, tmp_path)["truncated"]
    cases = [
        ([f"ckpt_path={kinds['CNN']}"], f"error: ckpt_path: {kinds['CNN']} is a CNN checkpoint"),
        (
            ["experiment=siren_cnn_n2d", f"data.normals.checkpoint={truncated}"],
            f"error: data.normals.checkpoint: {truncated} is truncated",
        ),
    ]
    for extra, start in cases:
        args = base[1:] + (extra if extra[0].startswith("experiment") else [base[0], *extra])
        proc = subprocess.run(
            [sys.executable, "-m", "sss2bathy.cli.train", *args, f"hydra.run.dir={tmp_path / 'o'}"],
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert proc.returncode == 2, proc.stderr[-2000:]
        lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith(start), lines
        assert "Traceback" not in proc.stdout + proc.stderr


def _calls(name: str) -> list[tuple[Path, ast.Call]]:
    found = []
    for path in sorted((ROOT / "sss2bathy").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and ast.unparse(node.func) == name:
                found.append((path, node))
    return found


def _keyword(call: ast.Call, name: str):
    for kw in call.keywords:
        if kw.arg == name:
            return ast.literal_eval(kw.value)
    return None


def test_every_load_in_the_package_is_safe():
    torch_loads = _calls("torch.load")
    np_loads = _calls("np.load")
    assert torch_loads and np_loads
    for path, call in torch_loads:
        assert _keyword(call, "weights_only") is True, f"{path}:{call.lineno}"
    for path, call in np_loads:
        assert _keyword(call, "allow_pickle") is False, f"{path}:{call.lineno}"
    assert not _calls("pickle.load") and not _calls("pickle.loads")
