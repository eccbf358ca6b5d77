"""studies/placement_on_map, survey mode: per line of a split, the flat-seabed and the
draped-on-each-map placement errors against the draping on the survey's MBES truth."""

from __future__ import annotations

import numpy as np
import pytest

from sss2bathy.survey import BathyGrid, Survey
from studies.placement_on_map import main, survey_placement
from tests.eval.test_mosaic import SEABED_Z, north_line, plane


def _survey(truth: BathyGrid) -> Survey:
    lines = [north_line(x=0.0, name="a"), north_line(x=30.0, name="b")]
    return Survey("slope", lines, truth, {"test": ["a", "b"]})


def test_a_map_equal_to_the_truth_places_every_bin_where_the_truth_does():
    truth = plane(a=0.05, c=SEABED_Z)
    flat = BathyGrid(np.full_like(truth.heights, SEABED_Z), truth.x0, truth.y0, truth.cell_size)
    header, rows = survey_placement(_survey(truth), "test", {"truth": truth, "level": flat})
    assert header[:3] == ["line", "flat median (m)", "flat p95 (m)"] and len(rows) == 2
    for row in rows:
        flat_median, truth_median, grid_flat_median = float(row[1]), float(row[3]), float(row[5])
        assert truth_median < 1e-3 < flat_median  # on the slope, only the truth is exact
        # a flat grid at the seabed's mean height misplaces bins like the flat seabed does
        assert grid_flat_median > 0.05


def test_survey_without_truth_or_bad_map_is_one_line(tmp_path, capsys):
    truth = plane()
    survey = _survey(truth)
    with pytest.raises(ValueError, match="MBES grid"):
        survey_placement(Survey("none", survey.lines, None, survey.splits), "test", {})
    folder = survey.save(tmp_path / "s")
    assert main(["--survey", str(folder), "--map", f"x={tmp_path / 'nowhere'}"]) == 2
    assert "--map: expected LABEL=" in capsys.readouterr().err
