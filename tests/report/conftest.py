"""A small demo folder with a real report, built without the (slow) polarimetric fit.

``demo_dir`` holds ``sim/`` (a 4-frame sphere capture, 16^2 texture), ``result/`` (the prepare stage
run for real; the polarimetric maps are the ground truth slightly perturbed; ``report.html`` written by
:func:`polarface.report.write_report`) and ``metrics.json``.
"""

from __future__ import annotations

import importlib
import json

import numpy as np
import pytest

from polarface.pipeline import ReconstructContext, run_stages
from polarface.report import write_report
from polarface.results import POLARIMETRIC_MAPS, RHO_SSS_BAR, ResultFolder
from polarface.simulate.sphere_capture import SphereCaptureConfig, make_sphere_capture

RES = 16

#: Metrics of the fixture: some targets met, some missed, one group skipped.
METRICS = {
    "polarimetric": {
        "texels": 100,
        "eta": {"median_abs_error": 0.0123456, "mean_abs_error": 0.02, "gt_median": 1.4},
        "alpha_s": {"median_abs_error": 0.08, "mean_abs_error": 0.1, "gt_median": 0.5},
        "rho_s": {"median_abs_error": 0.01, "mean_abs_error": 0.01, "gt_median": 0.1,
                  "median_relative_error": 0.194},
        RHO_SSS_BAR: {"median_abs_error": 0.01, "mean_abs_error": 0.01, "gt_median": 0.4,
                      "median_relative_error": 0.0177},
        "normal_angular_error_deg": {"median_abs_error": 0.5912, "mean_abs_error": 0.8},
    },
    "rerender": {"held_out_views": 2, "samples": 10, "i_sss_rmse": 0.027, "i_s_rmse": 0.0152,
                 "i_s_rmse_over_mean_abs": 0.3, "normalisation": "text"},
    "biophysical": {"skipped": "the RESULT has no biophysical maps (stage not run)"},
}


def _fake_polarimetric_stage(sim, result) -> None:
    truth = ResultFolder(sim / "ground_truth")
    folder = ResultFolder(result)
    maps = truth.read_maps(folder.channel_names())
    mask = maps.pop("mask")
    estimate = {n: (maps[n] * 1.02).astype(np.float32) for n in (*POLARIMETRIC_MAPS, RHO_SSS_BAR)}
    view_count = np.where(mask, 8.0, 0.0).astype(np.float32)
    folder.write_polarimetric_maps(estimate, mask, {"view_count": view_count})
    folder.record_stage("polarimetric", {"texels": int(mask.sum()), "config": {"min_views": 4}})


@pytest.fixture(scope="package")
def demo_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    sim, result = out / "sim", out / "result"
    make_sphere_capture(sim, SphereCaptureConfig(texture_resolution=RES, frames=4))
    result.mkdir()
    stage_prepare = importlib.import_module("polarface.pipeline.reconstruct.stages").stage_prepare
    context = ReconstructContext(
        sim / "static", result, sim / "ground_truth" / "mesh_rest.obj",
        sim / "ground_truth" / "static" / "poses.json", RES, "cpu", False, False, 4,
    )
    run_stages(context, [("prepare", stage_prepare)])
    _fake_polarimetric_stage(sim, result)
    write_report(result)
    (out / "metrics.json").write_text(json.dumps(METRICS))
    return out


@pytest.fixture
def metrics():
    """:data:`METRICS`, a fresh copy."""
    return json.loads(json.dumps(METRICS))
