"""Device selection (polarface.device.resolve_device)."""

from __future__ import annotations

import pytest
import torch

from polarface.device import resolve_device


def test_cpu_and_auto(monkeypatch):
    monkeypatch.delenv("POLARFACE_DEVICE", raising=False)
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(None).type == ("cuda" if torch.cuda.is_available() else "cpu")
    monkeypatch.setenv("POLARFACE_DEVICE", "cpu")
    assert resolve_device("auto") == torch.device("cpu")


@pytest.mark.parametrize("device", ["quantum", "cuda:x"])
def test_not_a_device_is_refused_by_name(device):
    with pytest.raises(ValueError, match="argument 'device'"):
        resolve_device(device)


def test_cuda_without_cuda_is_refused(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="CUDA was requested"):
        resolve_device("cuda")


def test_a_gpu_index_this_machine_lacks_is_refused(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert resolve_device("cuda:1") == torch.device("cuda", 1)
    assert resolve_device("cuda") == torch.device("cuda")
    message = r"'cuda:2' names GPU 2, but this machine has 2 \(cuda:0 to cuda:1\)"
    with pytest.raises(ValueError, match=message):
        resolve_device("cuda:2")
