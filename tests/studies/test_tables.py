"""The studies' table writer: Markdown alignment, CSV fields, both files beside each other."""

import csv
import io

import pytest

from studies.tables import fmt_cell, markdown_table, to_csv, write_tables


def test_markdown_table_aligns_and_checks_its_cells():
    lines = markdown_table(["run", "MAE (m)"], [["a", f"{0.12345:.3f}"], ["b", 2]], "lr")
    assert lines == ["| run | MAE (m) |", "|---|---:|", "| a | 0.123 |", "| b | 2 |"]
    assert markdown_table(["x"], [])[1] == "|---|"
    with pytest.raises(ValueError, match="align: expected 2 letters"):
        markdown_table(["run", "MAE"], [], "l")
    with pytest.raises(ValueError, match="row: expected 2 cells"):
        markdown_table(["run", "MAE"], [["a"]])
    assert fmt_cell(0.123456) == "0.123" and fmt_cell(3) == "3"


def test_csv_fields_missing_and_extra_keys(tmp_path):
    rows = [{"a": 1, "b": 0.5}, {"a": 2}]
    text = to_csv(rows, ["a", "b"])
    assert "\r" not in text
    assert list(csv.DictReader(io.StringIO(text))) == [{"a": "1", "b": "0.5"}, {"a": "2", "b": ""}]
    with pytest.raises(ValueError):
        to_csv([{"a": 1, "c": 3}], ["a"])
    assert to_csv([{"a": 1, "c": 3}], ["a"], ignore_extra=True) == "a\n1\n"
    paths = write_tables(tmp_path / "out", "study", "# t\n", text)
    assert paths["md"].read_text() == "# t\n" and paths["csv"].read_text() == text
    assert paths["csv"].name == "study.csv"
