"""Atomic writes: files get the mode the umask gives a plain ``open()``, not mkstemp's 0600."""

import os
import stat

import numpy as np
import pytest

from sss2bathy.survey import BathyGrid
from sss2bathy.utils.atomic import (
    atomic_path,
    atomic_write_text,
    current_umask,
    default_dir_mode,
    default_file_mode,
)


@pytest.fixture
def umask():
    """Set the process umask for one test; restored afterwards."""
    saved = os.umask(0o022)
    os.umask(saved)
    yield lambda mask: os.umask(mask)
    os.umask(saved)


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.mark.parametrize(("mask", "expected"), [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_atomic_files_follow_the_umask(tmp_path, umask, mask, expected):
    umask(mask)
    assert current_umask() == mask
    assert default_file_mode() == expected
    assert default_dir_mode() == 0o777 & ~mask
    atomic_write_text(tmp_path / "a.txt", "x")
    assert _mode(tmp_path / "a.txt") == expected
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    assert _mode(tmp_path / "a.txt") == _mode(plain)
    BathyGrid(np.zeros((3, 3)), 0.0, 0.0, 1.0).save_geotiff(tmp_path / "g.tif")
    assert _mode(tmp_path / "g.tif") == expected


def test_failed_atomic_write_leaves_nothing(tmp_path):
    target = tmp_path / "keep.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("new")
        raise RuntimeError("boom")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt"]
