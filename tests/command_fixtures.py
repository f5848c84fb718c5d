"""Small RESULT folders for the command tests (tests/commands), built in milliseconds (no simulation, no
fit), and helpers to compare folders and read the CLI's error lines.

:func:`write_command_result` is :func:`disk_fixtures.write_plane_result` (a 60 mm skin plane facing the
polarimetric module, constant maps, 16^2 texels) completed into what ``export`` and ``biophysical`` read: a
``result.json`` header and the six-channel ``maps/rho_sss_bar.exr``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from disk_fixtures import write_plane_result
from polarface.capture.rig import paper_rig
from polarface.results import RESULT_FORMAT, RESULT_VERSION, RHO_SSS_BAR, ResultFolder

__all__ = ["RESOLUTION", "error_lines", "files", "write_command_result"]

RESOLUTION = 16


def write_command_result(root: Path) -> Path:
    """The plane RESULT of the module docstring at ``root``."""
    result = write_plane_result(root, cells=4, resolution=RESOLUTION, width=48, height=40)
    names = list(paper_rig().spectral.channel_names)
    ResultFolder(result).write_channel_map(RHO_SSS_BAR, np.full((RESOLUTION, RESOLUTION, 6), 0.4, np.float32),
                                           names)
    header = {"format": RESULT_FORMAT, "version": RESULT_VERSION, "channel_names": names,
              "texture_resolution": [RESOLUTION, RESOLUTION], "stages": {}}
    (result / "result.json").write_text(json.dumps(header))
    return result


def files(root: Path) -> dict[str, bytes]:
    """Every file under ``root``: relative path -> content (to compare a folder before and after)."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def error_lines(err: str) -> list[str]:
    """stderr without tqdm's progress frames, argparse's usage block and log lines."""
    lines = [line for segment in err.replace("\r", "\n").splitlines() if (line := segment.strip())]
    lines = [line for line in lines if "%|" not in line and " INFO " not in line]
    if lines and lines[0].startswith("usage:"):
        lines = [line for line in lines[1:] if line.startswith("polarface")]
    return lines
