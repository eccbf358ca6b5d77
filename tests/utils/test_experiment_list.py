"""The one list of experiments (conf/experiment): the pipeline, the report and the Makefile
read it, every experiment is reachable from them and they name none it lacks."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from sss2bathy.cli.pipeline import REPORT, TRAIN, parse_args, plan_stages, select
from sss2bathy.eval.results import CNN_KEY, REPORT_TABLES, SIREN_TABLES
from sss2bathy.utils.experiments import (
    experiment_files,
    pipeline_experiments,
    prepare_stage,
    read_experiment,
)

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"
EXPERIMENTS = pipeline_experiments(CONF)
MAKE = shutil.which("make")


def test_the_paper_experiments_are_stages_in_order():
    names = [e.name for e in EXPERIMENTS]
    assert names[0] == "cnn" and {"siren_gt_n2d", "siren_cnn_n2d", "siren_lambert"} <= set(names)
    assert [e.order for e in EXPERIMENTS] == sorted({e.order for e in EXPERIMENTS})
    # CNN-N2d reads a CNN: the registry says so, the CNN runs earlier
    for e in EXPERIMENTS:
        assert ("cnn" in e.needs) == e.name.endswith("cnn_n2d"), e.name


def test_every_experiment_file_is_reachable_by_the_pipeline():
    outputs = ROOT / "no-such-outputs"
    for name in experiment_files(CONF):
        stages = select(parse_args([f"stages=[{name}]"]), outputs)
        runs = [s for s in stages if s.module == TRAIN and s.overrides == (f"experiment={name}",)]
        assert len(runs) == 1, (name, stages)
    full = select(parse_args([]), outputs)
    assert [s.name for s in full if s.module == TRAIN] == [e.name for e in EXPERIMENTS]
    assert full[-1].module == REPORT
    prepared = [s.name for s in full if s.name.startswith("prepare_")]
    assert prepared == list(dict.fromkeys(prepare_stage(s) for e in EXPERIMENTS for s in e.prepare))


def test_every_report_table_has_rows_and_every_row_a_table():
    tables = {e.table for e in EXPERIMENTS}
    assert tables == set(REPORT_TABLES), "an experiment names a table the report lacks, or back"
    assert [e.name for e in EXPERIMENTS if e.table == CNN_KEY] == ["cnn"]
    for key in SIREN_TABLES:
        labels = [e.label for e in EXPERIMENTS if e.table == key]
        assert len(labels) == len(set(labels)) >= 2, (key, labels)


def test_a_stage_composes_with_its_own_pipeline_key():
    """Every key is required, so a stage's block replaces whatever its parent's said."""
    with initialize_config_dir(str(CONF), version_base="1.3"):
        for experiment in EXPERIMENTS:
            cfg = compose("train", overrides=[f"experiment={experiment.name}", "scale=tiny"])
            block = OmegaConf.to_container(cfg, resolve=False)["pipeline"]
            assert block == {
                "order": experiment.order,
                "label": experiment.label,
                "table": experiment.table,
                "make": experiment.make,
                "needs": list(experiment.needs),
                "prepare": list(experiment.prepare),
            }, experiment.name


@pytest.mark.parametrize(
    "text, key",
    [
        ("pipeline: {order: 1, label: X, table: d1, make: x, needs: []}\n", "keys"),
        ("pipeline: {order: -1, label: X, table: d1, make: x, needs: [], prepare: []}\n", "order"),
        ("pipeline: {order: 1, label: '', table: d1, make: x, needs: [], prepare: []}\n", "label"),
        ("pipeline: {order: 1, label: X, table: d1, make: x, needs: cnn, prepare: []}\n", "needs"),
        ("pipeline: [1, 2]\n", "pipeline"),
    ],
)
def test_a_bad_pipeline_key_is_one_line_naming_file_and_key(tmp_path, text, key):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ValueError) as err:
        read_experiment(path)
    message = str(err.value)
    assert "\n" not in message and str(path) in message and key in message
    assert "expected" in message and "found" in message


def test_needs_must_name_an_earlier_stage(tmp_path):
    folder = tmp_path / "experiment"
    folder.mkdir()
    block = "pipeline: {{order: {}, label: {}, table: d1, make: x, needs: {}, prepare: []}}\n"
    (folder / "a.yaml").write_text(block.format(1, "A", "[b]"))
    (folder / "b.yaml").write_text(block.format(2, "B", "[]"))
    with pytest.raises(ValueError, match=r"a\.yaml: pipeline\.needs: expected one of the earlier"):
        pipeline_experiments(tmp_path)
    (folder / "a.yaml").write_text(block.format(2, "A", "[]"))
    with pytest.raises(ValueError, match=r"pipeline\.order: expected an order no other stage"):
        pipeline_experiments(tmp_path)
    (folder / "c.yaml").write_text("task_name: c\n")  # not a stage: left out, no error
    (folder / "a.yaml").write_text(block.format(1, "A", "[]"))
    assert [e.name for e in pipeline_experiments(tmp_path)] == ["a", "b"]
    assert [s.name for s in plan_stages(pipeline_experiments(tmp_path))] == ["a", "b", "report"]


def _help_targets() -> dict[str, str]:
    lines = (ROOT / "Makefile").read_text().splitlines()
    found = (re.match(r"^([a-zA-Z0-9_-]+):.*?## (.*)$", line) for line in lines)
    return {m.group(1): m.group(2) for m in found if m}


@pytest.mark.skipif(MAKE is None, reason="make is not installed")
def test_every_make_target_of_the_list_runs_the_pipeline_and_has_help():
    targets = list(dict.fromkeys(e.make for e in EXPERIMENTS))
    helped = _help_targets()
    for target in targets:
        assert target in helped, f"Makefile: expected a '{target}: ## <help>' line"
        proc = subprocess.run(
            [MAKE, "-n", "--no-print-directory", target, "SCALE=tiny"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert proc.returncode == 0, proc.stderr
        assert f"sss2bathy.cli.pipeline scale=tiny make={target}" in proc.stdout, proc.stdout
    # and no Makefile target runs an experiment the list does not know
    text = (ROOT / "Makefile").read_text()
    for name in re.findall(r"experiment=([a-z0-9_]+)(?=[\s'\"]|$)", text, re.M):
        assert name in experiment_files(CONF), f"Makefile: experiment={name} has no file"
