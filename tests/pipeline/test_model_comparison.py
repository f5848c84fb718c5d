"""The model comparison job (``polarface.pipeline.model_comparison``, benchmarks/bench_model_comparison.py)
on the tiny preset: the machinery (one RESULT per model on one surface, scored on the validation camera,
the ladder and ratios, a rerun that keeps the RESULTs); the numbers are the demo's (docs/validation.md)."""

from __future__ import annotations

import json

import pytest

from polarface.pipeline import ComparisonConfig, compare_models, format_comparison
from polarface.results import ResultFolder


@pytest.mark.slow
def test_three_models_on_the_known_surface(tmp_path):
    config = ComparisonConfig(preset="tiny", models=("homogeneous-ior", "paper", "no-single-scattering"),
                              geometry="known", fit_options={"iterations": 20})
    summary = compare_models(tmp_path, config, progress=False)
    assert json.loads((tmp_path / "comparison.json").read_text()) == json.loads(json.dumps(summary))
    models = summary["models"]
    assert list(models) == ["homogeneous-ior", "paper", "no-single-scattering"]
    for row in models.values():
        assert 0 < row["specular_rmse"] < row["full_rmse"] < 0.5 and row["seconds"] > 0
    record = ResultFolder(tmp_path / "homogeneous-ior").stage_record("polarimetric")
    assert record["model"] == "homogeneous-ior" and set(record["homogeneous_values"]) == {"eta"}
    assert summary["ablation"] is None  # Table 4's first row was not run
    assert summary["no_single_scattering_over_paper"] == pytest.approx(
        models["no-single-scattering"]["specular_rmse"] / models["paper"]["specular_rmse"])
    text = format_comparison(summary)
    assert "homogeneous-ior" in text and "no-single-scattering / paper" in text
    page = (tmp_path / "comparison.html").read_text()
    for name in models:
        assert f"figures/{name}_eta.png" in page and f"figures/{name}_validation.png" in page
        assert (tmp_path / "figures" / f"{name}_validation.png").is_file()
    # a rerun keeps the finished RESULTs and gives the same scores
    again = compare_models(tmp_path, config, progress=False)
    for name, row in again["models"].items():
        assert {k: v for k, v in row.items() if k != "seconds"} == {
            k: v for k, v in models[name].items() if k != "seconds"}


def test_bad_configurations_are_refused():
    with pytest.raises(ValueError, match="argument 'models'"):
        ComparisonConfig(models=("paper", "hwang2022"))
    with pytest.raises(ValueError, match="argument 'geometry'"):
        ComparisonConfig(geometry="photogrammetry")
    with pytest.raises(ValueError, match="lobes"):
        ComparisonConfig(models=("no-single-scattering",), fit_options={"lobes": "two"})
