"""Training the normal CNN on several surveys at once (SidescanWindowDataModule with
train_surveys / val_surveys / overlap_bins), on small built surveys."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from sss2bathy.data.windows import SidescanWindowDataModule, line_windows, union_envelopes
from sss2bathy.survey import Survey
from tests.data.test_windows import _hilly_grid, _line


def _wide_line(name: str, x: float, n_bins: int, r_max: float):
    line = _line(name, x, n_bins=n_bins)
    return dataclasses.replace(line, range_m=np.linspace(0.4, r_max, n_bins))


def _survey(root: Path, name: str, n_train: int, n_bins: int, r_max: float) -> dict:
    lines = [_wide_line(f"t{i}", -12.0 + 8.0 * i, n_bins, r_max) for i in range(n_train)]
    lines.append(_wide_line("test0", 2.0, n_bins, r_max))
    splits = {"train": [f"t{i}" for i in range(n_train)], "test": ["test0"]}
    folder = Survey(name, lines, _hilly_grid(), splits).save(root / name)
    return {"kind": "folder", "path": str(folder)}


@pytest.fixture(scope="module")
def surveys(tmp_path_factory) -> dict[str, dict]:
    root = tmp_path_factory.mktemp("pooled")
    return {
        "main": _survey(root, "main", 2, 64, 25.0),
        "a": _survey(root, "a", 2, 64, 25.0),
        "b": _survey(root, "b", 3, 128, 30.0),
        "val": _survey(root, "val", 1, 64, 25.0),
    }


def test_bin_overlap_of_its_own():
    o = line_windows(40, 128, 16, 64, overlap=0.75, overlap_bins=0.5)
    assert sorted(set(o[:, 1].tolist())) == [0, 32, 64]
    assert sorted(set(line_windows(40, 128, 16, 64, 0.75)[:, 1].tolist())) == [0, 16, 32, 48, 64]


def test_training_lines_pooled_from_several_surveys(surveys, tmp_path):
    dm = SidescanWindowDataModule(
        survey=surveys["main"],
        data_dir=str(tmp_path),
        window_pings=16,
        window_bins=64,
        overlap_bins=0.5,
        batch_size=4,
        train_surveys=[surveys["a"], surveys["b"]],
        val_surveys=[surveys["val"]],
        test_surveys=[surveys["b"]],
        seed=3,
    )
    dm.prepare_data()
    dm.setup("fit")
    # every training line of both surveys, none of the main survey's, named by survey
    assert dm.train_lines == ["a/t0", "a/t1", "b/t0", "b/t1", "b/t2"]
    assert dm.val_lines == ["val/t0", "val/test0"]
    assert dm.train_set.line_names == dm.train_lines
    # 128-bin lines give three 64-bin windows across each side (overlap_bins 0.5)
    b_rows = dm.train_set.index[dm.train_set.index[:, 0] >= 2]
    assert sorted(set(b_rows[:, 3].tolist())) == [0, 32, 64]
    batch = next(iter(dm.train_dataloader()))
    assert tuple(batch["inputs"].shape) == (4, 1, 16, 64)
    # the sonar envelope spans both training surveys
    env = dm.sonar_envelope
    assert env["survey"] == "a+b" and env["n_lines"] == 5
    assert env["settings"]["max_range_m"] == pytest.approx([25.0, 30.0])
    lo, hi = env["settings"]["bin_m"]
    assert lo == pytest.approx(29.6 / 127) and hi == pytest.approx(24.6 / 63)
    dm.setup("test")
    assert dm.test_set_names == ["main:test", "b:all"]
    assert dm.test_sets[0].line_names == ["test0"]


def test_pooled_without_val_surveys_carves_validation_lines(surveys, tmp_path):
    dm = SidescanWindowDataModule(
        survey=surveys["main"],
        data_dir=str(tmp_path),
        window_pings=16,
        window_bins=64,
        val_fraction=0.25,
        train_surveys=[surveys["a"], surveys["b"]],
        seed=0,
    )
    dm.setup("fit")
    assert len(dm.val_lines) == 1 and len(dm.train_lines) == 4
    assert set(dm.val_lines + dm.train_lines) == {"a/t0", "a/t1", "b/t0", "b/t1", "b/t2"}


def test_pooled_errors(surveys, tmp_path):
    with pytest.raises(ValueError, match="data.n_train_lines: expected null"):
        SidescanWindowDataModule(
            survey=surveys["main"], data_dir=str(tmp_path), train_surveys=[surveys["a"]],
            n_train_lines=2,
        )  # fmt: skip
    with pytest.raises(ValueError, match=r"data.train_surveys\[0\]"):
        SidescanWindowDataModule(
            survey=surveys["main"], data_dir=str(tmp_path), train_surveys=[{"path": "x"}]
        )
    dm = SidescanWindowDataModule(
        survey=surveys["main"], data_dir=str(tmp_path), window_pings=16, window_bins=64,
        train_surveys=[surveys["a"], surveys["a"]], val_surveys=[surveys["val"]],
    )  # fmt: skip
    with pytest.raises(ValueError, match="distinct names"):
        dm.setup("fit")
    with pytest.raises(ValueError, match="at least one"):
        union_envelopes([])


def test_surveys_prepared_side_by_side_as_one_after_another(tmp_path):
    """prepare_jobs > 1 drapes each survey in its own (spawned) process: the same windows."""
    sets = {"main": (2, 64, 25.0), "a": (2, 64, 25.0), "b": (3, 128, 30.0)}
    batches = []
    for jobs in (1, 3):
        root = tmp_path / f"jobs{jobs}"
        surveys = {k: _survey(root, k, *v) for k, v in sets.items()}
        dm = SidescanWindowDataModule(
            survey=surveys["main"], data_dir=str(root), window_pings=16, window_bins=64,
            batch_size=4, train_surveys=[surveys["a"], surveys["b"]], seed=3,
            prepare_jobs=jobs,
        )  # fmt: skip
        dm.prepare_data()
        # the drapes are cached in every survey's folder before setup reads them
        assert all(any((Path(s["path"]) / "draped").glob("*")) for s in surveys.values())
        dm.setup("fit")
        batches.append(dm.train_set[0]["inputs"].numpy())
    np.testing.assert_array_equal(*batches)
    with pytest.raises(ValueError, match="prepare_jobs"):
        SidescanWindowDataModule(survey={"kind": "folder", "path": "x"},
                                 data_dir=str(tmp_path), prepare_jobs=0)  # fmt: skip
