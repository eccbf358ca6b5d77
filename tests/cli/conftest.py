"""Fixtures of the CLI tests: the simulator's tiny lines written as XTF files."""

from __future__ import annotations

from pathlib import Path

import pytest
from omegaconf import OmegaConf

CONF = Path(__file__).resolve().parents[2] / "conf"


@pytest.fixture(scope="module")
def tiny_xtf(tmp_path_factory) -> tuple[Path, str]:
    """The simulator's tiny test lines (57 and 43 pings) written as XTF files."""
    from sss2bathy.io.xtf import write_xtf
    from sss2bathy.sim import config as sim_config
    from sss2bathy.sim import generate
    from sss2bathy.utils.config import survey_preset

    cfg = OmegaConf.create(survey_preset("synthetic_d1", "tiny", CONF))
    cfg.name = "sim_tiny"
    survey, _ = generate.generate_survey(
        sim_config.SyntheticSurveyConfig.from_mapping(OmegaConf.to_container(cfg))
    )
    folder = tmp_path_factory.mktemp("xtf") / "lines"
    for line in survey.split_lines("test"):
        write_xtf(line, folder / f"{line.name}.xtf", survey.origin)
    return folder, survey.origin["crs"]
