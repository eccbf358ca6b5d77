"""Project-wide test set-up: the project root for config paths, and single-threaded torch
(the suite runs on 2 cores; nested BLAS/OpenMP threads only oversubscribe them)."""

import os
from pathlib import Path

import pytest
import torch
from hypothesis import settings

ROOT = Path(__file__).resolve().parents[1]
os.environ.setdefault("SSS2BATHY_ROOT", str(ROOT))
# The small real files some tests and presets read (grids, an AUV sidescan line): beside the
# repository in ../shared/realdata, or wherever SSS2BATHY_REALDATA points. A clone without
# them skips those tests with one line saying what is missing.
REALDATA = Path(os.environ.get("SSS2BATHY_REALDATA", ROOT.parent / "shared" / "realdata"))


def skip_unless_real_file(path) -> Path:
    """``path`` as a ``Path``; skips the calling test with one line when it is missing."""
    path = Path(str(path))
    if not path.is_file():
        pytest.skip(
            f"real data file {path} is missing: put the shared real data in "
            f"../shared/realdata beside the repository or set SSS2BATHY_REALDATA=FOLDER"
        )
    return path


def skip_unless_survey_files(cfg) -> None:
    """Skips the calling test when a composed config's survey reads a real grid that is
    missing (``data.survey.terrain.grid`` of the presets over real seabed)."""
    from omegaconf import OmegaConf

    grid = OmegaConf.select(cfg, "data.survey.terrain.grid", default=None)
    if grid is not None:
        skip_unless_real_file(grid)


# Property tests draw the same examples on every run (CI must not fail at random); set
# HYPOTHESIS_PROFILE=explore for fresh random examples.
settings.register_profile("default", derandomize=True, print_blob=True)
settings.register_profile("explore", derandomize=False, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))


@pytest.fixture(autouse=True, scope="session")
def _single_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
