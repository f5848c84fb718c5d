"""The pipeline demo's index page and the report: metrics table, comparisons, links, scale bars."""

from __future__ import annotations

import re

import numpy as np
import pytest

from polarface.io import colormap_png, read_png
from polarface.report.demo_index import METRIC_TARGETS, demo_index_page, metric_rows, write_comparisons


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


def test_index_page_shows_comparisons_written_before(demo_dir, metrics, tmp_path, monkeypatch):
    """The demo writes the comparison figures on a worker and gives the page what that call returned."""
    import polarface.report.demo_index as demo_index

    items = write_comparisons(demo_dir, demo_dir / "result", demo_dir / "sim" / "ground_truth")
    assert [item.path for item in items][:2] == ["comparison/eta.png", "comparison/alpha_s.png"]
    monkeypatch.setattr(demo_index, "write_comparisons", lambda *args: pytest.fail("written again"))
    html = demo_index_page(demo_dir, "preset tiny", metrics, comparisons=items).write(
        tmp_path / "index.html").read_text(encoding="utf-8")
    assert all(f'src="{item.path}"' in html for item in items)


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


def test_dynamic_scalars_reduce_the_per_frame_lists_to_what_the_targets_bound():
    from polarface.report.demo_index import DYNAMIC_TARGETS, dynamic_scalars

    dynamic = {
        "frames": 3,
        "tracking_mm": {"median_per_frame": [0.2, 0.25, 0.3], "max": 0.45},
        "c_h_out_patch_abs_error": [0.004, 0.012, None],
        "recovery_time_constant_s": {"ground_truth": 0.667, "reconstructed": 0.8},
        "c_m_patch_drift_max": 0.001,
        "rho_sss_bar_median_relative_error": [0.02, 0.03, 0.025],
        "normal_median_deg": [2.0, 2.5, 2.2],
        "rho_s_flicker_median": 0.01,
        "seconds_per_frame": 42.0,
    }
    scalars = dynamic_scalars(dynamic)
    assert scalars["tracking_median_worst_mm"] == 0.3
    assert scalars["tracking_drift_ratio"] == pytest.approx(1.5)
    assert scalars["c_h_out_patch_worst"] == 0.012  # None (a failed frame) is skipped
    assert scalars["recovery_time_constant_relative_error"] == pytest.approx(0.133 / 0.667, rel=1e-3)
    rows = metric_rows({"dynamic": dynamic, "dynamic_scalars": scalars}, DYNAMIC_TARGETS)
    verdicts = {row[0]: row[3] for row in rows}
    assert verdicts["tracking drift: last / first frame median"] == "FAIL"
    assert verdicts["C_h_out patch abs error, worst frame"] == "FAIL"
    assert verdicts["rho_s flicker median"] == "pass"
    assert all(v in ("pass", "FAIL") for v in verdicts.values())
