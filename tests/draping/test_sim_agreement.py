"""Draping agrees with the simulator's recorded ground truth (issue item 4).

The tiny synthetic_d1 survey is generated with a noise-free MBES grid (so the grid is
the terrain the simulator ray-traced) and draped; the simulator records per bin the
energy-weighted head-plane normal of its first-visible hits and its own mask.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from sss2bathy.draping import drape_survey
from sss2bathy.sim.prepare import prepare_synthetic
from sss2bathy.survey import MASK_VALID, Survey
from sss2bathy.utils.config import survey_preset

CONF = Path(__file__).resolve().parents[2] / "conf"


def _tiny_d1() -> dict:
    root = OmegaConf.create({"data": {"survey": survey_preset("synthetic_d1", "tiny", CONF)}})
    root.data.survey.terrain.mbes_noise_m = 0.0
    root.data.survey.name = "agreement_d1_tiny"
    return OmegaConf.to_container(root.data.survey, resolve=True)


def test_draped_n_lat_and_masks_match_simulator(tmp_path):
    folder = prepare_synthetic(_tiny_d1(), tmp_path)
    survey = Survey.load(folder)
    draped = drape_survey(survey, folder)
    errors, mask_same, n_bins = [], 0, 0
    for line in survey.lines:
        d = draped[line.name]
        true_mask = line.extras["true_mask"]
        both = (d.mask == MASK_VALID) & (true_mask == MASK_VALID)
        errors.append(np.abs(d.n_lat - line.extras["true_n_lat"])[both])
        mask_same += int(((d.mask == MASK_VALID) == (true_mask == MASK_VALID)).sum())
        n_bins += d.mask.size
    err = np.concatenate(errors)
    assert err.size > 1000
    assert np.mean(err < 0.01) >= 0.99
    assert mask_same / n_bins >= 0.98
