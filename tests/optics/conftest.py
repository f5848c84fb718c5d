"""Shared helpers for the optics tests: Mitsuba 3 set-up (an oracle: failing, never skipping)."""

import numpy as np
import pytest


@pytest.fixture(scope="session")
def mi():
    """Mitsuba 3 in its scalar polarized variant (float32 arithmetic; no LLVM needed).

    A missing or broken Mitsuba makes the oracle tests fail, never skip.
    """
    import mitsuba

    mitsuba.set_variant("scalar_spectral_polarized")
    return mitsuba


def random_unit(rng: np.random.Generator, count: int, min_z: float | None = None) -> np.ndarray:
    """``(count, 3)`` random unit vectors, optionally with z >= min_z (upper hemisphere)."""
    v = rng.normal(size=(count, 3))
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    if min_z is not None:
        v[:, 2] = np.abs(v[:, 2])
        v = v[v[:, 2] >= min_z]
    return v
