"""The whole paper pipeline, stage by stage (``make demo``, ``make paper``).

    python -m sss2bathy.cli.pipeline scale=demo
    python -m sss2bathy.cli.pipeline scale=demo stages=[cnn,siren_cnn_n2d] trainer.max_epochs=3

Every argument other than ``scale=`` and ``stages=`` is passed to every training stage as a
Hydra override. Each stage runs as its own process with its own Hydra run folder, so a
failing stage stops the pipeline with that stage's error and leaves earlier results intact.
Stage wall times go to ``outputs/report/stage_times.json`` (``paths.output_dir=<dir>`` moves
the runs, the report and the times to ``<dir>``). ``--help`` prints this and runs nothing.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

from sss2bathy.cli._common import project_root, setup_environment
from sss2bathy.utils.atomic import atomic_write_text

# (stage name, entry module, overrides) in dependency order
STAGES: list[tuple[str, str, list[str]]] = [
    ("prepare_d1", "sss2bathy.cli.prepare", ["data/survey=synthetic_d1"]),
    ("prepare_d2", "sss2bathy.cli.prepare", ["data/survey=synthetic_d2"]),
    ("prepare_d3", "sss2bathy.cli.prepare", ["data/survey=synthetic_d3"]),
    ("prepare_d1_site2", "sss2bathy.cli.prepare", ["data/survey=synthetic_d1_site2"]),
    ("cnn", "sss2bathy.cli.train", ["experiment=cnn"]),
    ("siren_direct_fit", "sss2bathy.cli.train", ["experiment=siren_direct_fit"]),
    ("siren_heights_only", "sss2bathy.cli.train", ["experiment=siren_heights_only"]),
    ("siren_gt_n2d", "sss2bathy.cli.train", ["experiment=siren_gt_n2d"]),
    ("siren_cnn_n2d", "sss2bathy.cli.train", ["experiment=siren_cnn_n2d"]),
    ("siren_lambert_all", "sss2bathy.cli.train", ["experiment=siren_lambert_all"]),
    ("siren_lambert", "sss2bathy.cli.train", ["experiment=siren_lambert"]),
    ("d2_siren_cnn_n2d", "sss2bathy.cli.train", ["experiment=d2_siren_cnn_n2d"]),
    ("d2_siren_lambert", "sss2bathy.cli.train", ["experiment=d2_siren_lambert"]),
    ("d3_siren_cnn_n2d", "sss2bathy.cli.train", ["experiment=d3_siren_cnn_n2d"]),
    ("d3_siren_lambert", "sss2bathy.cli.train", ["experiment=d3_siren_lambert"]),
    ("report", "sss2bathy.cli.report", []),
]
STAGE_NAMES = [s[0] for s in STAGES]


HELP_FLAGS = ("-h", "--help")


def usage() -> str:
    """What ``--help`` prints: this module's docstring and the stages in order."""
    return (
        "usage: python -m sss2bathy.cli.pipeline [scale=<tiny|demo|paper>] "
        "[stages=[a,b,...]] [<Hydra override> ...]\n\n"
        + (__doc__ or "").strip()
        + "\n\nstages, in order: "
        + ", ".join(STAGE_NAMES)
        + "\n"
    )


def parse_args(argv: list[str]) -> tuple[str, list[str], list[str]]:
    """``(scale, stages, overrides for every training stage)`` of the command line."""
    scale, stages, rest = "demo", list(STAGE_NAMES), []
    for arg in argv:
        if arg.startswith("scale="):
            scale = arg.split("=", 1)[1]
        elif arg.startswith("stages="):
            value = arg.split("=", 1)[1].strip("[]")
            stages = [s.strip() for s in value.split(",") if s.strip()]
            unknown = sorted(set(stages) - set(STAGE_NAMES))
            if unknown:
                raise SystemExit(
                    f"stages: unknown stage(s) {unknown}; expected some of {STAGE_NAMES}"
                )
        else:
            rest.append(arg)
    return scale, stages, rest


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if any(a in HELP_FLAGS for a in argv):
        print(usage(), end="")
        return 0
    setup_environment()
    scale, selected, extra = parse_args(argv)
    root = project_root()
    plan = [s for s in STAGES if s[0] in selected]
    times: dict[str, float] = {}
    # the outputs folder the stages write to (a paths.output_dir override moves it)
    given = [a.split("=", 1)[1] for a in extra if a.startswith("paths.output_dir=")]
    outputs = root / Path(given[-1]).expanduser() if given else root / "outputs"
    times_path = outputs / "report" / "stage_times.json"
    t_all = time.perf_counter()
    for i, (name, module, overrides) in enumerate(plan, 1):
        args = list(overrides)
        if module == "sss2bathy.cli.report":
            args += ["--outputs", str(outputs)]
        else:
            # each run keeps its composed config in <run>/.hydra/; don't print it here
            args += [f"scale={scale}", "extras.print_config=false"]
            if module == "sss2bathy.cli.train":
                args += extra
        cmd = [sys.executable, "-m", module, *args]
        print(f"\n=== [{i}/{len(plan)}] {name}: {' '.join(cmd[2:])}", flush=True)
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, cwd=root)
        times[name] = round(time.perf_counter() - t0, 1)
        print(
            f"=== [{i}/{len(plan)}] {name}: {'done' if proc.returncode == 0 else 'FAILED'} "
            f"in {times[name]:.0f} s",
            flush=True,
        )
        if proc.returncode != 0:
            print(f"stage '{name}' failed (exit {proc.returncode}); stopping.", file=sys.stderr)
            return proc.returncode
        times["total"] = round(time.perf_counter() - t_all, 1)
        # written after every stage, so the report (the last stage) can show them
        atomic_write_text(times_path, json.dumps({"scale": scale, "seconds": times}, indent=2))
    print(f"\nAll {len(plan)} stages done in {times['total'] / 60:.1f} min.")
    if "report" in selected:
        print(f"Report: {outputs / 'report' / 'index.html'} (and index.md)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
