"""The README is a user guide: short, "your own survey" early, no work-log references (dates,
commit hashes, numbered work periods, issue numbers) and no paths outside the repository;
``make help`` and the config comments keep no work-log references either."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"

WORK_LOG = [
    (re.compile(r"\b[Ss]ession \d+"), "a numbered work session"),
    (re.compile(r"\b[Ii]ssues? #?\d+"), "an issue number"),
    (re.compile(r"(?<![\w/])#\d{1,4}\b"), "an issue number"),
    (re.compile(r"\b20\d\d-\d\d-\d\d\b"), "a date"),
    (re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,40}\b"), "a commit hash"),
]


def _work_log_hits(lines: list[str], where: str) -> list[str]:
    hits = []
    for number, line in enumerate(lines, 1):
        for pattern, what in WORK_LOG:
            found = pattern.search(line)
            if found:
                hits.append(f"{where}:{number}: {what} ({found.group(0)!r})")
    return hits


def test_readme_is_a_short_user_guide():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 300, f"README.md: expected <= 300 lines, found {len(lines)}"
    own = [i for i, line in enumerate(lines, 1) if line.startswith("## Your own survey")]
    assert own and own[0] <= 100, f"README.md: 'Your own survey' expected within 100 lines: {own}"


def test_readme_has_no_work_log_references_or_outside_paths():
    lines = README.read_text(encoding="utf-8").splitlines()
    hits = _work_log_hits(lines, "README.md")
    hits += [f"README.md:{n}: a path outside the repository" for n, line in
             enumerate(lines, 1) if "../" in line]  # fmt: skip
    assert not hits, "\n".join(hits)


def test_make_help_and_config_comments_have_no_work_log_references():
    help_lines = [ln for ln in (ROOT / "Makefile").read_text().splitlines() if "##" in ln]
    hits = _work_log_hits(help_lines, "Makefile (make help)")
    for path in sorted((ROOT / "conf").rglob("*.yaml")):
        comments = [
            ln.split("#", 1)[1] if "#" in ln else "" for ln in path.read_text().splitlines()
        ]
        hits += _work_log_hits(comments, str(path.relative_to(ROOT)))
    assert not hits, "\n".join(hits)


@pytest.mark.parametrize(
    "text",
    ["measured in session 14", "see issue #20", "fixed in #15", "on 2026-12-02", "commit 6d9605d"],
)
def test_the_check_finds_each_kind_of_reference(text):
    assert _work_log_hits([text], "x")


def test_every_make_command_in_the_readme_is_a_target():
    """``make <target>`` in the README names a target of the Makefile (or an experiment's,
    from conf/experiment)."""
    from sss2bathy.utils.experiments import pipeline_experiments

    text = README.read_text(encoding="utf-8")
    named = set(re.findall(r"`make ([a-z0-9-]+)", text))
    makefile = (ROOT / "Makefile").read_text()
    targets = set(re.findall(r"^([a-zA-Z0-9_-]+):(?!=)", makefile, re.M))
    targets |= {e.make for e in pipeline_experiments(ROOT / "conf")}
    assert named, "README.md: expected make commands"
    assert named <= targets, f"README.md: no such make target {sorted(named - targets)}"
