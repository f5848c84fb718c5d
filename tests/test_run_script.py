"""run.sh's set-up of the system libraries Open3D links (its ``system_libraries`` function, taken from
the script itself), with a stand-in ``open3d`` that fails to load as the real one does on a bare Debian."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="run.sh is a bash script")

ROOT = Path(__file__).resolve().parents[1]
MISSING = "libusb-1.0.so.0: cannot open shared object file: No such file or directory"


def _system_libraries(tmp_path: Path, fake: Path | None = None) -> subprocess.CompletedProcess:
    """Run run.sh's ``system_libraries`` with this interpreter (and its ``sys.path``) as
    ``$VENV/bin/python``; ``fake``: a folder put first on ``PATH`` and ``PYTHONPATH``."""
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    (venv / "bin" / "python").symlink_to(sys.executable)
    script = (ROOT / "run.sh").read_text()
    function = script[script.index("system_libraries() {"):]
    function = function[: function.index("\n}\n") + 3]
    first = [str(fake)] if fake else []
    env = {**os.environ, "PATH": os.pathsep.join([*first, os.environ["PATH"]]),
           "PYTHONPATH": os.pathsep.join([*first, *sys.path])}
    return subprocess.run(["bash", "-c", f'set -euo pipefail\nVENV="{venv}"\n{function}system_libraries'],
                          env=env, capture_output=True, text=True, timeout=120)


def test_a_missing_library_stops_the_set_up_with_the_packages_named(tmp_path):
    fake = tmp_path / "fake"
    fake.mkdir()
    (fake / "open3d.py").write_text(f"raise ImportError({MISSING!r})\n")
    (fake / "id").write_text("#!/bin/sh\necho 1000\n")  # not root: apt-get is not tried
    (fake / "id").chmod(0o755)
    run = _system_libraries(tmp_path, fake)
    assert run.returncode != 0
    assert "run.sh: Open3D (used by the geometry stage) could not be loaded: " + MISSING in run.stderr
    assert "apt-get install libusb-1.0-0 libudev1 libegl1 libgl1 libx11-6 libidn2-0" in run.stderr
    assert "Traceback" not in run.stderr  # one clear line, not a stack


def test_a_loadable_open3d_passes_the_set_up(tmp_path):
    run = _system_libraries(tmp_path)
    assert run.returncode == 0, run.stderr
    assert run.stderr == ""
