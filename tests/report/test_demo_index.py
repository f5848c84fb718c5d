"""The pipeline demo's index page and the report: metrics table, comparisons, links, scale bars."""

from __future__ import annotations

import re

import numpy as np

from polarface.io import colormap_png, read_png
from polarface.report.demo_index import METRIC_TARGETS, demo_index_page, metric_rows


def _sources(html: str) -> list[str]:
    return re.findall(r'<img src="([^"]+)"', html)


def test_metric_rows_value_target_pass(metrics):
    rows = {row[0]: row[1:] for row in metric_rows(metrics)}
    assert len(rows) == len(METRIC_TARGETS) == 11
    assert rows["eta median abs error"] == ("0.0123", "<= 0.02", "pass")
    assert rows["normal median angular error"] == ("0.591 deg", "<= 2 deg", "pass")
    assert rows["rho_sss_bar median relative error"] == ("1.77 %", "<= 3 %", "pass")
    assert rows["alpha_s median abs error"] == ("0.08", "<= 0.05", "FAIL")
    assert rows["rho_s median relative error"] == ("19.4 %", "<= 10 %", "FAIL")
    assert rows["held-out I_s RMSE / mean I_sss"] == ("0.0152", "< 0.0394", "pass")
    assert rows["C_m median abs error"] == ("-", "<= 0.005", "not computed")


def test_index_page(demo_dir, metrics):
    page = demo_index_page(demo_dir, "preset tiny", metrics).write(demo_dir / "index.html")
    html = page.read_text(encoding="utf-8")
    # links that `polarface demo --help` promises: the report, the metrics, the simulated frames
    for href in ("result/report.html", "metrics.json", "sim/static/raw/pol_upper/000000.png"):
        assert f'href="{href}"' in html
    assert "<th>target</th><th>pass</th>" in html and '<td class="num">0.0123</td>' in html
    assert '{"' not in html  # no raw JSON
    for name in ("eta", "alpha_s", "displacement_mm", "rho_sss_bar"):
        assert f'src="comparison/{name}.png"' in html
        figure = read_png(demo_dir / "comparison" / f"{name}.png")
        assert figure.shape[1] >= 1400  # three panels side by side at full page width
    assert 'src="frames/pol_upper_0000_I0.png"' in html
    sources = _sources(html)
    assert sources and all((demo_dir / src).is_file() for src in sources)
    # every thumbnail links to its full-size image
    assert all(f'<a href="{src}" title="open full size"><img src="{src}"' in html for src in sources)


def test_report_scale_bars_and_links(demo_dir):
    html = (demo_dir / "result" / "report.html").read_text(encoding="utf-8")
    sources = _sources(html)
    assert "previews/report_map_eta.png" in sources and "previews/report_dop_0_observed.png" in sources
    assert all((demo_dir / "result" / src).is_file() for src in sources)
    assert "repeat(3, 1fr)" in html and "max-width: 1400px" in html
    # a figure with a scale bar is wider than the map (legend on the right) and not pixel-exact
    assert read_png(demo_dir / "result" / "previews" / "report_map_eta.png").shape[1] > 500


def test_colormap_label_draws_a_scale_bar(tmp_path):
    image = np.linspace(0, np.pi, 64).reshape(8, 8)
    colormap_png(tmp_path / "plain.png", image)
    colormap_png(tmp_path / "bar.png", image, cmap="twilight", label="AoLP (rad)")
    assert read_png(tmp_path / "plain.png").shape == (8, 8, 3)
    assert read_png(tmp_path / "bar.png").shape[1] > 400
