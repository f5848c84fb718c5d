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
    assert list(METRIC_GROUPS) == ["polarimetric", "rerender", "biophysical", "geometry", "dynamic"]
    assert evaluate(tmp_path, tmp_path, ["biophysical"]) == {
        "biophysical": {"skipped": "the RESULT has no biophysical maps (stage not run)"}
    }


def test_resolve_reconstruct_inputs_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        resolve_reconstruct_inputs(tmp_path / "nope")
    with pytest.raises(ValueError, match="not a capture store"):
        resolve_reconstruct_inputs(tmp_path)
    (tmp_path / "manifest.json").write_text(json.dumps({}))
    stereo = resolve_reconstruct_inputs(tmp_path)  # no geometry given: the stereo geometry stage
    assert stereo.mesh_path is None and stereo.poses_path is None and stereo.geometry_dir is None
    with pytest.raises(ValueError, match="together"):
        resolve_reconstruct_inputs(tmp_path, mesh=tmp_path / "m.obj")
    with pytest.raises(ValueError, match="cannot be combined"):
        resolve_reconstruct_inputs(tmp_path, geometry=tmp_path, mesh=tmp_path / "m", poses=tmp_path / "p")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match=r"neither geometry\.json"):
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


def _keys(value, prefix=""):
    """Every key path of a nested dict."""
    if not isinstance(value, dict):
        return []
    return [p for k, v in value.items() for p in [prefix + k, *_keys(v, prefix + k + ".")]]


def test_evaluate_json_uses_one_naming_scheme(tmp_path, monkeypatch):
    """The biophysical group's ``median_abs`` etc. become ``median_abs_error`` and its alias is dropped."""
    import importlib

    evaluate_module = importlib.import_module("polarface.pipeline.evaluate")  # the package shadows the name
    fake = {
        "texels": 9,
        "c_m": {"median_abs_error": 0.1, "mean_abs_error": 0.2, "p95_abs_error": 0.3},
        "rho_sss_bar_relative_rmse": 0.01,
        "rerender_vs_gt_relative_rmse": 0.02,
    }
    monkeypatch.setattr(evaluate_module, "evaluate_biophysical", lambda result, gt: fake)
    for root in (tmp_path / "result", tmp_path / "gt"):
        (root / "maps").mkdir(parents=True)
        (root / "maps" / "c_m.exr").write_bytes(b"")
    ResultFolder(tmp_path / "result").update_result({"format": "polarface-result"})
    metrics = evaluate(tmp_path / "result", tmp_path / "gt", ["biophysical"])["biophysical"]
    assert metrics == {
        "texels": 9,
        "c_m": {"median_abs_error": 0.1, "mean_abs_error": 0.2, "p95_abs_error": 0.3},
        "rho_sss_bar_relative_rmse": 0.01,
        "rerender_vs_gt_relative_rmse": 0.02,
    }
    assert not [k for k in _keys(metrics) if k.endswith("_abs")]
