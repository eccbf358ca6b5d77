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

Stages that do not depend on each other run side by side: ``jobs=N`` at a time (default:
the usable cores divided by the scale's ``torch_threads``, so ``scale=demo``, one thread a
stage, runs two at once on two cores; a scale without a thread count runs one at a time). A
stage starts once the surveys are prepared and the runs it ``needs`` are finished; the report
comes last. With more than one at a time, each line a stage prints is prefixed with its name
and the whole output is kept in ``<outputs>/report/logs/<stage>.log``. The results do not
depend on ``jobs``: the thread count of a stage is the scale's, whatever runs beside it.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO

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
#: how long a finished stage's output is still copied (a worker it left may hold it open)
READER_GRACE_S = 30.0


@dataclass(frozen=True)
class Stage:
    """One process of the pipeline: its name, entry module and own overrides."""

    name: str
    module: str
    overrides: tuple[str, ...]
    needs: tuple[str, ...] = ()  # experiments whose finished run it reads


def plan_stages(experiments: list[Experiment]) -> list[Stage]:
    """The surveys ``experiments`` prepare (in their order), the experiments, the report."""
    surveys = list(dict.fromkeys(s for e in experiments for s in e.prepare))
    stages = [Stage(prepare_stage(s), PREPARE, (f"data/survey={s}",)) for s in surveys]
    stages += [Stage(e.name, TRAIN, (f"experiment={e.name}",), e.needs) for e in experiments]
    return stages + [Stage("report", REPORT, ())]


def dependencies(plan: list[Stage]) -> dict[str, set[str]]:
    """What each stage of ``plan`` waits for: nothing (preparing a survey); every preparing
    stage and the ``needs`` that are in the plan (training: an experiment may read any
    prepared survey); every other stage (the report)."""
    names = {s.name for s in plan}
    prepares = {s.name for s in plan if s.module == PREPARE}
    deps: dict[str, set[str]] = {}
    for s in plan:
        if s.module == PREPARE:
            deps[s.name] = set()
        elif s.module == TRAIN:
            deps[s.name] = prepares | (set(s.needs) & names)
        else:
            deps[s.name] = names - {s.name}
    return deps


def first_ready(pending: list[Stage], deps: dict[str, set[str]], done: set[str]) -> Stage | None:
    """The first stage of ``pending`` (plan order) whose dependencies are all ``done``."""
    return next((s for s in pending if deps[s.name] <= done), None)


def schedule(plan: list[Stage], jobs: int, durations: dict[str, float]) -> float:
    """The wall time of running ``plan`` ``jobs`` at a time, as :func:`run_plan` orders it
    (ready stages in plan order), with each stage taking ``durations[name]`` seconds: what
    ``jobs=`` buys, without running anything."""
    deps = dependencies(plan)
    done: set[str] = set()
    running: dict[str, float] = {}  # name -> end time
    pending = list(plan)
    now = 0.0
    while pending or running:
        while len(running) < jobs and (ready := first_ready(pending, deps, done)) is not None:
            pending.remove(ready)
            running[ready.name] = now + durations[ready.name]
        if not running:
            raise ValueError(f"stages {[s.name for s in pending]} wait for stages that never run")
        name = min(running, key=running.__getitem__)
        now = running.pop(name)
        done.add(name)
    return now


def usage() -> str:
    """What ``--help`` prints: this module's docstring, the stages and the make targets."""
    experiments = pipeline_experiments(config_dir())
    targets = list(dict.fromkeys(e.make for e in experiments))
    return (
        "usage: python -m sss2bathy.cli.pipeline [scale=<tiny|demo|paper>] "
        "[stages=[a,b,...] | make=<target> | needs=[a,...]] [jobs=N] "
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
    jobs: int | None = None  # None: the usable cores / the scale's torch_threads


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
        elif key == "jobs":
            value = arg.split("=", 1)[1].strip()
            if not value.isdigit() or int(value) < 1:
                raise ValueError(f"jobs: expected an integer >= 1, found {value!r}")
            args.jobs = int(value)
        else:
            args.overrides.append(arg)
    return args


def has_finished_run(outputs: Path, name: str, scale: str) -> bool:
    """Whether ``outputs/runs/<name>/`` holds a run of ``scale`` with ``checkpoints/last.ckpt``
    (what ``data.normals.checkpoint=latest`` takes)."""
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


def stage_threads(args: Args, conf_dir: str | Path) -> int | None:
    """The torch threads of each training stage: a ``torch_threads=`` override, else the
    scale's ``torch_threads`` (``conf/scale/<scale>.yaml``); None: the usable cores."""
    import yaml

    given = [a.split("=", 1)[1] for a in args.overrides or [] if a.startswith("torch_threads=")]
    if given:
        value = given[-1].strip()
    else:
        path = Path(conf_dir) / "scale" / f"{args.scale}.yaml"
        if not path.is_file():
            return None
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
        value = data.get("torch_threads") if isinstance(data, dict) else None
        value = None if value is None else str(value)
    if value is None or value.lower() in ("null", "none", ""):
        return None
    if not value.isdigit() or int(value) < 1:
        raise ValueError(f"torch_threads: expected an integer >= 1 or null, found {value!r}")
    return int(value)


def default_jobs(threads: int | None, cores: int) -> int:
    """Stages at a time: as many as the usable cores hold at ``threads`` each; one when a
    stage takes every core (``threads`` None)."""
    return 1 if threads is None else max(1, cores // threads)


def _read_times(path: Path) -> dict:
    try:
        data = json.loads(path.read_text()) if path.is_file() else {}
    except (OSError, json.JSONDecodeError):
        return {}
    return data if isinstance(data, dict) else {}


def record_time(path: Path, scale: str, name: str, seconds: float) -> None:
    """The latest wall time of each stage at ``scale`` in ``stage_times.json`` (a stage run
    again replaces its time; ``total`` is their sum)."""
    data = _read_times(path)
    old = data.get("seconds") if data.get("scale") == scale else None
    times = {k: v for k, v in old.items() if k != "total"} if isinstance(old, dict) else {}
    if not isinstance(old, dict):
        data = {}
    times[name] = round(seconds, 1)
    times["total"] = round(sum(times.values()), 1)
    data.update(scale=scale, seconds=times)
    atomic_write_text(path, json.dumps(data, indent=2))


def record_wall(path: Path, seconds: float | None, jobs: int | None) -> None:
    """The whole run's wall time (up to the report) and stages at a time beside the stage
    times, whose ``total`` is the sum of the stages: more than the wall time when they ran
    side by side. None removes them (a run that has not finished yet)."""
    data = _read_times(path)
    if not data and seconds is None:
        return
    data.pop("wall_seconds", None)
    data.pop("jobs", None)
    if seconds is not None:
        data.update(wall_seconds=round(seconds, 1), jobs=jobs)
    atomic_write_text(path, json.dumps(data, indent=2))


def _forward(stream: IO[str], prefix: str, log: IO[str], lock: threading.Lock) -> None:
    """Copy a stage's output line by line to the log file and, prefixed, to stdout."""
    for line in stream:
        log.write(line)
        log.flush()
        with lock:
            sys.stdout.write(prefix + line)
            sys.stdout.flush()


class Lane:
    """One running stage: its process, and the threads copying its output."""

    def __init__(self, cmd: list[str], cwd: Path, name: str, logs: Path | None) -> None:
        self.t0 = time.perf_counter()
        self.readers: list[threading.Thread] = []
        self.log: IO[str] | None = None
        if logs is None:  # one at a time: the stage owns the terminal (progress bars)
            self.proc = subprocess.Popen(cmd, cwd=cwd)
            return
        logs.mkdir(parents=True, exist_ok=True)
        self.log = open(logs / f"{name}.log", "w", encoding="utf-8")  # noqa: SIM115
        self.proc = subprocess.Popen(
            cmd,
            cwd=cwd,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            errors="replace",
            bufsize=1,
        )
        assert self.proc.stdout is not None
        reader = threading.Thread(
            target=_forward, args=(self.proc.stdout, f"[{name}] ", self.log, _PRINT), daemon=True
        )
        reader.start()
        self.readers.append(reader)

    def finish(self) -> float:
        """Seconds from the start to the exit; returns once the output is copied (waiting at
        most :data:`READER_GRACE_S`: a worker the stage left behind may hold it open)."""
        seconds = time.perf_counter() - self.t0
        for reader in self.readers:
            reader.join(timeout=READER_GRACE_S)
        if self.log is not None and not any(r.is_alive() for r in self.readers):
            self.log.close()
        return seconds


_PRINT = threading.Lock()


def _say(text: str) -> None:
    with _PRINT:
        print(text, flush=True)


def run_plan(
    plan: list[Stage],
    jobs: int,
    command: Callable[[Stage], list[str]],
    cwd: Path,
    logs: Path | None,
    on_done: Callable[[Stage, float], None],
) -> int:
    """Run ``plan``, ``jobs`` stages at a time, each once what it waits for
    (:func:`dependencies`) is done, ready ones in plan order; 0, or the exit status of the
    first stage that failed (no stage starts after a failure; running ones finish)."""
    deps = dependencies(plan)
    pending = list(plan)
    running: dict[str, tuple[Stage, Lane]] = {}
    done: set[str] = set()
    failed: tuple[str, int] | None = None
    n = len(plan)
    order = {s.name: i for i, s in enumerate(plan, 1)}
    try:
        while pending or running:
            while failed is None and len(running) < jobs:
                ready = first_ready(pending, deps, done)
                if ready is None:
                    break
                pending.remove(ready)
                cmd = command(ready)
                _say(f"\n=== [{order[ready.name]}/{n}] {ready.name}: {' '.join(cmd[2:])}")
                running[ready.name] = (ready, Lane(cmd, cwd, ready.name, logs))
            if not running:
                break
            finished = [name for name, (_, lane) in running.items() if lane.proc.poll() is not None]
            if not finished:
                time.sleep(0.2)
                continue
            for name in finished:
                stage, lane = running.pop(name)
                seconds = lane.finish()
                code = lane.proc.returncode
                status = "done" if code == 0 else "FAILED"
                _say(f"=== [{order[name]}/{n}] {name}: {status} in {seconds:.0f} s")
                if code != 0:
                    if failed is None:
                        failed = (name, code)
                    others = ", ".join(running)
                    _say(
                        f"stage '{name}' failed (exit {code}); no new stage starts"
                        + (f"; waiting for {others} to finish" if others else "")
                    )
                    continue
                done.add(name)
                on_done(stage, seconds)
    except KeyboardInterrupt:
        for _, lane in running.values():
            lane.proc.terminate()
        for _, lane in running.values():
            lane.proc.wait()
        raise
    if failed is not None:
        print(f"stage '{failed[0]}' failed (exit {failed[1]}); stopping.", file=sys.stderr)
        return failed[1]
    if pending:  # cannot happen with a checked plan (needs name earlier stages)
        names = [s.name for s in pending]
        print(f"stages {names} wait for stages that never ran; stopping.", file=sys.stderr)
        return 1
    return 0


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
        threads = stage_threads(args, config_dir())
    except ValueError as err:
        print(f"pipeline: {err}", file=sys.stderr)
        return 2
    from sss2bathy.utils.threads import available_cores

    cores = available_cores()
    jobs = args.jobs if args.jobs is not None else default_jobs(threads, cores)
    times_path = outputs / "report" / "stage_times.json"
    print(
        f"pipeline: {len(plan)} stages, {jobs} at a time ({cores} usable cores, torch threads "
        f"a stage: {threads if threads is not None else 'the usable cores'}; jobs=N to change)",
        flush=True,
    )

    def command(stage: Stage) -> list[str]:
        cmd_args = list(stage.overrides)
        if stage.module == REPORT:
            cmd_args += ["--outputs", str(outputs)]
        else:
            # each run keeps its composed config in <run>/.hydra/; don't print it here
            cmd_args += [f"scale={args.scale}", "extras.print_config=false"]
            if stage.module == TRAIN:
                cmd_args += args.overrides
        return [sys.executable, "-m", stage.module, *cmd_args]

    before_report = {s.name for s in plan if s.module != REPORT}
    finished: set[str] = set()

    def on_done(stage: Stage, seconds: float) -> None:
        # written after every stage, so the report (the last stage) can show them, with the
        # wall time up to the report once every other stage is done
        record_time(times_path, args.scale, stage.name, seconds)
        finished.add(stage.name)
        if before_report and finished == before_report:
            record_wall(times_path, time.perf_counter() - t_all, jobs)

    record_wall(times_path, None, None)  # an earlier run's wall time is not this run's
    t_all = time.perf_counter()
    logs = outputs / "report" / "logs" if jobs > 1 else None
    code = run_plan(plan, jobs, command, root, logs, on_done)
    if code != 0:
        return code
    wall = time.perf_counter() - t_all
    print(f"\nAll {len(plan)} stages done in {wall / 60:.1f} min ({jobs} at a time).")
    if any(s.module == REPORT for s in plan):
        print(f"Report: {outputs / 'report' / 'index.html'} (and index.md)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
