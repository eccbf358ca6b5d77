"""Scaling study: the power-law fit, the survey plan, the SIREN projection, bounded import."""

from __future__ import annotations

import math
import resource
import subprocess
import sys

import numpy as np
import pytest

from studies.scaling_study import (
    DEMO,
    _map_cmd,
    long_line,
    power_law,
    siren_projection,
    survey_plan,
)


def test_power_law_recovers_exponent_and_its_error():
    k = np.array([1.0, 4.0, 16.0, 64.0])
    fit = power_law(k, 3.0 * k**1.2)
    assert fit["b"] == pytest.approx(1.2) and fit["a"] == pytest.approx(3.0)
    assert fit["b_se"] == pytest.approx(0.0, abs=1e-9)
    rng = np.random.default_rng(0)
    noisy = power_law(k, 3.0 * k**0.9 * np.exp(rng.normal(0, 0.1, k.size)))
    assert abs(noisy["b"] - 0.9) < 3 * noisy["b_se"] + 0.05 and noisy["b_se"] > 0
    assert math.isnan(power_law([1.0, 2.0], [1.0, 2.0])["b_se"])


@pytest.mark.parametrize(
    ("sizes", "costs"), [([1.0], [1.0]), ([1.0, 2.0], [1.0, 0.0]), ([2.0, 2.0], [1.0, 3.0])]
)
def test_power_law_refuses_what_it_cannot_fit(sizes, costs):
    with pytest.raises(ValueError, match="sizes"):
        power_law(sizes, costs)


def test_survey_plan_scales_area_lines_and_pings():
    one, sixteen = survey_plan(1.0), survey_plan(16.0)
    assert one["n_lines"] == DEMO["n_lines"] and one["size_m"] == DEMO["size_m"]
    assert sixteen["n_lines"] == 4 * one["n_lines"]
    assert sixteen["size_m"] == (4 * DEMO["size_m"][0], 4 * DEMO["size_m"][1])
    assert sixteen["pings"] == 16 * one["pings"]
    with pytest.raises(ValueError, match="k:"):
        survey_plan(0.0)


def test_siren_projection_splits_fixed_and_per_step_cost():
    proj = siren_projection(12.0 + 30 * 0.5, 12.0 + 90 * 0.5, 30, 90, pings=1600)
    assert proj["per_step_s"] == pytest.approx(0.5) and proj["fixed_s"] == pytest.approx(12.0)
    assert proj["schedule_steps"] == 6 * 100
    assert proj["projected_s"] == pytest.approx(12.0 + 300.0)
    with pytest.raises(ValueError, match="steps"):
        siren_projection(1.0, 2.0, 30, 30, 100)


CHILD = """
import resource, sys
from sss2bathy.io.xtf import read_xtf
line, _ = read_xtf(sys.argv[1], 64, origin={"crs": "EPSG:32633", "easting": 680000.0,
                   "northing": 6580000.0})
print(line.n_pings, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


@pytest.mark.slow
def test_long_line_imports_in_memory_well_below_its_size(tmp_path):
    """A 40 MB line (4096 samples per side) read to 64 bins: the reader's peak memory grows
    far less than the file (the samples are resampled a few MB at a time; before, it held
    every sample as float64: ~4x the file)."""
    small = long_line(tmp_path / "small.xtf", 4.0)
    large = long_line(tmp_path / "large.xtf", 40.0)
    assert large.stat().st_size > 9 * small.stat().st_size

    def peak_mb(path):
        out = subprocess.run(
            [sys.executable, "-c", CHILD, str(path)], capture_output=True, text=True, check=True
        ).stdout.split()
        return int(out[0]), int(out[1]) / 1024

    (n_small, mb_small), (n_large, mb_large) = peak_mb(small), peak_mb(large)
    assert n_large > 9 * n_small
    grown = mb_large - mb_small
    assert grown < 0.4 * (large.stat().st_size - small.stat().st_size) / 2**20, (
        mb_small,
        mb_large,
    )
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss > 0


def test_report_round_trip_and_exponents(tmp_path):
    """The written table reads back to the same exponents; a stage whose peak never exceeds
    its baseline has no working-memory exponent."""
    from studies.scaling_study import exponents, read_table, write_report

    table = []
    for k in (1.0, 4.0, 16.0):
        pings = 11520 * k
        table.append(
            {"stage": "import", "k": k, "pings": pings, "work_s": 5.0 * k, "wall_s": 20 * k}
            | {"peak_mb": 300.0 + 10 * k, "baseline_mb": 280.0}
        )
        table.append(
            {"stage": "drape", "k": k, "pings": pings, "work_s": 4.0 * k**1.05, "wall_s": 9 * k}
            | {"peak_mb": 600.0, "baseline_mb": 600.0}
        )
    md = write_report(tmp_path, table, tmp_path / "fig.png")
    assert (tmp_path / "fig.png").stat().st_size > 0 and "b_time" in md
    fits = {f["stage"]: f for f in exponents(read_table(tmp_path / "scaling_study.csv"))}
    assert fits["import"]["b_time"] == pytest.approx(1.0)
    assert fits["drape"]["b_time"] == pytest.approx(1.05)
    assert fits["drape"]["b_peak"] == pytest.approx(0.0, abs=1e-12)
    assert math.isnan(fits["drape"]["b_working"])
    assert 0 < fits["import"]["b_working"] < 1
    assert (tmp_path / "scaling_fits.csv").read_text().startswith("stage,b_time")


def test_map_command_pins_the_smooth_siren_settings(tmp_path):
    # the published costs are the scale settings' fit; the map route's default is detail
    cmd = _map_cmd(tmp_path / "x", tmp_path / "d", "n", tmp_path / "r", 5)
    assert "map_settings=scale" in cmd
    assert "+trainer.max_steps=5" in cmd[-1]
