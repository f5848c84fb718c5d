"""Library entry points of the pipeline: input resolution, evaluation arguments, demo arguments."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from polarface.pipeline import (
    METRIC_GROUPS,
    evaluate,
    ground_truth_root,
    reconstruct_summary_line,
    resolve_reconstruct_inputs,
    run_sphere_demo,
)
from polarface.results import ResultFolder


def test_ground_truth_root(tmp_path):
    (tmp_path / "sim" / "ground_truth" / "maps").mkdir(parents=True)
    assert ground_truth_root(tmp_path / "sim") == tmp_path / "sim" / "ground_truth"
    assert ground_truth_root(tmp_path / "sim" / "ground_truth") == tmp_path / "sim" / "ground_truth"
    with pytest.raises(FileNotFoundError, match="ground-truth maps"):
        ground_truth_root(tmp_path)


def test_evaluate_checks_its_arguments(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"result\.json"):
        evaluate(tmp_path, tmp_path)
    ResultFolder(tmp_path).update_result({"format": "polarface-result"})
    (tmp_path / "maps").mkdir()
    with pytest.raises(ValueError, match="unknown \\['nope'\\]"):
        evaluate(tmp_path, tmp_path, ["nope"])
    assert list(METRIC_GROUPS) == ["polarimetric", "rerender", "biophysical"]
    assert evaluate(tmp_path, tmp_path, ["biophysical"]) == {
        "biophysical": {"skipped": "the RESULT has no biophysical maps (stage not run)"}
    }


def test_resolve_reconstruct_inputs_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        resolve_reconstruct_inputs(tmp_path / "nope")
    with pytest.raises(ValueError, match="not a capture store"):
        resolve_reconstruct_inputs(tmp_path)
    (tmp_path / "manifest.json").write_text(json.dumps({}))
    with pytest.raises(ValueError, match="no geometry"):
        resolve_reconstruct_inputs(tmp_path)
    with pytest.raises(ValueError, match="together"):
        resolve_reconstruct_inputs(tmp_path, mesh=tmp_path / "m.obj")


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
