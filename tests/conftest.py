"""Project-wide test set-up: the project root for config paths, and single-threaded torch
(the suite runs on 2 cores; nested BLAS/OpenMP threads only oversubscribe them)."""

import os
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
os.environ.setdefault("SSS2BATHY_ROOT", str(ROOT))


@pytest.fixture(autouse=True, scope="session")
def _single_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
