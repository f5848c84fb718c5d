"""The calibration check (``polarface.pipeline.calibration_check``, benchmarks/bench_rig_calibration.py) on
the tiny preset: a perturbed rig calibrated from its session comes within the targets of the true rig,
its capture reconstructed with the calibrated rig lies nearer the true rig's reconstruction than with the
nominal one; the demo's numbers are in docs/calibration.md."""

from __future__ import annotations

import json

import pytest

from polarface.pipeline import CalibrationCheckConfig, check_calibration, format_calibration_check


@pytest.mark.slow
def test_the_calibrated_rig_reconstructs_like_the_true_one(tmp_path):
    config = CalibrationCheckConfig(preset="tiny", seed=1, geometry="known", fit_options={"iterations": 20})
    summary = check_calibration(tmp_path, config, progress=False)
    assert json.loads((tmp_path / "calibration_check.json").read_text()) == json.loads(json.dumps(summary))
    rigs = summary["rigs"]
    assert list(rigs) == ["true", "calibrated", "nominal"]
    calibrated, nominal = rigs["calibrated"]["rig_errors"], rigs["nominal"]["rig_errors"]
    assert calibrated["light_position_mm"] < 2.0 < nominal["light_position_mm"]
    assert calibrated["gain"] < 0.005 < nominal["gain"]
    assert calibrated["intensity"] < 0.01 < nominal["intensity"]
    assert calibrated["response_peak_nm"] < 2.0
    assert calibrated["response_shape"] < 0.03 < nominal["response_shape"]
    assert all(value == 0.0 for value in rigs["true"]["rig_errors"].values())
    # the albedo follows the gains and intensities: calibrated, it stays by the true rig's
    differences = {name: rigs[name]["differences_from_true_rig"] for name in ("calibrated", "nominal")}
    assert differences["calibrated"]["rho_sss_bar"] < 0.01 < differences["nominal"]["rho_sss_bar"]
    assert differences["calibrated"]["eta"] < 0.003
    text = format_calibration_check(summary)
    assert all(name in text for name in rigs)


def test_bad_configurations_are_refused():
    with pytest.raises(ValueError, match="argument 'geometry'"):
        CalibrationCheckConfig(geometry="photogrammetry")
    with pytest.raises(ValueError, match="'seed'"):
        CalibrationCheckConfig(seed=-1)
    with pytest.raises(ValueError, match="preset"):
        CalibrationCheckConfig(preset="huge")
