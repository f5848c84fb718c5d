"""The reconstruction report and the pipeline demo's index page, loaded in headless Chromium.

Each page is loaded from disk (``file://``) with Debian's ``chromium``: the test asserts that it loads,
that the browser logs no console error (uncaught exception, resource that failed to load), that every
``<img>`` of the rendered DOM resolves to a file on disk, and that a 1400 px wide screenshot is drawn.
Skipped, with the reason shown by ``pytest -rs``, where no Chromium is installed.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path
from urllib.parse import unquote

import pytest

from polarface.io import image_header
from polarface.report.demo_index import demo_index_page

CHROMIUM = next((p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p), None)

pytestmark = pytest.mark.skipif(
    CHROMIUM is None,
    reason="headless Chromium is not installed (Debian package 'chromium'): the report and the demo "
    "index were not loaded in a browser",
)

#: Console lines that mean the page is broken.
_ERRORS = re.compile(r"Uncaught|Failed to load resource|ERR_FILE_NOT_FOUND|net::ERR_|SyntaxError", re.I)


def _chromium(tmp_path: Path, page: Path, *extra: str) -> subprocess.CompletedProcess:
    command = [
        CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--no-first-run",
        f"--user-data-dir={tmp_path / 'profile'}", "--enable-logging=stderr", "--v=0",
        "--virtual-time-budget=10000", *extra, page.resolve().as_uri(),
    ]
    return subprocess.run(command, capture_output=True, text=True, timeout=180, check=False)


def _check_page(tmp_path: Path, page: Path) -> str:
    loaded = _chromium(tmp_path, page, "--dump-dom")
    assert loaded.returncode == 0, loaded.stderr[-2000:]
    dom = loaded.stdout
    assert "<h1>" in dom and "</html>" in dom, f"{page}: Chromium returned no document"
    console = [line for line in loaded.stderr.splitlines() if "CONSOLE" in line or _ERRORS.search(line)]
    assert not [line for line in console if _ERRORS.search(line)], "\n".join(console)
    sources = re.findall(r'<img[^>]*\ssrc="([^"]+)"', dom)
    assert sources, f"{page}: no image"
    missing = [s for s in sources if not (page.parent / unquote(s)).is_file()]
    assert not missing, f"{page}: images that do not resolve: {missing}"
    shot = tmp_path / f"{page.stem}.png"
    drawn = _chromium(tmp_path, page, f"--screenshot={shot}", "--window-size=1400,1800", "--hide-scrollbars")
    assert drawn.returncode == 0 and shot.is_file(), drawn.stderr[-2000:]
    assert image_header(shot)[0] == 1400  # the page drawn at the width its layout is meant for
    return dom


def test_report_loads_in_chromium(demo_dir, tmp_path):
    dom = _check_page(tmp_path, demo_dir / "result" / "report.html")
    assert "Parameter maps" in dom and "DoP validation" in dom


def test_demo_index_loads_in_chromium(demo_dir, metrics, tmp_path):
    page = demo_index_page(demo_dir, "preset tiny", metrics).write(demo_dir / "index.html")
    dom = _check_page(tmp_path, page)
    assert "<th>target</th>" in dom and "comparison/eta.png" in dom


def test_dynamic_section_loads_in_chromium(tmp_path):
    from dynamic_fixtures import write_dynamic_result
    from polarface.report import HtmlPage, dynamic_section

    root = write_dynamic_result(tmp_path / "result", frames=4, failed={1: "tracking lost"})
    page = HtmlPage("dynamic sequence")
    dynamic_section(page, root)
    dom = _check_page(tmp_path, page.write(root / "report.html"))
    assert "previews/dynamic_c_h_out.gif" in dom and "failed: tracking lost" in dom
