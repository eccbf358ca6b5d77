"""experiment=pretrain: twelve training seabeds (six recipes, two seabeds each), validation on the validation site, every scored
survey unseen; the low-pass loss term stays off for the other experiments."""

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

CONF = Path(__file__).resolve().parents[2] / "conf"


def _data(*overrides: str) -> dict:
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=["logger=none", *overrides])
    data = OmegaConf.to_container(cfg.data, resolve=True)
    model = OmegaConf.to_container(cfg.model, resolve=False)
    return {"data": data, "loss": OmegaConf.to_container(cfg.model.loss, resolve=True),
            "model": model, "task": cfg.task_name}  # fmt: skip


@pytest.mark.parametrize("scale", ["tiny", "demo"])
def test_pretrain_trains_on_twelve_unseen_seabeds(scale):
    c = _data("experiment=pretrain", f"scale={scale}")
    data = c["data"]
    assert c["task"] == "pretrain"
    train = data["train_surveys"]
    names = [s["name"] for s in train]
    assert names == [f"synthetic_pretrain_{k}_{scale}" for k in "abcdefghijkl"]
    # every seabed its own seed; g-l repeat a-f's recipes and sonars on other seabeds
    assert len({s["seed"] for s in train}) == 12
    for first, second in zip(train[:6], train[6:], strict=True):
        assert first["sonar"] == second["sonar"] and first["terrain"] == second["terrain"]
    assert all(s["randomize"]["enabled"] for s in train)
    assert [s["name"] for s in data["val_surveys"]] == [f"synthetic_d1_valsite_{scale}"]
    scored = [data["survey"], *data["test_surveys"], *data["val_surveys"]]
    assert {s["name"] for s in scored} >= {f"synthetic_d1_site2_{scale}", f"synthetic_d2_{scale}"}
    # no training seabed shares a seed with a scored one
    assert not {s["seed"] for s in train} & {s["seed"] for s in scored}
    # the sonars span 20-50 m, 256 and 512 bins, 400-900 kHz
    assert {s["sonar"]["n_bins"] for s in train} == {256, 512}
    assert {s["sonar"]["max_range_m"] for s in train} == {20.0, 30.0, 40.0, 50.0}
    assert (
        min(s["sonar"]["frequency_khz"] for s in train)
        <= 600
        <= max(s["sonar"]["frequency_khz"] for s in train)
    )
    assert data["input_channels"] == ["intensity", "grazing", "range"]
    # demo: plain l1 (lever A of docs/studies/cnn_levers.md); tiny keeps the term exercised
    assert c["loss"]["lowpass_weight"] == {"tiny": 1.0, "demo": 0.0}[scale]


def test_the_low_pass_term_is_off_for_the_demo_cnn():
    c = _data("experiment=cnn", "scale=demo")
    assert c["loss"]["lowpass_weight"] == 0.0
    assert c["data"]["train_surveys"] is None and c["data"]["val_surveys"] is None
