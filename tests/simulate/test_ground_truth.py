"""polarface.simulate.ground_truth: the colour table's nearest entries."""

from __future__ import annotations

import numpy as np
import pytest

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


def test_a_skin_without_single_scattering():
    """``single_scattering=False``: rho_ss is zero on every texel, the other maps are the default's; the
    recorded configuration says so (and leaves it out by default, as older folders have it)."""
    from polarface.simulate.scene import SimulationConfig, SimulationScene

    plain = SimulationScene.build(SimulationConfig(preset="tiny"))
    without = SimulationScene.build(SimulationConfig(preset="tiny", single_scattering=False))
    assert (without.maps.rho_ss == 0).all() and (plain.maps.rho_ss[plain.maps.mask] > 0).all()
    for name in ("eta", "alpha_s", "alpha_ss", "rho_s", "rho_sss_bar", "c_h_out"):
        np.testing.assert_array_equal(getattr(without.maps, name), getattr(plain.maps, name))
    assert without.config.to_json()["single_scattering"] is False
    assert "single_scattering" not in plain.config.to_json()
    with pytest.raises(ValueError, match="single_scattering"):
        SimulationConfig(single_scattering="no")
