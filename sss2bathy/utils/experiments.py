"""The one list of experiments: the files ``conf/experiment/<name>.yaml``.

An experiment that is a stage of the paper pipeline (``make demo``) says so in its own file,
in one key read here by the pipeline (``sss2bathy.cli.pipeline``: stage order, what to run
first), the report (``sss2bathy.eval.report``: which table, under which name) and the
Makefile (its make target)::

    pipeline:
      order: 40               # stage order, lower first
      label: SIREN-CNN-N2d    # its row in the report's table
      table: d1               # the report's table it is a row of (cnn, d1, d2, d3)
      make: siren-cnn-n2d     # the make target that runs it (experiments may share one)
      needs: [cnn]            # experiments whose finished run it reads (trained first if none)
      prepare: []             # synthetic surveys prepared first, each as its own stage

Each file's own key counts, not the composed config: a file that inherits from a stage but
is not one sets ``pipeline: null``. An experiment without the key still runs by name
(``sss2bathy-train experiment=<name>``, the pipeline's ``stages=[<name>]``); it is not in
the pipeline's default plan nor in the report's tables.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sss2bathy.utils.checks import is_integer, require

#: the keys of an experiment's ``pipeline`` block, every one required
PIPELINE_KEYS = ("order", "label", "table", "make", "needs", "prepare")
KEY = "pipeline"


@dataclass(frozen=True)
class Experiment:
    """A stage of the paper pipeline: ``conf/experiment/<name>.yaml`` and its ``pipeline``
    key."""

    name: str
    order: int
    label: str
    table: str
    make: str
    needs: tuple[str, ...]
    prepare: tuple[str, ...]


def default_conf_dir() -> Path:
    """``conf/`` of the project: ``$SSS2BATHY_ROOT/conf``, else the checkout this package
    lives in."""
    root = os.environ.get("SSS2BATHY_ROOT")
    return (Path(root) if root else Path(__file__).resolve().parents[2]) / "conf"


def experiment_files(conf_dir: str | Path | None = None) -> dict[str, Path]:
    """``name -> conf/experiment/<name>.yaml`` of every experiment, by name."""
    folder = Path(conf_dir or default_conf_dir()) / "experiment"
    return {p.stem: p for p in sorted(folder.glob("*.yaml"))}


def _text(where: str, value: Any) -> str:
    return require(where, value, isinstance(value, str) and value.strip() != "", "a name")


def _names(where: str, value: Any) -> tuple[str, ...]:
    ok = isinstance(value, list) and all(isinstance(v, str) and v for v in value)
    return tuple(require(where, value, ok, "a list of names ([] for none)"))


def read_experiment(path: Path) -> Experiment | None:
    """The file's own ``pipeline`` block as an :class:`Experiment`; None without one. A bad
    block is one ``ValueError`` naming the file, the key, the expected and the found value."""
    import yaml

    data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    block = data.get(KEY) if isinstance(data, dict) else None
    if block is None:
        return None
    where = f"{path}: {KEY}"
    require(where, block, isinstance(block, dict), f"a mapping of {list(PIPELINE_KEYS)}")
    keys = sorted(block)
    require(f"{where} keys", keys, keys == sorted(PIPELINE_KEYS), str(sorted(PIPELINE_KEYS)))
    order = block["order"]
    require(f"{where}.order", order, is_integer(order) and order >= 0, "an integer >= 0")
    return Experiment(
        name=path.stem,
        order=order,
        label=_text(f"{where}.label", block["label"]),
        table=_text(f"{where}.table", block["table"]),
        make=_text(f"{where}.make", block["make"]),
        needs=_names(f"{where}.needs", block["needs"]),
        prepare=_names(f"{where}.prepare", block["prepare"]),
    )


def pipeline_experiments(conf_dir: str | Path | None = None) -> list[Experiment]:
    """The experiments with a ``pipeline`` key, in stage order; checked as a whole: distinct
    orders, ``needs`` naming earlier stages."""
    files = experiment_files(conf_dir)
    found = [e for p in files.values() if (e := read_experiment(p)) is not None]
    found.sort(key=lambda e: (e.order, e.name))
    seen: dict[int, str] = {}
    for e in found:
        other = seen.setdefault(e.order, e.name)
        where = f"{files[e.name]}: {KEY}.order"
        require(where, e.order, other == e.name, f"an order no other stage has ({other})")
        earlier = [x.name for x in found if x.order < e.order]
        for need in e.needs:
            where = f"{files[e.name]}: {KEY}.needs"
            require(where, need, need in earlier, f"one of the earlier stages {earlier}")
    return found


def prepare_stage(survey: str) -> str:
    """The pipeline's stage name that prepares ``survey`` (``synthetic_d3`` -> ``prepare_d3``)."""
    return "prepare_" + survey.removeprefix("synthetic_")
