"""The model comparison job (``polarface.pipeline.model_comparison``, benchmarks/bench_model_comparison.py)
on the tiny preset: the machinery (one RESULT per model on one surface, scored on the validation camera,
the ladder and ratios, a rerun that keeps the RESULTs); the numbers are the demo's (docs/validation.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from chromium_page import NEEDS_CHROMIUM, check_page
from polarface.pipeline import ComparisonConfig, compare_models, format_comparison
from polarface.pipeline.model_comparison import free_pass_source
from polarface.results import ResultFolder

NAMES = ("paper", "homogeneous-ior", "no-single-scattering", "hwang2022")
CONFIG = ComparisonConfig(preset="tiny", models=NAMES, geometry="known", fit_options={"iterations": 20})


@pytest.fixture(scope="module")
def compared(tmp_path_factory):
    out = tmp_path_factory.mktemp("comparison")
    return out, compare_models(out, CONFIG, progress=False)


@pytest.mark.slow
def test_four_models_on_the_known_surface(compared):
    tmp_path, summary = compared
    names, config = NAMES, CONFIG
    assert json.loads((tmp_path / "comparison.json").read_text()) == json.loads(json.dumps(summary))
    models = summary["models"]
    assert list(models) == list(names)
    for row in models.values():
        assert 0 < row["specular_rmse"] < row["full_rmse"] < 0.5 and row["seconds"] > 0
    record = ResultFolder(tmp_path / "homogeneous-ior").stage_record("polarimetric")
    assert record["model"] == "homogeneous-ior" and set(record["homogeneous_values"]) == {"eta"}
    # its free pass is the paper's fit, taken from that RESULT rather than fitted again
    paper = ResultFolder(tmp_path / "paper")
    median = float(np.median(paper.read_scalar_map("eta")[paper.read_mask()]))
    assert record["homogeneous_values"]["eta"] == pytest.approx(median, abs=1e-5)
    clustered = ResultFolder(tmp_path / "hwang2022").stage_record("polarimetric")
    assert clustered["model"] == "hwang2022" and sum(clustered["clusters"]["texels"]) == clustered["texels"]
    assert summary["ablation"] is None  # Table 4's first row was not run
    assert summary["comparison"] is None  # nor Riviere et al.'s model
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


@pytest.mark.slow
@NEEDS_CHROMIUM
def test_the_comparison_page_loads_in_chromium(compared, tmp_path):
    out, summary = compared
    dom = check_page(tmp_path, out / "comparison.html")
    assert "Model comparison" in dom and "no-single-scattering / paper specular RMSE" in dom
    for name in summary["models"]:
        assert f"figures/{name}_validation.png" in dom and f"figures/{name}_rho_s.png" in dom


def test_bad_configurations_are_refused():
    with pytest.raises(ValueError, match="argument 'models'"):
        ComparisonConfig(models=("paper", "hwang"))
    with pytest.raises(ValueError, match="argument 'geometry'"):
        ComparisonConfig(geometry="photogrammetry")
    with pytest.raises(ValueError, match="lobes"):
        ComparisonConfig(models=("no-single-scattering",), fit_options={"lobes": "two"})


def test_the_free_pass_comes_from_the_variant_with_its_options():
    assert free_pass_source("paper", ["no-single-scattering"]) is None  # one pass
    assert free_pass_source("homogeneous-ior", ["no-single-scattering", "paper"]) == "paper"
    assert free_pass_source("riviere2020", ["paper", "no-single-scattering"]) == "no-single-scattering"
    assert free_pass_source("homogeneous-ior-no-single-scattering", ["paper"]) is None  # not run before
    assert free_pass_source("hwang2022", ["paper"]) == "paper"
