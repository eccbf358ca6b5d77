"""The report of one map run (report.html): figures embedded, the coverage, uncertainty and
verdict numbers, the import's warnings once each, the settings and the provenance; checked
in headless Chromium when it is installed; ``sss2bathy-report RUN`` writes it."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess

import numpy as np
import pytest
import yaml

from sss2bathy.eval.map_report import (
    import_counts_table,
    is_map_run,
    log_warnings,
    write_map_report,
)
from sss2bathy.eval.maps import render_map
from sss2bathy.eval.uncertainty import write_run_uncertainty
from sss2bathy.eval.verdict import kfold_verdict
from sss2bathy.io.export import write_geotiff
from sss2bathy.survey import BathyGrid

ORIGIN = {"crs": "EPSG:32619", "easting": 512700.0, "northing": 5365800.0}
LOG = """\
[2026-12-04 04:32:36,517][sss2bathy.io.xtf][WARNING] - line.xtf: 1024 samples per side resampled to 512 bins
[2026-12-04 04:32:36,704][sss2bathy.io.xtf][INFO] - imported 460 pings
[2026-12-04 04:39:20,250][sss2bathy.io.xtf][WARNING] - line.xtf: 1024 samples per side resampled to 512 bins
[2026-12-04 04:39:20,308][sss2bathy.io.xtf][WARNING] - line.xtf: navigation/ping repairs: pings dropped: 1
"""


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A finished map run folder with everything sss2bathy-map writes (small, generated)."""
    tmp = tmp_path_factory.mktemp("maprun")
    run = tmp / "run"
    (run / ".hydra").mkdir(parents=True)
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:40, 0:60]
    heights = (-20.0 + 0.05 * xx + np.sin(yy / 6.0)).astype(np.float32)
    covered = np.abs(yy - 20) < 12
    grid = BathyGrid(heights, 0.25, 0.25, 0.5, ORIGIN["crs"])
    geom = {"x0": 0.25, "y0": 0.25, "cell_size": 0.5}
    np.savez(run / "map.npz", heights=heights, coverage=covered, **geom)
    write_geotiff(grid, run / "map.tif", origin=ORIGIN, mask=covered)
    render_map(BathyGrid(np.where(covered, heights, np.nan), 0.25, 0.25, 0.5), run / "map.png",
               "map", origin=ORIGIN)  # fmt: skip
    for k in range(3):
        fold = run / "verdict" / "siren_lambert" / f"fold{k}"
        fold.mkdir(parents=True)
        np.savez(fold / "map.npz", heights=heights + rng.normal(0, 0.05, heights.shape), **geom)
    sigma = write_run_uncertainty(run, "siren_lambert", 4.97, ORIGIN, "SIREN-Lambert")
    verdict = kfold_verdict(
        {
            "siren_lambert": [0.061, 0.070, 0.058],
            "siren_heights_only": [0.080, 0.075, 0.079],
            "interpolation": [0.110, 0.120, 0.100],
        },
        "siren_lambert",
        block_m=6.96,
        block_pings=57.2,
        seconds=600.0,
        imaged_share=0.0,
    )
    (run / "verdict.json").write_text(json.dumps(verdict.to_dict()))
    metrics = {
        "final/imaged_area_m2": 2458.5,
        "final/written_area_m2": 2489.5,
        "final/extrapolated_share": 0.0,
        "final/track_region_extrapolated_share": 0.598,
        **verdict.metrics(),
        **sigma.to_metrics(),
    }
    (run / "metrics.json").write_text(json.dumps(metrics))
    (run / "map.log").write_text(LOG)
    data = tmp / "data" / "xtf_line"
    data.mkdir(parents=True)
    stats = {"line": {"pings": 460, "pings_dropped_nav": 1, "crs": "EPSG:32619"}}
    (data / "survey.yaml").write_text(yaml.safe_dump({"metadata": {"import_stats": stats}}))
    info = {"task_name": "siren_lambert", "survey_name": "xtf_line", "data_dir": str(tmp / "data")}
    (run / "run_info.json").write_text(json.dumps(info))
    (run / "config.yaml").write_text("task_name: siren_lambert\nseed: 42\nnote: <b>&</b>\n")
    (run / ".hydra" / "overrides.yaml").write_text("- files=/data/line.xtf\n- survey.tilt_deg=20\n")
    write_map_report(run, summary=["sss2bathy-map: siren_lambert on survey 'xtf_line'"])
    return run, metrics


def test_log_warnings_are_each_message_once_with_its_count():
    assert log_warnings(LOG) == [
        ("sss2bathy.io.xtf", "line.xtf: 1024 samples per side resampled to 512 bins", 2),
        ("sss2bathy.io.xtf", "line.xtf: navigation/ping repairs: pings dropped: 1", 1),
    ]
    assert log_warnings("no log lines\n[x][y][INFO] - z") == []


def test_import_counts_are_one_row_per_count_one_column_per_file():
    table = import_counts_table(
        {"a": {"pings": 3, "crs": "x", "ok": True}, "b": {"pings": 4, "gap": 1}}
    )
    assert table[0] == "| count | `a` | `b` |"
    assert "| pings | 3 | 4 |" in table and "| gap | – | 1 |" in table
    assert not any("crs" in row or "| ok" in row for row in table)  # numbers only
    assert import_counts_table({}) == []


def test_the_report_holds_the_figures_numbers_warnings_settings_and_provenance(run):
    run, metrics = run
    page = (run / "report.html").read_text()
    # every figure the run has, embedded; the hillshade made from map.npz
    assert (run / "hillshade.png").is_file()
    srcs = re.findall(r'<img [^>]*src="([^"]+)"', page)
    files = re.findall(r'<img [^>]*data-file="([^"]+)"', page)
    assert set(files) == {"map.png", "hillshade.png", "uncertainty.png"}
    assert all(s.startswith("data:image/png;base64,") for s in srcs)
    assert "mosaic.png" in page and "not in this run" in page  # what is missing is said
    # coverage and uncertainty numbers
    assert ">2458</td>" in page and ">2490</td>" in page  # imaged, written m²
    assert f"{metrics['uncertainty/sigma_median_m']:.3f}" in page
    assert f"{metrics['uncertainty/sigma_p95_m']:.3f}" in page and "4.97" in page
    # the verdict table with its spread, the comparisons and the sentence
    assert ">0.063</td>" in page  # SIREN-Lambert's mean of 0.061, 0.070, 0.058
    assert ">0.006</td>" in page  # its std over folds
    assert "0.058 - 0.070" in page and "VERDICT:" in page and "7.0 m of track" in page
    # the import's warnings once each, with their count; the import counts
    assert page.count("1024 samples per side resampled") == 1 and "(× 2)" in page
    assert "navigation/ping repairs" in page and ">460</td>" in page
    # settings (escaped) and provenance
    assert "survey.tilt_deg=20" in page and "&lt;b&gt;&amp;&lt;/b&gt;" in page
    assert "SSS2BATHY_VERSION" in page and "SSS2BATHY_COMMAND" in page
    assert re.search(r'<a href="map.tif">map.tif</a></td>\s*<td>yes</td>', page)
    assert re.search(r'<a href="uncertainty.tif">uncertainty.tif</a></td>\s*<td>yes</td>', page)
    assert "siren_lambert on survey" in page  # the command's own summary


def test_a_folder_that_is_not_a_map_run_is_refused(tmp_path):
    assert not is_map_run(tmp_path)
    (tmp_path / "map.tif").write_bytes(b"")
    with pytest.raises(ValueError, match="found no map.npz, metrics.json"):
        write_map_report(tmp_path)


def test_sss2bathy_report_on_a_map_run_writes_its_page(run, tmp_path, capsys):
    from sss2bathy.cli.report import main

    run_dir, _ = run
    (run_dir / "report.html").unlink()
    main([str(run_dir)])
    assert (run_dir / "report.html").is_file()
    assert str(run_dir / "report.html") in capsys.readouterr().out
    with pytest.raises(SystemExit) as exit_:
        main([str(tmp_path)])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "expected a finished sss2bathy-map run folder" in err[0]


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


CHECK_SCRIPT = """
<script>
window.addEventListener('load', () => {
  const imgs = [...document.images];
  const out = document.createElement('pre');
  out.id = 'load-check';
  out.textContent = JSON.stringify({images: imgs.length,
    decoded: imgs.filter(i => i.complete && i.naturalWidth > 0).length,
    tables: document.querySelectorAll('table').length,
    widths: imgs.map(i => i.naturalWidth)});
  document.body.appendChild(out);
});
</script>
"""


@pytest.mark.skipif(
    _chromium() is None,
    reason="headless Chromium not installed (Debian: apt-get install -y chromium)",
)
def test_the_report_loads_in_headless_chromium_with_every_figure_decoded(run, tmp_path):
    run_dir, _ = run
    page = (run_dir / "report.html").read_text()
    probe = run_dir / "_probe.html"
    probe.write_text(page.replace("</body>", CHECK_SCRIPT + "</body>"))
    cmd = [
        _chromium(),
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={tmp_path / 'profile'}",
        "--virtual-time-budget=10000",
        "--dump-dom",
        probe.as_uri(),
    ]
    proc = subprocess.run(
        cmd, capture_output=True, text=True, timeout=120, env=dict(os.environ, HOME=str(tmp_path))
    )
    probe.unlink()
    assert proc.returncode == 0, proc.stderr[-2000:]
    match = re.search(r'<pre id="load-check">(.*?)</pre>', proc.stdout, re.S)
    assert match, f"the page's load check did not run: {proc.stderr[-2000:]}"
    check = json.loads(match.group(1).replace("&quot;", '"'))
    assert check["images"] == check["decoded"] == 3, check
    assert min(check["widths"]) > 300
    assert check["tables"] >= 4  # coverage, verdict, import counts, provenance
