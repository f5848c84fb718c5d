"""polarface.simulate.ground_truth: the colour table's nearest entries."""

from __future__ import annotations

import numpy as np

from polarface.simulate.ground_truth import _nearest_table_entry


def test_nearest_table_entry_is_the_first_closest_row():
    rng = np.random.default_rng(2)
    table = rng.normal(size=(300, 3))
    table[200:260] = table[10]  # clamped chromophores repeat rows: ties go to the first index
    table[100:110] = table[42]
    points = np.concatenate([rng.normal(size=(5000, 3)), table[[10, 42, 230, 105]] + 1e-9])
    nearest = _nearest_table_entry(table)(points)
    squared = ((points[:, None, :] - table[None]) ** 2).sum(-1)
    assert nearest.dtype == np.int64
    assert np.array_equal(nearest, squared.argmin(axis=1))
    assert nearest[-4:].tolist() == [10, 42, 10, 42]
