"""The metric groups' registry and driver (``polarface.evaluate.groups``): arguments, naming scheme."""

from __future__ import annotations

import pytest

from polarface.evaluate import METRIC_GROUPS, evaluate
from polarface.results import ResultFolder


def test_evaluate_checks_its_arguments(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"result\.json"):
        evaluate(tmp_path, tmp_path)
    ResultFolder(tmp_path).update_result({"format": "polarface-result"})
    (tmp_path / "maps").mkdir()
    with pytest.raises(ValueError, match="unknown \\['nope'\\]"):
        evaluate(tmp_path, tmp_path, ["nope"])
    assert list(METRIC_GROUPS) == [
        "polarimetric", "rerender", "biophysical", "geometry", "dynamic", "validation",
    ]
    assert evaluate(tmp_path, tmp_path, ["biophysical"]) == {
        "biophysical": {"skipped": "the RESULT has no biophysical maps (stage not run)"}
    }


def _keys(value, prefix=""):
    """Every key path of a nested dict."""
    if not isinstance(value, dict):
        return []
    return [p for k, v in value.items() for p in [prefix + k, *_keys(v, prefix + k + ".")]]


def test_evaluate_json_uses_one_naming_scheme(tmp_path, monkeypatch):
    """The biophysical group's ``median_abs`` etc. become ``median_abs_error`` and its alias is dropped."""
    import importlib

    biophysical_module = importlib.import_module("polarface.evaluate.biophysical")
    fake = {
        "texels": 9,
        "c_m": {"median_abs_error": 0.1, "mean_abs_error": 0.2, "p95_abs_error": 0.3},
        "rho_sss_bar_relative_rmse": 0.01,
        "rerender_vs_gt_relative_rmse": 0.02,
    }
    monkeypatch.setattr(biophysical_module, "evaluate_biophysical", lambda result, gt: fake)
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
