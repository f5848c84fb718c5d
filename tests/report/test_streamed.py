"""Statistics over arrays read one at a time (``polarface.report.streamed``) against numpy's on the
concatenated arrays."""

from __future__ import annotations

import numpy as np
import pytest

from polarface.report import streamed
from polarface.report.streamed import streamed_percentiles, streamed_std

Q = [0, 1, 12.345, 50, 99, 99.5, 100]


def _chunks() -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    chunks = [rng.normal(size=(int(rng.integers(0, 40)), 50)) for _ in range(13)]
    chunks[3][:2] = np.nan
    chunks[5][0, :4] = np.inf
    return [*chunks, np.zeros(3000), np.full(100, 7.0)]  # many ties, at the low and the high end


@pytest.mark.parametrize("held", [None, 5000, 100, 1])
def test_percentiles_equal_numpys_whatever_is_held(held):
    chunks = _chunks()
    values = np.concatenate([c.ravel() for c in chunks])
    reference = np.percentile(values[np.isfinite(values)], Q)
    reads = []

    def read(index: int) -> np.ndarray:
        reads.append(index)
        return chunks[index]

    got = streamed_percentiles(read, len(chunks), Q, held=held)
    assert got == [float(v) for v in reference]  # the same rounding as numpy's linear method
    passes = len(reads) / len(chunks)
    assert passes == 1 if held is None else passes > 1  # what does not fit is read again


def test_percentiles_of_nothing_and_bad_arguments():
    assert np.isnan(streamed_percentiles(lambda i: np.full(3, np.nan), 2, [50, 99])).all()
    assert np.isnan(streamed_percentiles(lambda i: np.zeros(0), 0, [50])).all()
    with pytest.raises(ValueError, match="'q'"):
        streamed_percentiles(lambda i: np.ones(3), 1, [101])
    with pytest.raises(ValueError, match="'held'"):
        streamed_percentiles(lambda i: np.ones(3), 1, [50], held=0)


def test_std_equals_numpys_population_std():
    stack = np.random.default_rng(1).random((7, 4, 5)) * 1e-3 + 0.05  # small changes on an offset
    std, count = streamed_std(iter(stack))
    assert count == 7
    np.testing.assert_allclose(std, stack.std(axis=0), rtol=1e-12, atol=0)
    empty, none = streamed_std([])
    assert none == 0 and empty.size == 0
    with pytest.raises(ValueError, match="shapes"):
        streamed_std([np.zeros(3), np.zeros(4)])


def test_held_default_is_the_module_constant(monkeypatch):
    monkeypatch.setattr(streamed, "HELD_VALUES", 10)
    reads = []
    streamed_percentiles(lambda i: reads.append(i) or np.arange(20.0), 1, [50])
    assert len(reads) > 1
