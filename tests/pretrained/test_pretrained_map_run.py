"""sss2bathy-map end to end with an exported CNN (.safetensors) on a tiny XTF survey (slow)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[2]


def _run(module: str, args: list[str], tmp: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, SSS2BATHY_ROOT=str(ROOT), OMP_NUM_THREADS="1", HYDRA_FULL_ERROR="1")
    return subprocess.run(
        [sys.executable, "-m", module, *args],
        cwd=tmp, env=env, capture_output=True, text=True, timeout=900,
    )  # fmt: skip


@pytest.mark.slow
def test_sss2bathy_map_with_an_exported_cnn(tmp_path):
    from sss2bathy.io.xtf import write_xtf
    from sss2bathy.pretrained import export_checkpoint
    from sss2bathy.sim import config as sim_config
    from sss2bathy.sim import generate
    from sss2bathy.utils.config import survey_preset

    cfg = OmegaConf.create(survey_preset("synthetic_d1", "tiny", ROOT / "conf"))
    cfg.name = "sim_tiny"
    survey, _ = generate.generate_survey(
        sim_config.SyntheticSurveyConfig.from_mapping(OmegaConf.to_container(cfg))
    )
    lines = tmp_path / "lines"
    for line in survey.split_lines("test"):
        write_xtf(line, lines / f"{line.name}.xtf", survey.origin)
    common = [
        f"paths.data_dir={tmp_path / 'data'}", f"paths.output_dir={tmp_path / 'outputs'}",
        "scale=tiny", "logger=none", "torch_threads=1",
    ]  # fmt: skip
    cnn = tmp_path / "cnn"
    proc = _run(
        "sss2bathy.cli.train",
        ["experiment=cnn", "trainer.enable_progress_bar=false", "data.test_surveys=[]",
         f"hydra.run.dir={cnn}", *common],
        tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    weights, _ = export_checkpoint(cnn / "checkpoints" / "last.ckpt", tmp_path / "m", "m")
    run = tmp_path / "run"
    proc = _run(
        "sss2bathy.cli.map",
        [f"files={lines}", "method=siren_cnn_n2d", f"cnn_checkpoint={weights}",
         f"survey.crs={survey.origin['crs']}", "survey.n_bins=null", "holdout.block_pings=10",
         "verdict.folds=0", "mosaic.placement=none", f"hydra.run.dir={run}",
         'overrides=["callbacks=none","trainer.enable_progress_bar=false"]', *common],
        tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "siren_cnn_n2d" in proc.stdout
    metrics = json.loads((run / "metrics.json").read_text())
    assert np.isfinite(metrics["final/holdout_alt_mae"]) and (run / "map.tif").is_file()
    # the simulator's sonar is the one the CNN was trained on; the test lines fly lower and
    # higher than its one training line: one WARNING, naming the exported file and only that
    warned = [ln for ln in (proc.stderr + proc.stdout).splitlines() if "was trained on" in ln]
    assert len(warned) == 1, warned
    assert f"the CNN checkpoint {weights} was trained on 850 kHz" in warned[0]
    assert "altitude (outside): 1 setting(s) outside" in warned[0]
    # the cached predictions are the exported model's
    assert any((tmp_path / "data").glob("*/predictions/*/*.npz"))
