"""Test-wide settings: one torch thread per xdist worker, deterministic seeds, shared paths."""

from __future__ import annotations

import uuid
from pathlib import Path

import numpy as np
import pytest
import torch

torch.set_num_threads(1)

TEST_DATA = Path(__file__).parent / "data"


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)
    np.random.seed(0)  # noqa: NPY002 - seeds legacy global-RNG users in third-party code


@pytest.fixture
def test_data() -> Path:
    """Folder of small real-data files copied into the repository (see tests/data/README.md)."""
    return TEST_DATA


@pytest.fixture
def memory_url():
    """``memory://polarface-test-<random>``: an empty folder of fsspec's in-memory file system (shared by
    every ``memory://`` URL of this process), removed after the test."""
    from polarface.io.storage import remove_tree

    url = f"memory://polarface-test-{uuid.uuid4().hex[:10]}"
    yield url
    remove_tree(url)
