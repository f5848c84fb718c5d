"""``--executor ray --ray-address ADDR`` on ``ingest``, ``simulate``, ``geometry`` and ``reconstruct``
(whose geometry stage runs its frames on the executor): an address where nothing answers is refused
within seconds with one line naming the argument, and nothing is written."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import pytest

from polarface.capture.rig import paper_rig
from polarface.cli import main
from polarface.simulate.sphere_capture import SphereCaptureConfig, make_sphere_capture


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    """A sphere capture (its stereo pairs rectify) and a rig.json."""
    root = tmp_path_factory.mktemp("cli_executors")
    make_sphere_capture(root / "sphere", SphereCaptureConfig(texture_resolution=16, frames=2))
    paper_rig(width=48, height=32).save(root / "rig.json")
    return {"capture": root / "sphere" / "static", "rig": root / "rig.json", "raw": root / "raw"}


def _unreachable() -> str:
    with socket.socket() as probe:  # a port nobody listens on
        probe.bind(("127.0.0.1", 0))
        return f"127.0.0.1:{probe.getsockname()[1]}"


@pytest.mark.parametrize("command", ["ingest", "simulate", "geometry", "reconstruct"])
def test_an_unreachable_ray_address_is_refused_within_seconds_and_nothing_is_written(
        command, inputs, tmp_path, capsys):
    pytest.importorskip("ray")
    out = tmp_path / "out"
    arguments = {
        "ingest": [str(inputs["raw"]), "--rig", str(inputs["rig"]), "--no-progress"],
        "simulate": ["--preset", "tiny"],
        "geometry": [str(inputs["capture"]), "--quiet"],
        "reconstruct": [str(inputs["capture"]), "--quiet"],
    }[command]
    address = _unreachable()
    started = time.perf_counter()
    assert main([command, *arguments, "--out", str(out), "--executor", "ray", "--ray-address", address]) == 2
    assert time.perf_counter() - started < 15.0
    error = capsys.readouterr().err
    assert f"'--ray-address': no Ray cluster answers at '{address}'" in error and error.count("\n") == 1
    assert list(tmp_path.iterdir()) == []  # no output, no lock beside it
