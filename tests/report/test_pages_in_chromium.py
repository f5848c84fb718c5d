"""The reconstruction report and the pipeline demo's index page, loaded in headless Chromium
(:func:`chromium_page.check_page`); skipped, with the reason shown by ``pytest -rs``, where no Chromium is
installed.
"""

from __future__ import annotations

from chromium_page import NEEDS_CHROMIUM, check_page
from polarface.report.demo_index import demo_index_page

pytestmark = NEEDS_CHROMIUM


def test_report_loads_in_chromium(demo_dir, tmp_path):
    dom = check_page(tmp_path, demo_dir / "result" / "report.html")
    assert "Parameter maps" in dom and "DoP validation" in dom


def test_demo_index_loads_in_chromium(demo_dir, metrics, tmp_path):
    page = demo_index_page(demo_dir, "preset tiny", metrics).write(demo_dir / "index.html")
    dom = check_page(tmp_path, page)
    assert "<th>target</th>" in dom and "comparison/eta.png" in dom


def test_dynamic_section_loads_in_chromium(tmp_path):
    from dynamic_fixtures import write_dynamic_result
    from polarface.report import HtmlPage, dynamic_section

    root = write_dynamic_result(tmp_path / "result", frames=4, failed={1: "tracking lost"})
    page = HtmlPage("dynamic sequence")
    dynamic_section(page, root)
    dom = check_page(tmp_path, page.write(root / "report.html"))
    assert "previews/dynamic_c_h_out.gif" in dom and "failed: tracking lost" in dom
