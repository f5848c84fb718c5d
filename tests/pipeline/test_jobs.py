"""Library entry points of the pipeline: input resolution and demo arguments."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from polarface.pipeline import reconstruct_summary_line, resolve_reconstruct_inputs, run_sphere_demo


def test_resolve_reconstruct_inputs_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        resolve_reconstruct_inputs(tmp_path / "nope")
    with pytest.raises(ValueError, match="not a capture store"):
        resolve_reconstruct_inputs(tmp_path)
    (tmp_path / "manifest.json").write_text(json.dumps({}))
    stereo = resolve_reconstruct_inputs(tmp_path)  # no geometry given: the stereo geometry stage
    assert stereo.mesh_path is None and stereo.poses_path is None and stereo.geometry_folder is None
    with pytest.raises(ValueError, match="together"):
        resolve_reconstruct_inputs(tmp_path, mesh=tmp_path / "m.obj")
    with pytest.raises(ValueError, match="cannot be combined"):
        resolve_reconstruct_inputs(tmp_path, geometry=tmp_path, mesh=tmp_path / "m", poses=tmp_path / "p")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"not a GEOM folder or a simulation's ground_truth folder"):
        resolve_reconstruct_inputs(tmp_path, geometry=tmp_path / "empty")


def test_summary_line():
    record = {"stages": {"polarimetric": {"texels": 12, "throughput_texel_view_iterations_per_s": 1234.5}}}
    line = reconstruct_summary_line("R", record)
    expected = "polarface reconstruct: wrote R (12 texels, 1.23e+03 texel-view it/s); report: R/report.html"
    assert line == expected
    assert reconstruct_summary_line(Path("out") / "R", {}).endswith(str(Path("out") / "R" / "report.html"))


def test_sphere_demo_bad_arguments_write_nothing(tmp_path):
    with pytest.raises(ValueError, match="--size"):
        run_sphere_demo(tmp_path / "x", size=4)
    with pytest.raises(ValueError, match="--eta"):
        run_sphere_demo(tmp_path / "x", size=16, eta=1.0)
    assert not (tmp_path / "x").exists()
