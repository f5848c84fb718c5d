"""Statistics over a sequence of arrays read one at a time, so that a report's memory does not grow with
the number of frames it summarises.

:func:`streamed_percentiles` is ``np.percentile`` (linear interpolation) of the concatenated finite values
of ``read(0) .. read(count - 1)``: while the values fit in :data:`HELD_VALUES` they are kept and handed to
``np.percentile``; past that, the order statistics are found by counting values in bins of a narrowing
range (each pass reads the arrays again; only the values of the bins that hold a wanted rank are kept).
:func:`streamed_std` is the population standard deviation over the sequence, per element (Welford).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator, Sequence

import numpy as np

__all__ = ["HELD_VALUES", "streamed_percentiles", "streamed_std"]

#: Most values kept in memory at once (float64: 32 MiB).
HELD_VALUES = 1 << 22
#: Bins of one counting pass.
_BINS = 4096

Reader = Callable[[int], np.ndarray]


def _finite(values: np.ndarray) -> np.ndarray:
    flat = np.asarray(values, np.float64).ravel()
    return flat if np.isfinite(flat).all() else flat[np.isfinite(flat)]


def _in_range(read: Reader, index: int, low: float, high: float) -> np.ndarray:
    values = _finite(read(index))
    return values[(values >= low) & (values <= high)]


def _bins(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """Bin of each value of ``[low, high]`` (monotonic in the value, so bins keep the values' order)."""
    return np.minimum(((values - low) * (_BINS / (high - low))).astype(np.int64), _BINS - 1)


def _bin_values(read: Reader, count: int, low: float, high: float, bin_index: int) -> Iterator[np.ndarray]:
    """The values of each array that fall in bin ``bin_index`` of ``[low, high]``, one array at a time."""
    for index in range(count):
        values = _in_range(read, index, low, high)
        yield values[_bins(values, low, high) == bin_index]


def _order_statistics(read: Reader, count: int, ranks: list[int], low: float, high: float,
                      below: int, held: int) -> dict[int, float]:
    """The values of 0-based ``ranks`` among the finite values, all of which lie in ``[low, high]``
    with ``below`` finite values smaller than ``low``."""
    if low == high:
        return dict.fromkeys(ranks, low)
    counts = np.zeros(_BINS, np.int64)
    for index in range(count):
        counts += np.bincount(_bins(_in_range(read, index, low, high), low, high), minlength=_BINS)
    ends = np.cumsum(counts)
    wanted: dict[int, list[int]] = {}
    for rank in ranks:
        wanted.setdefault(int(np.searchsorted(ends, rank - below, side="right")), []).append(rank)
    found: dict[int, float] = {}
    for bin_index, bin_ranks in sorted(wanted.items()):
        before = below + (int(ends[bin_index - 1]) if bin_index else 0)
        if counts[bin_index] > held:  # too many to keep: narrow to this bin's range and count again
            low_bin, high_bin = math.inf, -math.inf
            for part in _bin_values(read, count, low, high, bin_index):
                if part.size:
                    low_bin, high_bin = min(low_bin, float(part.min())), max(high_bin, float(part.max()))
            found |= _order_statistics(read, count, bin_ranks, low_bin, high_bin, before, held)
            continue
        values = np.sort(np.concatenate(list(_bin_values(read, count, low, high, bin_index))))
        found |= {rank: float(values[rank - before]) for rank in bin_ranks}
    return found


def _lerp(a: float, b: float, t: float) -> float:
    """numpy's linear interpolation of the ``linear`` percentile method (the same rounding)."""
    difference = b - a
    return b - difference * (1.0 - t) if t >= 0.5 else a + difference * t


def streamed_percentiles(read: Reader, count: int, q: Sequence[float],
                         held: int | None = None) -> list[float]:
    """Percentiles ``q`` (0..100) of the finite values of the arrays ``read(0) .. read(count - 1)``.

    Equal to ``np.percentile(np.concatenate([...]), q)`` of those values (method ``linear``); NaN for each
    ``q`` when there is no finite value. At most about ``held`` values (default :data:`HELD_VALUES`) are
    kept at once; beyond that each array is read several times (a few passes per wanted order statistic).

    Args:
        read: ``read(i)`` -> the i-th array (any shape; non-finite entries are ignored).
        count: number of arrays.
        q: percentiles in [0, 100].

    Raises:
        ValueError: a percentile is outside [0, 100], or ``held`` < 1.
    """
    quantiles = [float(v) for v in q]
    if any(not 0.0 <= v <= 100.0 for v in quantiles):
        raise ValueError(f"argument 'q' must lie in [0, 100]; got {quantiles}")
    held = HELD_VALUES if held is None else held
    if held < 1:
        raise ValueError(f"argument 'held' must be >= 1; got {held}")
    kept: list[np.ndarray] | None = []
    total, low, high = 0, math.inf, -math.inf
    for index in range(count):
        values = _finite(read(index))
        total += values.size
        if values.size:
            low, high = min(low, float(values.min())), max(high, float(values.max()))
        if kept is not None and total <= held:
            kept.append(values)
        else:
            kept = None
    if total == 0:
        return [math.nan] * len(quantiles)
    if kept is not None:
        return [float(v) for v in np.percentile(np.concatenate(kept), quantiles)]
    positions = [v / 100.0 * (total - 1) for v in quantiles]
    ranks = sorted({r for p in positions for r in (math.floor(p), min(math.floor(p) + 1, total - 1))})
    values = _order_statistics(read, count, ranks, low, high, 0, held)
    return [_lerp(values[math.floor(p)], values[min(math.floor(p) + 1, total - 1)], p - math.floor(p))
            for p in positions]


def streamed_std(arrays: Iterable[np.ndarray]) -> tuple[np.ndarray, int]:
    """Per-element population standard deviation of equally shaped arrays met one at a time (Welford's
    update in float64), and how many there were (an empty float64 array and 0 for no array).

    Raises:
        ValueError: the arrays' shapes differ.
    """
    count, mean, squares = 0, None, None
    for array in arrays:
        values = np.asarray(array, np.float64)
        if mean is None:
            mean, squares = np.zeros_like(values), np.zeros_like(values)
        elif values.shape != mean.shape:
            raise ValueError(f"arrays of different shapes: {mean.shape} and {values.shape}")
        count += 1
        delta = values - mean
        mean += delta / count
        squares += delta * (values - mean)
    if mean is None or squares is None:
        return np.zeros(0), 0
    return np.sqrt(squares / count), count
