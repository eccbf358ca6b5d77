"""The model card is written from an exported model's JSON and metrics files alone."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sss2bathy.data.cnn_model_file import write_model
from sss2bathy.models.normal_cnn import NormalResNet
from studies.model_card import main, site_rows, sonar_rows, write_card

ENVELOPE = {
    "version": 1,
    "survey": "pool",
    "n_lines": 12,
    "settings": {
        "frequency_hz": [400e3, 900e3],
        "max_range_m": [20.0, 50.0],
        "bin_m": [0.04, 0.2],
        "tilt_deg": [15.0, 35.0],
        "beam_width_deg": [40.0, 70.0],
        "altitude_m": [3.0, 15.0],
    },
}


def make_model(folder: Path) -> Path:
    """A width-2 network exported with the metadata a training run gives it."""
    net = NormalResNet(in_channels=3, base_width=2, n_blocks=1)
    meta = {
        "network": net.config(),
        "input_channels": ["intensity", "grazing", "range"],
        "sonar_mask": {"shadow_threshold": 0.15},
        "windows": {"window_pings": 64, "window_bins": 256, "overlap": 0.5, "batch_size": 16},
        "sonar_envelope": ENVELOPE,
        "training": {
            "source_checkpoint": "epoch_0007.ckpt",
            "source_sha256": "ab" * 32,
            "epoch": 7,
            "global_step": 800,
            "command": "sss2bathy-train experiment=pretrain scale=demo",
            "loss": {"kind": "l1", "lowpass_weight": 1.0},
            "optimizer": {"name": "torch.optim.adam.Adam", "lr": 5e-4},
            "data": {
                "batch_size": 16,
                "train_surveys": [
                    {"name": "synthetic_pretrain_a_demo", "kind": "synthetic"},
                    {"name": "synthetic_pretrain_b_demo", "kind": "synthetic"},
                ],
            },
            "config": {"seed": 42, "scale": {"name": "demo"}, "trainer": {"max_epochs": 8}},
            "run_info": {"git_revision": "abc123"},
        },
        "metrics": {
            "values": {
                "val/nlat_mae": 0.041,
                "test/synthetic_d2_demo:all/nlat_mae": 0.03,
                "test/synthetic_d2_demo:all/constant/nlat_mae": 0.06,
            }
        },
        "software": {"sss2bathy": "0.1.0", "torch": "2.x"},
    }
    weights, _ = write_model(net.state_dict(), meta, folder, "pool_cnn")
    return weights


def test_the_card_says_what_the_json_and_the_metrics_say(tmp_path):
    weights = make_model(tmp_path / "m")
    extra = tmp_path / "eval.json"
    extra.write_text(
        json.dumps(
            {
                "test/synthetic_d1_site2_demo:all/nlat_mae": 0.05,
                "test/synthetic_d1_site2_demo:all/constant/nlat_mae": 0.08,
                "test/synthetic_d2_demo:all/nlat_mae": 0.024,  # wins over the model's own
                "test/x/nlat_rmse": float("nan"),
                "note": "text is skipped",
            }
        )
    )
    section = tmp_path / "siren.md"
    section.write_text("## SIREN-CNN-N2d maps\n\n| site | MAE |\n|---|---|\n| d1 | 0.2 |\n")
    out = write_card(weights, tmp_path / "card.md", [extra], [section])
    text = out.read_text()
    meta = json.loads(weights.with_suffix(".json").read_text())
    assert meta["weights"]["sha256"] in text
    assert "`NormalResNet(in_channels=3, base_width=2, n_blocks=1," in text
    assert "intensity, grazing, range" in text and "64 pings × 256 bins, overlap 0.5" in text
    assert "Command: `sss2bathy-train experiment=pretrain scale=demo`" in text
    assert "`synthetic_pretrain_a_demo`, `synthetic_pretrain_b_demo`" in text
    assert "| epochs | 8 |" in text and "| training lines (sonar envelope) | 12 |" in text
    assert "| frequency | 400 – 900 kHz | ±10 % of the bound |" in text
    assert "| tilt (depression of the beam axis) | 15 – 35 ° | ±5 ° |" in text
    # one row per data set: d2 from the metrics file (0.024 / 0.06 = 0.40), site2 added
    assert "| `synthetic_d2_demo:all` | 0.0240 | 0.0600 | 0.40 |" in text
    assert "| `synthetic_d1_site2_demo:all` | 0.0500 | 0.0800 | 0.62 |" in text
    assert "| validation lines | 0.0410 |" in text
    assert text.rstrip().endswith("| d1 | 0.2 |") and f"<!-- from {section} -->" in text
    assert "--metrics eval.json" in text.splitlines()[2]


def test_pure_parts():
    assert site_rows({}) == [] and sonar_rows(None) == []
    rows = site_rows({"test/a/nlat_mae": 0.1, "test/a/constant/nlat_mae": 0.2})
    assert rows == [["`a`", "0.1000", "0.2000", "0.50", "", ""]]
    assert [r[0] for r in sonar_rows(ENVELOPE)][:2] == ["frequency", "range (last bin)"]


def test_a_changed_weights_file_or_a_bad_input_is_refused(tmp_path, capsys):
    weights = make_model(tmp_path / "m")
    with pytest.raises(SystemExit):
        main(["--model", str(weights), "--out", str(tmp_path / "c.md"), "--section", "nope.md"])
    assert "--section: expected a Markdown file" in capsys.readouterr().err
    weights.write_bytes(weights.read_bytes()[:-1] + b"\x00")
    with pytest.raises(SystemExit):
        main(["--model", str(weights), "--out", str(tmp_path / "c.md")])
    assert "weights.sha256: expected" in capsys.readouterr().err
    assert not (tmp_path / "c.md").exists()
