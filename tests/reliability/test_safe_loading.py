"""Safe loading: checkpoints of every module hold only tensors and plain values and load
with ``weights_only=True``; a checkpoint carrying code is refused, its code never runs;
every ``torch.load`` / ``np.load`` in the package is a safe one."""

from __future__ import annotations

import ast
import pickle
from pathlib import Path

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
    with pytest.raises(pickle.UnpicklingError, match="Weights only load failed"):
        train(cfg, run)
    assert not marker.exists()


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
