"""Survey caches (synthetic and imported XTF) carry a digest of their files: a truncated
or altered file is detected and the survey rebuilt with a warning; an intact folder is
reused; a folder from before digests is verified by loading it and gets its digest."""

from __future__ import annotations

import importlib.util
import json
import logging

import pytest
from reliability_helpers import ROOT

import sss2bathy.sim.generate as generate_module
from sss2bathy.io.xtf import write_xtf
from sss2bathy.io.xtf_survey import prepare_xtf_survey
from sss2bathy.sim.prepare import prepare_synthetic
from sss2bathy.survey import Survey
from sss2bathy.utils.atomic import FOLDER_DIGEST, folder_digest_problems, write_folder_digest


def _module(name: str, rel: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / rel)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_folder_digest_detects_truncation_alteration_and_loss(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "a.bin").write_bytes(b"0123456789")
    (tmp_path / "sub" / "b.bin").write_bytes(b"abc")
    (tmp_path / ".tmp-x").write_bytes(b"ignored")
    assert folder_digest_problems(tmp_path) is None  # no digest yet
    digest = write_folder_digest(tmp_path)
    assert sorted(digest) == ["a.bin", "sub/b.bin"]
    assert folder_digest_problems(tmp_path) == []
    (tmp_path / "a.bin").write_bytes(b"01234")
    (tmp_path / "sub" / "b.bin").write_bytes(b"abd")
    assert folder_digest_problems(tmp_path) == [
        "a.bin: 5 bytes, expected 10",
        "sub/b.bin: content hash differs",
    ]
    (tmp_path / "sub" / "b.bin").unlink()
    assert "sub/b.bin: missing" in folder_digest_problems(tmp_path)


@pytest.fixture
def tiny_cfg():
    preset = _module("_reliability_sim", "tests/sim/sim_helpers.py").preset
    # smaller than scale=tiny: two short lines
    return preset(
        "synthetic_d1",
        "tiny",
        sonar__max_range_m=10.0,
        plan__n_train=1,
        plan__n_test=1,
        sonar__n_bins=32,
    )


def test_synthetic_survey_cache_truncated_or_altered_file_is_rebuilt(
    tmp_path, tiny_cfg, monkeypatch, caplog
):
    calls = []
    original = generate_module.generate_survey
    monkeypatch.setattr(
        generate_module, "generate_survey", lambda c: calls.append(1) or original(c)
    )
    folder = prepare_synthetic(tiny_cfg, tmp_path)
    assert (folder / FOLDER_DIGEST).is_file() and len(calls) == 1
    line = sorted((folder / "lines").glob("*.npz"))[0]
    good = line.read_bytes()
    assert prepare_synthetic(tiny_cfg, tmp_path) == folder and len(calls) == 1  # reused

    line.write_bytes(good[: len(good) // 2])  # truncated
    with caplog.at_level(logging.WARNING):
        prepare_synthetic(tiny_cfg, tmp_path)
    assert len(calls) == 2 and "corrupt" in caplog.text and line.name in caplog.text
    assert line.read_bytes() == good  # same config, same survey

    flipped = bytearray(good)
    flipped[len(flipped) // 2] ^= 0xFF  # same size, other content
    line.write_bytes(bytes(flipped))
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        prepare_synthetic(tiny_cfg, tmp_path)
    assert len(calls) == 3 and "content hash differs" in caplog.text
    assert Survey.load(folder).line(line.stem).n_pings > 0

    # a folder from before digests: verified by loading, then given its digest, not rebuilt
    (folder / FOLDER_DIGEST).unlink()
    prepare_synthetic(tiny_cfg, tmp_path)
    assert len(calls) == 3 and folder_digest_problems(folder) == []

    stale = dict(tiny_cfg, seed=9)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        prepare_synthetic(stale, tmp_path)
    assert len(calls) == 4 and "stale" in caplog.text


def test_imported_xtf_survey_cache_truncated_file_is_rebuilt(tmp_path, caplog):
    io_helpers = _module("_reliability_io", "tests/io/conftest.py")
    raw = tmp_path / "raw"
    for i in range(2):
        line = io_helpers.synthetic_line(f"L{i}", n_pings=30, n_bins=64, seed=i)
        write_xtf(line, raw / f"L{i}.xtf", dict(io_helpers.ORIGIN))
    cfg = json.loads(json.dumps({"kind": "xtf", "name": "imported", "files": str(raw)}))
    folder = prepare_xtf_survey(cfg, tmp_path)
    assert folder_digest_problems(folder) == []
    path = folder / "lines" / "L1.npz"
    good = path.read_bytes()
    path.write_bytes(good[:100])
    with caplog.at_level(logging.WARNING):
        prepare_xtf_survey(cfg, tmp_path)
    assert "corrupt" in caplog.text and "L1.npz" in caplog.text
    assert Survey.load(folder).line("L1").n_pings == 30
