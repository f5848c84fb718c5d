"""``simulate`` with its frames as executor units on Ray (2 workers of a local Ray instance) and in 2
worker processes against the local executor, on a small tiny-preset simulation (2 static + 2 dynamic
frames): the same bytes, a killed worker's frame rerun, a stopped run resumed from the frames already
written."""

from __future__ import annotations

import hashlib
import json
import threading
import time
from pathlib import Path

import pytest

from polarface.executors import ProcessExecutor, RayExecutor
from polarface.simulate.pipeline import SimulationConfig, simulate
from ray_fixtures import RAY_CPUS, ray_instance, ray_worker_running_a_unit  # noqa: F401 (fixture)

pytestmark = pytest.mark.slow

CONFIG = SimulationConfig(preset="tiny", static_frames=2)


def _tree(root: Path) -> dict[str, str]:
    """Digests of every file of a simulation folder but ``simulation.json`` (timings, placements)."""
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and p.name != "simulation.json"}


@pytest.fixture(scope="module")
def local(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    """The simulation by the local executor and its files' digests."""
    out = tmp_path_factory.mktemp("simulate_executors") / "local"
    summary = simulate(out, CONFIG, progress=False)
    assert summary["executor"]["name"] == "local"
    assert sorted(summary["executor"]["units"]) == ["dynamic/0", "dynamic/1", "static/0", "static/1"]
    return out, _tree(out)


def test_ray_frames_are_the_local_executor_bytes(local, ray_instance, tmp_path):  # noqa: F811
    summary = simulate(tmp_path / "ray", CONFIG, progress=False, executor=RayExecutor(workers=RAY_CPUS))
    assert _tree(tmp_path / "ray") == local[1]
    units = summary["executor"]["units"]
    assert summary["executor"]["name"] == "ray"
    # every frame is a unit, the exposure frame too: this process rendered only its exposure view
    assert all(units[key]["node_id"] and units[key]["render_s"] > 0
               for key in ("static/0", "static/1", "dynamic/0", "dynamic/1"))
    assert summary["timings"]["exposure_s"] > 0 and summary["timings"]["frames_s"] > 0
    assert summary["exposures"] == json.loads((local[0] / "simulation.json").read_text())["exposures"]


def test_process_frames_are_the_local_executor_bytes(local, tmp_path):
    with ProcessExecutor(workers=2, threads_per_worker=1) as executor:
        summary = simulate(tmp_path / "processes", CONFIG, progress=False, executor=executor)
    assert _tree(tmp_path / "processes") == local[1]  # the workers' scene file is gone too
    units = summary["executor"]["units"]
    assert summary["executor"]["name"] == "processes"
    assert {units[key]["pid"] for key in ("static/0", "static/1", "dynamic/0", "dynamic/1")} - {None} != set()


def test_a_killed_worker_is_retried_and_the_files_are_identical(local, ray_instance, tmp_path):  # noqa: F811
    out = tmp_path / "ray"
    summaries = []
    run = threading.Thread(target=lambda: summaries.append(
        simulate(out, CONFIG, progress=False, executor=RayExecutor(workers=RAY_CPUS))))
    run.start()
    victim = ray_worker_running_a_unit(300)
    time.sleep(1.0)  # mid-frame: building the scene or rendering, perhaps writing
    victim.kill()
    run.join(timeout=600)
    assert not run.is_alive() and summaries, "the run did not finish"
    assert victim.pid not in {unit["pid"] for unit in summaries[0]["executor"]["units"].values()}
    assert _tree(out) == local[1]


class _Stop(Exception):
    """Stands for Ctrl-C in the submitting process."""


class _StopAtFirstDynamicFrame(RayExecutor):
    """A Ray executor whose submitting process stops as soon as a dynamic frame finishes (the other one,
    still running, is cancelled: its worker is killed wherever it is)."""

    def map_units(self, fn, units, **options):
        on_done = options.pop("on_done")

        def done(outcome):
            on_done(outcome)
            if outcome.unit.sequence == "dynamic":
                raise _Stop

        return super().map_units(fn, units, on_done=done, **options)


def test_a_stopped_run_resumes_from_the_frames_written(local, ray_instance, tmp_path):  # noqa: F811
    out = tmp_path / "ray"
    with pytest.raises(_Stop):
        simulate(out, CONFIG, progress=False, executor=_StopAtFirstDynamicFrame(workers=RAY_CPUS))
    assert not json.loads((out / "simulation.json").read_text())["complete"]
    kept = {p: p.stat().st_mtime_ns for p in sorted((out / "static" / "raw").rglob("*.png"))}
    static_done = sorted(p.name for p in (out / "static" / "frames").glob("*.json"))
    assert static_done == ["000000.json", "000001.json"]
    summary = simulate(out, CONFIG, progress=False, executor=RayExecutor(workers=RAY_CPUS))
    assert summary["complete"] and _tree(out) == local[1]
    assert {p: p.stat().st_mtime_ns for p in kept} == kept  # the static frames were not redone
    resumed = list(summary["executor"]["units"])  # this run's units: the dynamic frame left
    assert len(resumed) == 1 and resumed[0].startswith("dynamic/")
