"""Test-wide settings: one torch thread per xdist worker, deterministic seeds, shared paths."""

from __future__ import annotations

import os
import tempfile
import uuid
from pathlib import Path

# numba's on-disk cache is not safe to fill from concurrent processes (numba issues 4807 and 10128: a
# 'polarface dynamic' subprocess segfaulted in a fresh clone while the other xdist worker compiled the
# same kernels): each xdist worker, with the processes its tests start, keeps its own cache
if os.environ.get("PYTEST_XDIST_WORKER") and "NUMBA_CACHE_DIR" not in os.environ:
    os.environ["NUMBA_CACHE_DIR"] = str(
        Path(tempfile.gettempdir()) / f"polarface-numba-{os.getuid()}" / os.environ["PYTEST_XDIST_WORKER"]
    )

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
