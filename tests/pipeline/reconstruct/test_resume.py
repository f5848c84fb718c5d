"""Interrupt (SIGKILL) then resume gives the same files as an uninterrupted run: simulate (tiny
preset); the simulate ``resume`` argument and the configuration recorded when a run starts."""

from __future__ import annotations

import hashlib
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from polarface.simulate.pipeline import SimulationConfig, simulate

SRC = Path(__file__).resolve().parents[3] / "src"
_SCRIPT = """
import sys
from polarface.simulate.pipeline import SimulationConfig, simulate
simulate(sys.argv[1], SimulationConfig(preset="tiny", sequences=("static",), noise=False), progress=False)
"""


def _run(out: Path, kill_when: Path | None = None, delay: float = 0.0) -> None:
    env = {**os.environ, "PYTHONPATH": f"{SRC}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    process = subprocess.Popen([sys.executable, "-c", _SCRIPT, str(out)], env=env)
    if kill_when is None:
        assert process.wait(timeout=600) == 0
        return
    deadline = time.monotonic() + 300
    while not kill_when.exists() and process.poll() is None:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    time.sleep(delay)
    process.send_signal(signal.SIGKILL)
    process.wait(timeout=60)


def _tree(root: Path) -> dict[str, str]:
    out = {}
    for path in sorted(root.rglob("*")):
        if not path.is_file():
            continue
        data = path.read_bytes()
        if path.name == "simulation.json":  # timings, peak memory, where frames ran differ between runs
            summary = json.loads(data)
            summary.pop("timings"), summary.pop("peak_rss_mb"), summary.pop("executor")
            data = json.dumps(summary, sort_keys=True).encode()
        out[path.relative_to(root).as_posix()] = hashlib.sha256(data).hexdigest()
    return out


@pytest.mark.slow
def test_simulate_sigkill_then_resume_gives_the_same_files(tmp_path):
    straight, killed = tmp_path / "straight", tmp_path / "killed"
    _run(straight)
    delay = random.Random(os.getpid()).uniform(0.0, 2.0)
    _run(killed, kill_when=killed / "static" / "frames" / "000000.json", delay=delay)
    recorded = json.loads((killed / "simulation.json").read_text())
    assert recorded["complete"] is False and recorded["config"]["preset"] == "tiny"
    with pytest.raises(ValueError, match="another configuration"):  # refused before it finished
        simulate(killed, SimulationConfig(preset="tiny", sequences=("static",), seed=3), progress=False)
    _run(killed)
    assert not list(killed.rglob(".tmp-*"))
    assert _tree(killed) == _tree(straight)
    assert json.loads((killed / "simulation.json").read_text())["complete"] is True


def test_simulate_without_resume_refuses_a_non_empty_folder(tmp_path):
    (tmp_path / "x").write_text("x")
    with pytest.raises(ValueError, match="exists and is not empty; pass '--resume'"):
        simulate(tmp_path, SimulationConfig(preset="tiny"), progress=False, resume=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x"]
