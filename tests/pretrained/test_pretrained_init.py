"""model.init: a CNN fit that starts from trained weights, refused in one line when the
network or the input channels differ."""

from __future__ import annotations

from functools import partial

import pytest
import torch

from sss2bathy.data import cnn_normals
from sss2bathy.data.cnn_normals import load_normal_net
from sss2bathy.losses import NormalLoss
from sss2bathy.models.normal_cnn import NormalResNet
from sss2bathy.modules.cnn_parts import sonar_mask_mismatch
from sss2bathy.modules.normal_cnn import NormalCNNModule


def _module(init, channels=None, **net):
    torch.manual_seed(123)
    return NormalCNNModule(
        net=partial(NormalResNet, **{"base_width": 2, "n_blocks": 1, **net}),
        loss=NormalLoss(),
        optimizer=partial(torch.optim.Adam, lr=1e-3),
        image_every_n_epochs=0,
        input_channels=channels,
        init=init,
    )


@pytest.mark.parametrize("source", ["ckpt", "exported"])
def test_init_loads_the_trained_weights(tiny_run, exported, source):
    path = tiny_run[0] if source == "ckpt" else exported
    module = _module(str(path))
    trained = load_normal_net(path)
    for (name, ours), theirs in zip(
        module.net.state_dict().items(), trained.state_dict().values(), strict=True
    ):
        assert torch.equal(ours, theirs), name
    fresh = next(iter(_module(None).net.parameters()))
    assert not torch.equal(fresh, next(iter(module.net.parameters())))  # not the random start
    record = module.hparams["init"]
    assert record["path"] == str(path) and len(record["sha256"]) == 64
    assert _module(None).hparams["init"] is None


def test_init_pretrained_is_the_shipped_model(exported, tmp_path, monkeypatch):
    monkeypatch.setattr(cnn_normals, "PRETRAINED_DIR", tmp_path / "none")
    with pytest.raises(ValueError, match="model.init: expected 'pretrained' to name the CNN"):
        _module("pretrained")


@pytest.mark.parametrize(
    ("kw", "message"),
    [
        ({"base_width": 4}, r"model.init: expected this run's network .* base_width=4 \(file: 2\)"),
        ({"n_blocks": 2, "dilation": 2}, r"dilation=2 \(file: 1\), n_blocks=2 \(file: 1\)"),
        (
            {"channels": ["intensity", "range"]},
            r"trained on input channels \['intensity'\], expected this run's "
            r"\['intensity', 'range'\]",
        ),
    ],
)
def test_a_different_network_or_input_is_refused_in_one_line(exported, kw, message):
    channels = kw.pop("channels", None)
    with pytest.raises(ValueError, match=message) as err:
        _module(str(exported), channels, **kw)
    assert "\n" not in str(err.value) and str(exported) in str(err.value)


def test_init_refuses_a_file_that_is_no_cnn(tmp_path):
    text = tmp_path / "x.ckpt"
    text.write_text("no")
    with pytest.raises(ValueError, match=f"model.init: {text} is not a checkpoint"):
        _module(str(text))
    with pytest.raises(FileNotFoundError, match="model.init: expected a CNN checkpoint"):
        _module(str(tmp_path / "missing.safetensors"))


def test_a_data_sonar_mask_other_than_the_weights_is_named(caplog):
    record = {"path": "m.safetensors", "sonar_mask": {"shadow_threshold": 0.15}}
    assert sonar_mask_mismatch(record, {"shadow_threshold": 0.15}) is None
    assert sonar_mask_mismatch(None, {"shadow_threshold": 0.3}) is None
    text = sonar_mask_mismatch(record, {"shadow_threshold": 0.3})
    assert text is not None and "shadow_threshold=0.3 (weights: 0.15)" in text
