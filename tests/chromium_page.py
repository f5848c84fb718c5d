"""A page loaded from disk (``file://``) in headless Chromium (Debian's ``chromium``) and checked: it
loads, the browser logs no console error (uncaught exception, resource that failed to load), every
``<img>`` of the rendered DOM resolves to a file on disk, and a 1400 px wide screenshot is drawn
(:func:`check_page`). Tests that use it skip, with the reason, where no Chromium is installed
(:data:`NEEDS_CHROMIUM`)."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path
from urllib.parse import unquote

import pytest

from chromium_pipe import CHROMIUM
from polarface.io import image_header

NEEDS_CHROMIUM = pytest.mark.skipif(
    CHROMIUM is None,
    reason="headless Chromium is not installed (Debian package 'chromium'): the page was not loaded in a "
    "browser",
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


def check_page(tmp_path: Path, page: Path) -> str:
    """Load ``page`` and check it (module docstring), Chromium's profile and screenshot in ``tmp_path``;
    returns the rendered DOM."""
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
