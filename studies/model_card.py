"""The model card of an exported normal CNN: docs/pretrained_model.md from its JSON metadata.

    python -m studies.model_card                                  (the shipped model)
    python -m studies.model_card --model RUN.safetensors --metrics eval/metrics.json \\
        --section docs/studies/siren_tables.md --out docs/pretrained_model.md

Everything on the card comes from the model's ``.json`` (``python -m sss2bathy.pretrained
export`` wrote it; its weights' SHA-256 is checked here) and the optional ``--metrics``
files (flat metrics JSON such as a run's ``metrics.json``: ``test/<set>/nlat_mae`` and
``test/<set>/constant/nlat_mae`` become rows of the per-site table; later files win over
the model's own): what the network is and what it reads, how to use it, the training
recipe and command, the data and the sonar ranges it covers (the settings outside which
sss2bathy-map warns, with their tolerance), its n_lat scores per data set, and ``--section``
Markdown files appended as they are (e.g. the SIREN map tables, the real line's verdict).
Nothing is typed in by hand, so the card cannot drift from the files it describes.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from sss2bathy.data.cnn_model_file import read_model_weights
from sss2bathy.data.cnn_normals import resolve_model_path
from sss2bathy.data.sonar_envelope import SETTINGS, TOLERANCE, describe
from sss2bathy.utils.atomic import atomic_write_text
from studies.tables import markdown_table

DEFAULT_OUT = Path("docs/pretrained_model.md")
#: How each recorded sonar setting is named on the card and its unit.
SETTING_NAMES = {
    "frequency_hz": ("frequency", "kHz", 1e-3),
    "max_range_m": ("range (last bin)", "m", 1.0),
    "bin_m": ("bin size", "m", 1.0),
    "tilt_deg": ("tilt (depression of the beam axis)", "°", 1.0),
    "beam_width_deg": ("vertical beam width", "°", 1.0),
    "altitude_m": ("altitude (5th-95th percentile per line)", "m", 1.0),
}


def read_metrics(paths: Sequence[str | Path]) -> dict[str, float]:
    """The finite numbers of flat metrics JSON files (later files win)."""
    out: dict[str, float] = {}
    for path in paths:
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise ValueError(f"--metrics {path}: expected a metrics JSON file ({err})") from None
        if not isinstance(data, dict):
            raise ValueError(
                f"--metrics {path}: expected a JSON object, found {type(data).__name__}"
            )
        for key, value in data.items():
            if isinstance(value, int | float) and not isinstance(value, bool):
                if math.isfinite(value):
                    out[str(key)] = float(value)
    return out


def site_rows(metrics: Mapping[str, float]) -> list[list[str]]:
    """Rows ``[data set, CNN MAE, constant MAE, skill, RMSE, δ<1.05]`` of every
    ``test/<set>/nlat_mae`` (sorted by set) and the validation MAE."""
    sets = sorted(
        k.split("/")[1] for k in metrics
        if k.startswith("test/") and k.count("/") == 2 and k.endswith("/nlat_mae")
    )  # fmt: skip
    rows = []
    for name in sets:
        mae = metrics[f"test/{name}/nlat_mae"]
        const = metrics.get(f"test/{name}/constant/nlat_mae")
        rmse = metrics.get(f"test/{name}/nlat_rmse")
        delta = metrics.get(f"test/{name}/nlat_delta1")
        rows.append(
            [
                f"`{name}`",
                f"{mae:.4f}",
                "" if const is None else f"{const:.4f}",
                "" if not const else f"{mae / const:.2f}",
                "" if rmse is None else f"{rmse:.4f}",
                "" if delta is None else f"{delta:.1f}",
            ]
        )
    if "val/nlat_mae" in metrics:
        rows.append(["validation lines", f"{metrics['val/nlat_mae']:.4f}", "", "", "", ""])
    return rows


def _tolerance(key: str) -> str:
    kind, amount = TOLERANCE.get(key, ("rel", 0.0))
    if kind == "rel":
        return f"±{100 * amount:.0f} % of the bound"
    return f"±{amount:g} {SETTING_NAMES[key][1]}"


def sonar_rows(envelope: Mapping[str, Any] | None) -> list[list[str]]:
    """``[setting, trained range, tolerance]`` per recorded setting."""
    if not envelope:
        return []
    settings = envelope.get("settings") or {}
    rows = []
    for key in SETTINGS:
        if key not in settings:
            continue
        name, unit, factor = SETTING_NAMES[key]
        lo, hi = (float(v) * factor for v in settings[key])
        text = f"{lo:.3g}" if f"{lo:.3g}" == f"{hi:.3g}" else f"{lo:.3g} – {hi:.3g}"
        rows.append([name, f"{text} {unit}", _tolerance(key)])
    return rows


def training_surveys(data: Mapping[str, Any]) -> list[str]:
    """Names of the surveys the training windows came from (``train_surveys`` when pooled,
    else the ``survey``)."""
    pooled = data.get("train_surveys") or []
    names = [str(s.get("name")) for s in pooled if isinstance(s, Mapping) and s.get("name")]
    if names:
        return names
    survey = data.get("survey")
    return [str(survey["name"])] if isinstance(survey, Mapping) and survey.get("name") else []


def _value(mapping: Mapping[str, Any] | None, *keys: str) -> Any:
    node: Any = mapping
    for key in keys:
        if not isinstance(node, Mapping) or key not in node:
            return None
        node = node[key]
    return node


def card_markdown(
    meta: Mapping[str, Any],
    weights: Path,
    metrics: Mapping[str, float],
    sections: Sequence[tuple[str, str]] = (),
    command: str = "python -m studies.model_card",
) -> str:
    """The card's Markdown (``sections``: ``(source file, its text)`` appended as they are)."""
    net = dict(meta["network"])
    cls = str(net.pop("_target_")).rsplit(".", 1)[-1]
    args = ", ".join(f"{k}={v}" for k, v in net.items())
    record = meta["weights"]
    training = meta.get("training") or {}
    data = training.get("data") or {}
    config = training.get("config") or {}
    run_info = training.get("run_info") or {}
    windows = meta["windows"]
    envelope = meta.get("sonar_envelope")
    software = meta.get("software") or {}
    surveys = training_surveys(data)
    kinds = sorted(
        {str(s.get("kind")) for s in [data.get("survey"), *(data.get("train_surveys") or [])]
         if isinstance(s, Mapping) and s.get("kind")}
    )  # fmt: skip
    mask = ", ".join(f"{k}={v}" for k, v in meta["sonar_mask"].items())
    lines = [
        f"# The pretrained normal CNN (`{meta['name']}`)",
        "",
        f"Generated by `{command}` from `{weights.with_suffix('.json').name}` (its weights' "
        "SHA-256 checked); do not edit by hand. The inverse sensor model of SIREN-CNN-N2d: "
        "it reads sidescan windows and predicts n_lat, the seabed normal's component in the "
        "plane of each ping, which the SIREN stage integrates into a height map.",
        "",
        "## What it is",
        "",
    ]
    lines += markdown_table(
        ["", ""],
        [
            ["network", f"`{cls}({args})`"],
            [
                "parameters",
                f"{record.get('n_parameters', '?')} in {record.get('n_tensors', '?')} "
                f"tensors ({', '.join(record.get('dtypes') or [])})",
            ],  # fmt: skip
            [
                "weights",
                f"`{record['file']}`, {record.get('bytes', 0) / 1e6:.2f} MB, "
                f"safetensors (tensors only), SHA-256 `{record['sha256']}`",
            ],  # fmt: skip
            ["input channels", ", ".join(meta["input_channels"])],
            ["input normalisation", f"intensity over the sonar-only mask ({mask})"],
            [
                "windows",
                f"{windows['window_pings']} pings × "
                f"{windows['window_bins'] or 'all the line’s'} bins, overlap {windows['overlap']}",
            ],  # fmt: skip
            [
                "source checkpoint",
                f"`{training.get('source_checkpoint', '?')}` (SHA-256 "
                f"`{str(training.get('source_sha256', '?'))[:16]}…`), epoch "
                f"{training.get('epoch', '?')}, step {training.get('global_step', '?')}",
            ],  # fmt: skip
            [
                "code",
                f"sss2bathy {software.get('sss2bathy', '?')}"
                + (f", git {run_info['git_revision']}" if run_info.get("git_revision") else "")
                + f"; torch {software.get('torch', '?')}",
            ],  # fmt: skip
        ],
        "ll",
    )
    lines += [
        "",
        "## Use",
        "",
        "```",
        "sss2bathy-map files=LINES method=siren_cnn_n2d          # uses this model by default",
        "sss2bathy-map files=LINES cnn_checkpoint=pretrained     # the same, by name",
        "python -m sss2bathy.pretrained show                     # check the files",
        "sss2bathy-train experiment=cnn data/survey=SITE model.init=pretrained \\",
        "    $(python -m sss2bathy.pretrained overrides)         # fine-tune on a site's lines",
        "```",
        "",
        "## Training recipe",
        "",
        f"Command: `{training.get('command') or 'unknown (exported without its run folder)'}`",
        "",
    ]
    recipe = [
        ["training data", ", ".join(f"`{s}`" for s in surveys) or "unknown"],
        ["kind of data", ", ".join(kinds) or "unknown"],
        ["training lines (sonar envelope)", str(_value(envelope, "n_lines") or "unknown")],
        ["scale", str(_value(config, "scale", "name") or run_info.get("scale") or "unknown")],
        ["epochs", str(_value(config, "trainer", "max_epochs") or "unknown")],
        ["batch", str(data.get("batch_size", "unknown"))],
        ["loss", ", ".join(f"{k}={v}" for k, v in (training.get("loss") or {}).items())],
        ["optimizer", ", ".join(f"{k}={v}" for k, v in (training.get("optimizer") or {}).items())],
        ["scheduler", ", ".join(f"{k}={v}" for k, v in (training.get("scheduler") or {}).items())],
        ["seed", str(config.get("seed", data.get("seed", "unknown")))],
    ]
    lines += markdown_table(["", ""], recipe, "ll")
    lines += ["", "## Sonar covered", ""]
    rows = sonar_rows(envelope)
    if rows:
        lines += [
            f"The training lines' sonar ({describe(envelope['settings'])}). sss2bathy-map "
            "warns (one WARNING line) when a survey's sonar lies outside these ranges by "
            "more than the tolerance; the normals are computed all the same.",
            "",
        ]
        lines += markdown_table(
            ["setting", "trained on", "tolerance before a warning"], rows, "lll"
        )
    else:
        lines.append("Not recorded: every survey gets a warning that its sonar may be unknown.")
    lines += ["", "## Metrics", ""]
    table = site_rows(metrics)
    if table:
        lines += [
            "n_lat on each data set's lines (unitless): the CNN's MAE, that of predicting the "
            "training mean everywhere (constant), skill = CNN / constant (below 1: better "
            "than the constant), RMSE and the share of bins within a 1.05 ratio (%).",
            "",
        ]
        lines += markdown_table(
            ["data set", "CNN MAE", "constant MAE", "skill", "RMSE", "δ<1.05 (%)"], table,
            "lrrrrr",
        )  # fmt: skip
    else:
        lines.append("No test metrics recorded.")
    for source, text in sections:
        lines += ["", f"<!-- from {source} -->", "", text.strip()]
    return "\n".join(lines) + "\n"


def write_card(
    model: str | Path = "pretrained",
    out: str | Path = DEFAULT_OUT,
    metrics: Sequence[str | Path] = (),
    sections: Sequence[str | Path] = (),
) -> Path:
    """Validate the model, merge its metrics with ``metrics`` files and write the card."""
    weights = resolve_model_path(model, "--model")
    meta, _ = read_model_weights(weights)
    merged = dict((meta.get("metrics") or {}).get("values") or {})
    merged.update(read_metrics(metrics))
    texts = []
    for path in sections:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"--section: expected a Markdown file, found no file {path}")
        texts.append((str(path), path.read_text()))
    parts = ["python -m studies.model_card"]
    if str(model) != "pretrained":
        parts.append(f"--model {weights.name}")
    parts += [f"--metrics {Path(p).name}" for p in metrics]
    parts += [f"--section {Path(p)}" for p in sections]
    text = card_markdown(meta, weights, merged, texts, " ".join(parts))
    atomic_write_text(out, text)
    return Path(out)


def main(argv: Sequence[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(
        prog="python -m studies.model_card",
        description="Write the model card (docs/pretrained_model.md) of an exported CNN.",
    )
    parser.add_argument("--model", default="pretrained", help="a .safetensors or pretrained")
    parser.add_argument("--out", default=str(DEFAULT_OUT))
    parser.add_argument("--metrics", action="append", default=[], help="metrics JSON (repeatable)")
    parser.add_argument("--section", action="append", default=[], help="Markdown to append")
    args = parser.parse_args(argv)
    try:
        out = write_card(args.model, args.out, args.metrics, args.section)
    except (ValueError, FileNotFoundError) as err:
        parser.error(" ".join(str(err).split()))
    print(f"model card written to {out}")
    return out


if __name__ == "__main__":
    main()
