"""conf/scale/<scale>.yaml holds every size of a scale: the SIREN fit, the CNN and the
synthetic surveys. A survey section only sizes keys its preset reads from it, so a typo'd
or unread key fails here instead of being silently ignored."""

from pathlib import Path

import pytest
from omegaconf import OmegaConf

from sss2bathy.utils.config import scale_config, survey_preset

CONF = Path(__file__).resolve().parents[2] / "conf"
SCALES = sorted(p.stem for p in (CONF / "scale").glob("*.yaml"))


def _leaves(node, prefix=""):
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _leaves(v, f"{prefix}.{k}" if prefix else str(k))
    else:
        yield prefix, node


def test_scales_exist_and_carry_every_stage():
    assert {"tiny", "demo", "paper"} <= set(SCALES)
    for scale in SCALES:
        cfg = scale_config(scale, CONF)
        assert cfg["name"] == scale
        assert {"siren", "cnn", "survey"} <= set(cfg), scale


@pytest.mark.parametrize("scale", SCALES)
def test_every_sized_key_is_read_by_its_preset(scale):
    for preset, sizes in scale_config(scale, CONF)["survey"].items():
        # a section is read by its preset, or by the base a family of presets shares
        # (synthetic_pretrain_base.yaml for the pretraining seabeds a-f)
        candidates = [CONF / "data" / "survey" / f"{preset}{s}.yaml" for s in ("", "_base")]
        path = next((p for p in candidates if p.is_file()), candidates[0])
        assert path.is_file(), f"scale/{scale}.yaml survey.{preset}: no preset {path}"
        raw = OmegaConf.load(path)
        for key, _ in _leaves(sizes):
            node = OmegaConf.to_container(raw, resolve=False)
            for part in key.split("."):
                assert isinstance(node, dict) and part in node, (
                    f"scale/{scale}.yaml survey.{preset}.{key}: the preset has no key {key}"
                )
                node = node[part]
            wanted = f"${{oc.select:scale.survey.{preset}.{key},"
            assert isinstance(node, str) and node.startswith(wanted), (
                f"scale/{scale}.yaml survey.{preset}.{key}: the preset's {key} must read it "
                f"({wanted}<paper value>}}), found {node!r}"
            )


def test_sized_preset_takes_the_scale_values():
    tiny = survey_preset("synthetic_d1", "tiny", CONF)
    paper = survey_preset("synthetic_d1", "paper", CONF)
    assert tiny["name"] == "synthetic_d1_tiny" and tiny["sonar"]["n_bins"] == 64
    assert tiny["terrain"]["size_m"] == [50.0, 40.0]
    assert paper["sonar"]["n_bins"] == 512 and paper["plan"]["n_train"] == 45
    # unsized keys are the preset's at every scale
    assert tiny["terrain"]["cell_m"] == paper["terrain"]["cell_m"] == 0.5


def test_unknown_scale_or_survey_is_one_clear_error():
    with pytest.raises(ValueError, match=r"scale: expected one of \[.*'tiny'.*found 'huge'"):
        scale_config("huge", CONF)
    with pytest.raises(ValueError, match=r"survey: expected one of \[.*found 'nowhere'"):
        survey_preset("nowhere", "tiny", CONF)
