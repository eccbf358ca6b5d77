"""Project-wide test set-up: the project root for config paths, and single-threaded torch
(the suite runs on 2 cores; nested BLAS/OpenMP threads only oversubscribe them)."""

import os
from pathlib import Path

import pytest
import torch
from hypothesis import settings

ROOT = Path(__file__).resolve().parents[1]
os.environ.setdefault("SSS2BATHY_ROOT", str(ROOT))

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
