"""The whole paper pipeline, stage by stage (``make demo``, ``make paper``, one make target
per experiment).

    python -m sss2bathy.cli.pipeline scale=demo
    python -m sss2bathy.cli.pipeline scale=demo make=d2             # a make target's experiments
    python -m sss2bathy.cli.pipeline scale=demo stages=[cnn,siren_cnn_n2d] trainer.max_epochs=3
    python -m sss2bathy.cli.pipeline scale=demo needs=[cnn]         # a CNN, only if none exists

The stages come from ``conf/experiment/``: every experiment with a ``pipeline`` key, in its
order (:mod:`sss2bathy.utils.experiments`), the surveys those prepare first, then the
report. ``stages=`` picks some (any experiment by name, even one outside the plan),
``make=`` those of one make target. An experiment that ``needs`` another's run (CNN-N2d
reads a CNN) gets it trained first when no finished run of this scale exists.

Every other argument is passed to every training stage as a Hydra override. Each stage
runs as its own process with its own Hydra run folder, so a failing stage stops the
pipeline with that stage's error and leaves earlier results intact. The latest wall time of
each stage goes to ``outputs/report/stage_times.json`` (``paths.output_dir=<dir>`` moves the
runs, the report and the times to ``<dir>``). ``--help`` prints this and runs nothing.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from sss2bathy.cli._common import config_dir, project_root, setup_environment
from sss2bathy.utils.atomic import atomic_write_text
from sss2bathy.utils.experiments import (
    Experiment,
    experiment_files,
    pipeline_experiments,
    prepare_stage,
)

PREPARE = "sss2bathy.cli.prepare"
TRAIN = "sss2bathy.cli.train"
REPORT = "sss2bathy.cli.report"
HELP_FLAGS = ("-h", "--help")


@dataclass(frozen=True)
class Stage:
    """One process of the pipeline: its name, entry module and own overrides."""

    name: str
    module: str
    overrides: tuple[str, ...]


def plan_stages(experiments: list[Experiment]) -> list[Stage]:
    """The surveys ``experiments`` prepare (in their order), the experiments, the report."""
    surveys = list(dict.fromkeys(s for e in experiments for s in e.prepare))
    stages = [Stage(prepare_stage(s), PREPARE, (f"data/survey={s}",)) for s in surveys]
    stages += [Stage(e.name, TRAIN, (f"experiment={e.name}",)) for e in experiments]
    return stages + [Stage("report", REPORT, ())]


def usage() -> str:
    """What ``--help`` prints: this module's docstring, the stages and the make targets."""
    experiments = pipeline_experiments(config_dir())
    targets = list(dict.fromkeys(e.make for e in experiments))
    return (
        "usage: python -m sss2bathy.cli.pipeline [scale=<tiny|demo|paper>] "
        "[stages=[a,b,...] | make=<target> | needs=[a,...]] "
        "[<Hydra override> ...]\n\n"
        + (__doc__ or "").strip()
        + "\n\nstages, in order: "
        + ", ".join(s.name for s in plan_stages(experiments))
        + "\nmake targets: "
        + ", ".join(targets)
        + "\n"
    )


@dataclass
class Args:
    """The command line: scale, what to run, overrides for every training stage."""

    scale: str = "demo"
    stages: list[str] | None = None  # None: the whole pipeline
    make: str | None = None
    needs: list[str] | None = None
    overrides: list[str] | None = None


def _names(arg: str) -> list[str]:
    value = arg.split("=", 1)[1].strip().strip("[]")
    return [s.strip() for s in value.split(",") if s.strip()]


def parse_args(argv: list[str]) -> Args:
    """:class:`Args` of the command line (``key=value`` words; the rest are overrides)."""
    args = Args(overrides=[])
    for arg in argv:
        key = arg.split("=", 1)[0]
        if key == "scale":
            args.scale = arg.split("=", 1)[1]
        elif key == "stages":
            args.stages = _names(arg)
        elif key == "needs":
            args.needs = _names(arg)
        elif key == "make":
            args.make = arg.split("=", 1)[1]
        else:
            args.overrides.append(arg)
    return args


def has_finished_run(outputs: Path, name: str, scale: str) -> bool:
    """Whether ``outputs/runs/<name>/`` holds a run of ``scale`` with ``checkpoints/last.ckpt``
    (what ``data.cnn_checkpoint=latest`` takes)."""
    from sss2bathy.utils.checkpoints import find_checkpoints, run_scale

    return any(run_scale(p) == scale for p in find_checkpoints(outputs / "runs" / name))


def select(args: Args, outputs: Path) -> list[Stage]:
    """The stages to run, in plan order: all of them, or the chosen ones with what they need.

    A chosen experiment's ``needs`` are added when not chosen themselves and no finished run
    of this scale exists (:func:`has_finished_run`); its ``prepare`` surveys come first; an
    experiment outside the plan runs after the plan's stages, before the report."""
    experiments = pipeline_experiments(config_dir())
    every = plan_stages(experiments)
    if args.stages is None and args.make is None and args.needs is None:
        return every
    by_name = {e.name: e for e in experiments}
    others = sorted(set(experiment_files(config_dir())) - set(by_name))
    known = [s.name for s in every] + others
    chosen = list(args.stages or [])
    unknown = [s for s in chosen if s not in known]
    if unknown:
        raise SystemExit(f"stages: unknown stage(s) {unknown}; expected some of {known}")
    if args.make is not None:
        targets = list(dict.fromkeys(e.make for e in experiments))
        if args.make not in targets:
            raise SystemExit(f"make: expected one of {targets}, found {args.make!r}")
        chosen += [e.name for e in experiments if e.make == args.make]
    for need in args.needs or []:
        if need not in by_name:
            raise SystemExit(f"needs: expected some of {sorted(by_name)}, found {need!r}")
        if not has_finished_run(outputs, need, args.scale):
            chosen.append(need)
    for name in chosen:  # grows while it is read: what the added ones need is added too
        for need in by_name[name].needs if name in by_name else ():
            if need not in chosen and not has_finished_run(outputs, need, args.scale):
                chosen.append(need)
    keep = set(chosen) | {
        prepare_stage(s) for n in chosen if n in by_name for s in by_name[n].prepare
    }
    stages = [s for s in every if s.name in keep and s.module != REPORT]
    stages += [Stage(n, TRAIN, (f"experiment={n}",)) for n in dict.fromkeys(chosen) if n in others]
    return stages + [s for s in every if s.module == REPORT and s.name in keep]


def record_time(path: Path, scale: str, name: str, seconds: float) -> None:
    """The latest wall time of each stage at ``scale`` in ``stage_times.json`` (a stage run
    again replaces its time; ``total`` is their sum)."""
    times: dict[str, float] = {}
    if path.is_file():
        try:
            old = json.loads(path.read_text())
            if old.get("scale") == scale:
                times = {k: v for k, v in old.get("seconds", {}).items() if k != "total"}
        except (OSError, json.JSONDecodeError, AttributeError):
            times = {}
    times[name] = round(seconds, 1)
    times["total"] = round(sum(times.values()), 1)
    atomic_write_text(path, json.dumps({"scale": scale, "seconds": times}, indent=2))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    try:  # a bad experiment file's pipeline key is one line
        if any(a in HELP_FLAGS for a in argv):
            print(usage(), end="")
            return 0
        setup_environment()
        args = parse_args(argv)
        root = project_root()
        # the outputs folder the stages write to (a paths.output_dir override moves it)
        given = [a.split("=", 1)[1] for a in args.overrides if a.startswith("paths.output_dir=")]
        outputs = root / Path(given[-1]).expanduser() if given else root / "outputs"
        plan = select(args, outputs)
    except ValueError as err:
        print(f"pipeline: {err}", file=sys.stderr)
        return 2
    times_path = outputs / "report" / "stage_times.json"
    t_all = time.perf_counter()
    for i, stage in enumerate(plan, 1):
        cmd_args = list(stage.overrides)
        if stage.module == REPORT:
            cmd_args += ["--outputs", str(outputs)]
        else:
            # each run keeps its composed config in <run>/.hydra/; don't print it here
            cmd_args += [f"scale={args.scale}", "extras.print_config=false"]
            if stage.module == TRAIN:
                cmd_args += args.overrides
        cmd = [sys.executable, "-m", stage.module, *cmd_args]
        print(f"\n=== [{i}/{len(plan)}] {stage.name}: {' '.join(cmd[2:])}", flush=True)
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, cwd=root)
        seconds = time.perf_counter() - t0
        print(
            f"=== [{i}/{len(plan)}] {stage.name}: "
            f"{'done' if proc.returncode == 0 else 'FAILED'} in {seconds:.0f} s",
            flush=True,
        )
        if proc.returncode != 0:
            print(
                f"stage '{stage.name}' failed (exit {proc.returncode}); stopping.", file=sys.stderr
            )
            return proc.returncode
        # written after every stage, so the report (the last stage) can show them
        record_time(times_path, args.scale, stage.name, seconds)
    print(f"\nAll {len(plan)} stages done in {(time.perf_counter() - t_all) / 60:.1f} min.")
    if any(s.module == REPORT for s in plan):
        print(f"Report: {outputs / 'report' / 'index.html'} (and index.md)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
