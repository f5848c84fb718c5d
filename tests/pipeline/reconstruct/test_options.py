"""The fit options a reconstruction takes: the patch grid (pipeline.reconstruct.options._patch_grid,
_units_per_gpu) and the optimiser the reference surface calls for (surface_fit_options)."""

from __future__ import annotations

import json

import pytest

import polarface.inverse.polarimetric as polarimetric
from polarface.executors import LocalExecutor, ProcessExecutor
from polarface.pipeline.reconstruct import UNVERIFIED_SURFACE_FIT_OPTIONS, surface_fit_options
from polarface.pipeline.reconstruct.options import _patch_grid, _units_per_gpu


class _Ray:  # the attributes of RayExecutor that matter here
    def __init__(self, gpus_per_unit: float, workers: int | None = None):
        self.gpus_per_unit, self.workers = gpus_per_unit, workers


@pytest.mark.parametrize(
    ("executor", "units"),
    [(None, 1), (LocalExecutor(), 1), (ProcessExecutor(3), 3), (_Ray(1.0), 1), (_Ray(2.0), 1),
     (_Ray(0.25), 4), (_Ray(0.0, workers=2), 2)],
)
def test_units_sharing_one_gpu(executor, units):
    assert _units_per_gpu(executor) == units


def test_the_grid_comes_from_the_device_or_from_the_resumed_result(tmp_path, monkeypatch):
    seen = []

    def fake(device, units_per_gpu=1):
        seen.append((str(device), units_per_gpu))
        return {"patch": 256, "sample_budget": 1_000_000 // units_per_gpu}

    monkeypatch.setattr(polarimetric, "device_fit_options", fake)
    assert _patch_grid("cpu", ProcessExecutor(2), tmp_path / "new", resume=False) == {
        "patch": 256, "sample_budget": 500_000
    }
    assert seen == [("cpu", 2)]
    # a resume of a folder without a result yet: the device's
    assert _patch_grid("cpu", None, tmp_path / "new", resume=True)["sample_budget"] == 1_000_000
    # a resume keeps the grid the RESULT recorded, whatever the device says now
    out = tmp_path / "started"
    out.mkdir()
    grid = {"patch": 64, "sample_budget": 300_000}
    record = {"fingerprint": {"options": grid}}
    (out / "result.json").write_text(json.dumps(record))
    assert _patch_grid("cpu", None, out, resume=True) == {"patch": 64, "sample_budget": 300_000}


def test_the_optimiser_follows_the_reference_surface():
    options = {"patch": 64, "sample_budget": 300_000}
    refined = {"surface_refinement": {"applied": True, "not_applied_reason": None}}
    unrefined = {"surface_refinement": {"applied": False,
                                        "not_applied_reason": "12 % of the texels measured"}}
    # known geometry (no geometry.json) and a surface the images verified: the config's L-BFGS
    assert surface_fit_options(options, False, {}) == (options, "known geometry")
    assert surface_fit_options(options, False, refined)[0] == options
    # a stereo surface not refined, or refinement switched off: RMSprop for 150 steps, and why
    chosen, why = surface_fit_options(options, False, unrefined)
    assert chosen == {**options, **UNVERIFIED_SURFACE_FIT_OPTIONS} and chosen["optimizer"] == "rmsprop"
    assert "12 % of the texels measured" in why
    assert surface_fit_options(options, False, {"surface_refinement": None})[1].startswith(
        "stereo surface not refined (refinement off)")
    # the user's iterations are kept, and a given optimiser is never replaced
    assert surface_fit_options({"iterations": 40}, False, unrefined)[0]["iterations"] == 40
    assert surface_fit_options({"optimizer": "lbfgs"}, True, unrefined) == ({"optimizer": "lbfgs"}, "given")
