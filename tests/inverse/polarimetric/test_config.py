"""Device-dependent fit options (config.device_fit_options): larger patches on a GPU."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from polarface.inverse.polarimetric import PolarimetricConfig, device_fit_options
from polarface.inverse.polarimetric.config import CUDA_BYTES_PER_SAMPLE, CUDA_MEMORY_FRACTION
from polarface.inverse.polarimetric.patch_units import patch_side


@pytest.mark.parametrize("device", ["cpu", torch.device("cpu")])
def test_the_cpu_keeps_the_paper_defaults(device):
    assert device_fit_options(device) == {}
    assert device_fit_options(device, memory_bytes=10**12) == {}


def test_a_large_gpu_gets_the_full_budget_and_a_small_one_what_its_memory_holds():
    h200 = device_fit_options("cuda", memory_bytes=143_155 * 2**20)
    assert h200 == {"patch": 256, "sample_budget": 2_000_000}
    small = device_fit_options(torch.device("cuda", 1), memory_bytes=8 * 2**30)
    assert small["patch"] == 256
    assert small["sample_budget"] == int(CUDA_MEMORY_FRACTION * 8 * 2**30 / CUDA_BYTES_PER_SAMPLE) < 2_000_000
    # two worker processes fitting on one GPU share its memory
    shared = device_fit_options("cuda", memory_bytes=8 * 2**30, units_per_gpu=2)["sample_budget"]
    assert shared == int(CUDA_MEMORY_FRACTION * 4 * 2**30 / CUDA_BYTES_PER_SAMPLE)
    assert device_fit_options("cuda", memory_bytes=143_155 * 2**20, units_per_gpu=2) == h200
    # a tiny card still gets a valid configuration
    assert device_fit_options("cuda", memory_bytes=1)["sample_budget"] == 1000
    for options in (h200, small):
        PolarimetricConfig(**options)  # valid options


def test_the_gpu_options_give_larger_patches_than_the_cpu_defaults():
    counts = np.full((512, 512), 30)  # views per texel, as on the demo preset
    cpu = patch_side(counts, PolarimetricConfig())
    gpu = patch_side(counts, PolarimetricConfig(**device_fit_options("cuda", memory_bytes=80 * 2**30)))
    assert cpu == 64 and gpu == 250  # sqrt(2e6 / 30) - 2 halos of 4
    assert gpu**2 * 30 < 2_000_000 < (gpu + 2 * 4 + 1) ** 2 * 30


@pytest.mark.parametrize(
    ("argument", "value"), [("memory_bytes", 0), ("memory_bytes", -5), ("units_per_gpu", 0)]
)
def test_bad_arguments_are_refused_by_name(argument, value):
    with pytest.raises(ValueError, match=argument):
        device_fit_options("cuda", **{"memory_bytes": 2**30, argument: value})


def test_a_cuda_device_without_memory_given_asks_torch(monkeypatch):
    class Properties:
        total_memory = 4 * 2**30

    monkeypatch.setattr(torch.cuda, "get_device_properties", lambda device: Properties())
    assert device_fit_options("cuda:0")["sample_budget"] == int(0.4 * 4 * 2**30 / 4000)
