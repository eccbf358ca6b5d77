"""The report: ``index.md`` and the self-contained web page ``index.html`` (tables, figures,
run config links, stage times), checked in headless Chromium when it is installed."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from sss2bathy.eval.report import build_report

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"
SIREN_TASKS = ("siren_gt_n2d", "siren_cnn_n2d", "siren_lambert")
CNN_METRICS = {
    f"test/{name}/{k}": v
    for name in ("synthetic_d1_tiny", "synthetic_d2_tiny")
    for k, v in {
        "mae": 0.05,
        "rel": 0.4,
        "rmse": 0.07,
        "delta1": 0.5,
        "delta2": 0.7,
        "delta3": 0.8,
    }.items()
}


def _survey(data_dir: Path) -> Path:
    """The tiny synthetic_d1 survey (a few seconds to generate)."""
    from hydra import compose, initialize_config_dir

    from sss2bathy.sim.prepare import prepare_synthetic

    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("prepare", overrides=["scale=tiny", "data/survey=synthetic_d1"])
    return prepare_synthetic(OmegaConf.to_container(cfg.data.survey, resolve=True), data_dir)


def _run(outputs: Path, task: str, info: dict, metrics: dict, stamp: str) -> Path:
    run = outputs / "runs" / task / stamp
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text(f"task_name: {task}\nseed: 42\n")
    (run / "run_info.json").write_text(json.dumps({"task_name": task, **info}))
    (run / "metrics.json").write_text(json.dumps(metrics))
    return run


@pytest.fixture(scope="module")
def outputs(tmp_path_factory) -> Path:
    """An outputs folder with a CNN run, three SIREN runs on the tiny synthetic_d1 (their
    maps: the MBES plus offsets) and the pipeline's stage times."""
    from sss2bathy.survey import Survey

    tmp = tmp_path_factory.mktemp("report")
    folder = _survey(tmp / "data")
    grid = Survey.load_grid(folder)
    outputs = tmp / "outputs"
    _run(outputs, "cnn", {}, CNN_METRICS, "2026-01-01_00-00-00")
    info = {"survey_name": folder.name, "data_dir": str(tmp / "data")}
    rng = np.random.default_rng(0)
    region = np.isfinite(grid.heights)
    region[:, : grid.shape[1] // 4] = False
    for k, task in enumerate(SIREN_TASKS):
        run = _run(outputs, task, info, {"final/mae": 0.1 * (k + 1)}, "2026-01-01_00-00-00")
        heights = grid.heights + 0.05 * (k + 1) * rng.standard_normal(grid.shape)
        np.savez(
            run / "map.npz",
            heights=heights,
            region=region,
            x0=grid.x0,
            y0=grid.y0,
            cell_size=grid.cell_size,
        )
    times = {"scale": "tiny", "seconds": {"cnn": 12.5, "siren_gt_n2d": 3.0, "total": 15.5}}
    (outputs / "report").mkdir(parents=True)
    (outputs / "report" / "stage_times.json").write_text(json.dumps(times))
    build_report(outputs)
    return outputs


def test_index_md_and_html_hold_every_table_figure_link_and_stage_time(outputs):
    report = outputs / "report"
    md = (report / "index.md").read_text()
    page = (report / "index.html").read_text()
    figures = re.findall(r"!\[[^\]]*\]\(([^)]+\.png)\)", md)
    assert {"pdf_d1.png", "maps_d1.png", "zoom_d1_0.png"} <= set(figures)
    for name in figures:
        assert (report / name).is_file(), name
    # every figure embedded: the page needs nothing beside it
    srcs = re.findall(r'<img [^>]*src="([^"]+)"', page)
    assert len(srcs) == len(figures) and all(s.startswith("data:image/png;base64,") for s in srcs)
    # the paper-table layout: CNN table, SIREN d1 table with the paper rows, stage times
    assert page.count("<table>") == 3
    assert "<th>variant</th>" in page and "SIREN-CNN-N2d" in page and "published" in md.lower()
    assert "<td>cnn</td>" in page and "15.5" in page
    # each run's composed config, linked relative to the report
    for task in ("cnn", *SIREN_TASKS):
        link = f"../runs/{task}/2026-01-01_00-00-00/.hydra/config.yaml"
        assert f'href="{link}"' in page, task
        assert (report / link).is_file()


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


CHECK_SCRIPT = """
<script>
window.addEventListener('load', () => {
  const imgs = [...document.images];
  const ok = imgs.filter(i => i.complete && i.naturalWidth > 0).length;
  const out = document.createElement('pre');
  out.id = 'load-check';
  out.textContent = JSON.stringify({images: imgs.length, decoded: ok,
    tables: document.querySelectorAll('table').length,
    figures: document.querySelectorAll('figure').length,
    widths: imgs.map(i => i.naturalWidth)});
  document.body.appendChild(out);
});
</script>
"""


@pytest.mark.skipif(
    _chromium() is None,
    reason="headless Chromium not installed (Debian: apt-get install -y chromium)",
)
def test_index_html_loads_in_headless_chromium_with_every_figure_decoded(outputs, tmp_path):
    page = (outputs / "report" / "index.html").read_text()
    probe = outputs / "report" / "_probe.html"  # beside index.html: the same relative links
    probe.write_text(page.replace("</body>", CHECK_SCRIPT + "</body>"))
    cmd = [
        _chromium(),
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={tmp_path / 'profile'}",
        "--virtual-time-budget=10000",
        "--dump-dom",
        probe.as_uri(),
    ]
    env = dict(os.environ, HOME=str(tmp_path))
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)
    probe.unlink()
    assert proc.returncode == 0, proc.stderr[-2000:]
    match = re.search(r'<pre id="load-check">(.*?)</pre>', proc.stdout, re.S)
    assert match, f"the page's load check did not run: {proc.stderr[-2000:]}"
    check = json.loads(match.group(1).replace("&quot;", '"'))
    md = (outputs / "report" / "index.md").read_text()
    n_figures = len(re.findall(r"!\[[^\]]*\]\(([^)]+\.png)\)", md))
    assert check["images"] == check["figures"] == n_figures
    assert check["decoded"] == n_figures, check  # every <img> decodes
    assert min(check["widths"]) > 300  # real figures, not broken-image icons
    assert check["tables"] == 3


def test_results_json_holds_the_tables_of_the_runs_and_renders_the_results_page(outputs):
    import csv

    from sss2bathy.eval.results import readme_results, results_markdown

    report = outputs / "report"
    results = json.loads((report / "results.json").read_text())
    assert results["scale"] == "tiny"  # from the stage times: these run records name none
    assert results["commits"] == ["unknown"] and "cores" in results["machine"]
    assert set(results["cnn"]["rows"]) == {"synthetic_d1_tiny", "synthetic_d2_tiny"}
    table = results["siren"]["d1"]
    # the rows, in the experiments' order and names, are those of the report's own table
    assert list(table["rows"]) == ["SIREN-GT-N2d", "SIREN-CNN-N2d", "SIREN-Lambert"]
    with open(report / "table_siren_d1.csv") as fh:
        ours = [r for r in csv.DictReader(fh) if r["source"].startswith("ours")]
    for row in ours:
        assert float(row["mae"]) == pytest.approx(table["rows"][row["variant"]]["mae"])
        assert int(row["n_cells"]) == table["rows"][row["variant"]]["n_cells"]
    assert table["runs"] == ["2026-01-01_00-00-00"] * 3
    assert (report / "results.md").read_text() == results_markdown(results)
    assert "| SIREN-CNN-N2d |" in readme_results(results)
