"""GPU projection of a paper-scale SIREN fit from a measured step."""

from __future__ import annotations

import pytest

from benchmarks.projection import paper_fit_steps, project_fit_minutes, projection_section


def test_paper_fit_steps():
    assert paper_fit_steps() == 1500 * 375
    assert paper_fit_steps(lines=1, pings_per_line=65, batch_pings=64, epochs=2) == 4
    with pytest.raises(ValueError, match="batch_pings: expected a positive integer"):
        paper_fit_steps(batch_pings=0)


def test_minutes_scale_with_work_and_efficiency():
    a = project_fit_minutes(1e11, 0.5, steps=1000, peaks={"G": {"fp32": 10.0}})
    # 1e14 FLOP at 10 TFLOP/s x 0.5 = 20 s
    assert a["minutes"]["G"]["fp32"] == pytest.approx(20.0 / 60.0)
    b = project_fit_minutes(2e11, 1.0, steps=1000, peaks={"G": {"fp32": 10.0}})
    assert b["minutes"]["G"]["fp32"] == pytest.approx(a["minutes"]["G"]["fp32"])
    with pytest.raises(ValueError, match="efficiency"):
        project_fit_minutes(1e11, 1.5)


def test_section_from_siren_step_result():
    sec = projection_section({"info": {"recorded_flops": 68.6e9, "bound_fraction": 0.52}})
    names = {f["name"]: f["median"] for f in sec["figures"]}
    fp32 = names["H100-SXM5 fp32: projected fit"]
    assert fp32 == pytest.approx(68.6e9 * 562500 / (67e12 * 0.52) / 60)
    assert names["H100-SXM5 bf16: projected fit"] < fp32
    with pytest.raises(ValueError, match="recorded_flops"):
        projection_section({"info": {}})
