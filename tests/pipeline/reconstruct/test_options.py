"""The patch grid a reconstruction takes (pipeline.reconstruct_options._patch_grid, _units_per_gpu)."""

from __future__ import annotations

import json

import pytest

import polarface.inverse.polarimetric as polarimetric
from polarface.executors import LocalExecutor, ProcessExecutor
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
