"""The results are written from runs: ``docs/results.md`` and the README's results block are
what the renderers make of the committed ``docs/results.json``; publishing a report writes
all three; a README without the block or a report without runs is one line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sss2bathy.eval.results import (
    README_END,
    README_START,
    publish,
    readme_block,
    readme_results,
    replace_block,
    results_markdown,
)

ROOT = Path(__file__).resolve().parents[2]
DOCS_JSON = ROOT / "docs" / "results.json"


def test_docs_results_md_is_rendered_from_docs_results_json():
    results = json.loads(DOCS_JSON.read_text())
    assert (ROOT / "docs" / "results.md").read_text() == results_markdown(results)
    for figures in (results.get("figures") or {}).values():
        for figure in figures:
            assert (ROOT / "docs" / figure).is_file(), figure


def test_readme_results_are_rendered_from_docs_results_json():
    results = json.loads(DOCS_JSON.read_text())
    block = readme_block((ROOT / "README.md").read_text(encoding="utf-8"))
    assert block, f"README.md: expected the block {README_START} ... {README_END}"
    assert block == readme_results(results), "README.md: run make results (or render it)"


def _results() -> dict:
    row = {"mae": 0.05, "rel": 0.05, "rmse": 0.06, "delta1": 60.0, "delta2": 90.0, "delta3": 99.0}
    return {
        "scale": "tiny",
        "commits": ["abcdef0"],
        "machine": "a CPU, 2 cores",
        "date": "2000-01-01",
        "source": "a test",
        "cnn": {"rows": {"s1": row}, "constant": {"s1": {**row, "mae": 0.1, "value": 0.0}}},
        "siren": {
            "d1": {"title": "t", "survey": "s1", "rows": {"SIREN-GT-N2d": {"mae": 0.2}}},
            "d3": {"title": "t3", "survey": "s3", "rows": {"SIREN-Lambert": {"mae": 0.4}}},
        },
        "stage_times": {"scale": "tiny", "seconds": {"cnn": 3.0, "total": 3.0}},
    }


def test_the_readme_block_holds_the_numbers_of_the_results():
    block = readme_results(_results())
    assert block.startswith(README_START) and block.endswith(README_END)
    assert "| s1 | 0.0500 | 0.1000 | 0.50 |" in block  # skill = CNN MAE / constant MAE
    assert "| SIREN-GT-N2d | 0.200 |  | 0.079 / 0.740 |" in block  # the paper beside ours
    assert "SIREN on synthetic_d3 (another sonar): SIREN-Lambert 0.400 m." in block


def test_publish_writes_docs_and_readme_from_the_report(tmp_path):
    report = tmp_path / "report"
    report.mkdir()
    (report / "results.json").write_text(json.dumps(_results()))
    (report / "pdf_d1.png").write_bytes(b"png")
    (report / "zoom_d1_0.png").write_bytes(b"zoom")
    readme = tmp_path / "README.md"
    readme.write_text(f"# x\n\nbefore\n{README_START}\nold\n{README_END}\nafter\n")
    written = publish(report, tmp_path / "docs", readme)
    results = json.loads((tmp_path / "docs" / "results.json").read_text())
    assert results["figures"] == {"d1": ["images/pdf_d1_tiny.png", "images/zoom_d1_0_tiny.png"]}
    assert (tmp_path / "docs" / "images" / "pdf_d1_tiny.png").read_bytes() == b"png"
    assert (tmp_path / "docs" / "results.md").read_text() == results_markdown(results)
    text = readme.read_text()
    assert readme_block(text) == readme_results(results) and "old" not in text
    assert text.startswith("# x\n\nbefore\n") and text.endswith("\nafter\n")
    assert readme in written and len(written) == 5


def test_publish_refuses_a_report_without_runs_and_a_readme_without_the_block(tmp_path):
    report = tmp_path / "report"
    report.mkdir()
    (report / "results.json").write_text(json.dumps({"cnn": None, "siren": {}}))
    readme = tmp_path / "README.md"
    readme.write_text("# x\n")
    with pytest.raises(ValueError, match="expected the tables of at least one finished run"):
        publish(report, tmp_path / "docs", readme)
    assert not (tmp_path / "docs").exists()
    with pytest.raises(ValueError, match=r"README\.md: expected one block .* found no start"):
        replace_block("# x\n", "block", "README.md")
