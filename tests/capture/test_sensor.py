"""polarface.capture.sensor: mosaic layout, phase, noise model."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from polarface.capture.sensor import (
    SensorNoise,
    angle_index_map,
    colour_index_map,
    lattices,
    mosaic,
    pattern_period,
    simulate_raw,
)


def _constant_images(shape, values=(1.0, 2.0, 3.0, 4.0)):
    return [np.full(shape, v) for v in values]


def test_mono_layout_matches_sony_pattern():
    raw = mosaic(*_constant_images((4, 6)), sensor="mono-polarization")
    # I0=1, I45=2, I90=3, I135=4; row 0: 90 45, row 1: 135 0
    assert raw[0, 0] == 3 and raw[0, 1] == 2 and raw[1, 0] == 4 and raw[1, 1] == 1
    assert raw.shape == (4, 6) and isinstance(raw, np.ndarray)


def test_colour_layout_rggb_at_block_level():
    colours = np.array([10.0, 20.0, 30.0])
    images = [np.broadcast_to(colours * (k + 1), (8, 8, 3)).copy() for k in range(4)]
    raw = mosaic(*images, sensor="color-polarization")
    assert raw[0, 0] == 3 * 10  # 90 deg, R
    assert raw[1, 1] == 1 * 10  # 0 deg, R
    assert raw[0, 2] == 3 * 20 and raw[2, 0] == 3 * 20  # G blocks
    assert raw[3, 3] == 1 * 30  # 0 deg, B
    assert raw[2, 3] == 2 * 30  # 45 deg, B


def test_phase_shifts_pattern():
    images = _constant_images((6, 6))
    shifted = mosaic(*images, sensor="mono-polarization", phase=(1, 0))
    base = mosaic(*[np.full((7, 6), v) for v in (1.0, 2.0, 3.0, 4.0)], sensor="mono-polarization")
    np.testing.assert_array_equal(shifted, base[1:7])
    assert angle_index_map("mono-polarization", 2, 2, (1, 1))[0, 0] == 0
    assert pattern_period("color-polarization") == 4 and len(lattices("color-polarization")) == 16


def test_colour_index_map_counts():
    colours = colour_index_map("color-polarization", 8, 8)
    assert np.bincount(colours.ravel()).tolist() == [16, 32, 16]
    assert colour_index_map("mono-polarization", 2, 2).max() == 0


def test_mosaic_torch_differentiable():
    images = [torch.rand(4, 4, 3, dtype=torch.float64, requires_grad=True) for _ in range(4)]
    raw = mosaic(*images, sensor="color-polarization")
    assert isinstance(raw, torch.Tensor) and raw.dtype == torch.float64
    assert torch.autograd.gradcheck(lambda *x: mosaic(*x, sensor="color-polarization"), images)


def test_mosaic_float32_kept():
    raw = mosaic(*[torch.ones(2, 2, dtype=torch.float32)] * 4)
    assert raw.dtype == torch.float32


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"sensor": "rgb"}, "sensor"),
        ({"sensor": "color-polarization"}, "color-polarization"),
    ],
)
def test_mosaic_errors(kwargs, message):
    with pytest.raises(ValueError, match=message):
        mosaic(*_constant_images((4, 4)), **kwargs)


def test_mosaic_shape_mismatch_and_nan():
    with pytest.raises(ValueError, match="share one shape"):
        mosaic(np.ones((4, 4)), np.ones((4, 4)), np.ones((4, 4)), np.ones((2, 4)))
    with pytest.raises(ValueError, match="i0"):
        mosaic(np.full((4, 4), np.nan), np.ones((4, 4)), np.ones((4, 4)), np.ones((4, 4)))


def test_noise_statistics_and_determinism():
    noise = SensorNoise(black_level=64.0)
    signal = np.full((200, 200), 0.25)
    a = simulate_raw(signal, noise, seed=3)
    b = simulate_raw(signal, noise, seed=3)
    np.testing.assert_array_equal(a, b)
    assert a.dtype == np.uint16
    electrons = (a.astype(float) - 64.0) * noise.electrons_per_count
    assert abs(electrons.mean() - 0.25 * 10_500) < 10
    expected_std = np.sqrt(0.25 * 10_500 + 2.4**2 + noise.electrons_per_count**2 / 12)
    assert abs(electrons.std() / expected_std - 1) < 0.05


def test_noise_saturates_and_clips():
    raw = simulate_raw(np.array([[0.0, 2.0]]), SensorNoise(), noiseless=True)
    assert raw.tolist() == [[0, 4095]]


@pytest.mark.parametrize(
    ("noise", "field"),
    [
        (SensorNoise(bit_depth=20), "bit_depth"),
        (SensorNoise(full_well_e=0), "full_well_e"),
        (SensorNoise(exposure=0), "exposure"),
        (SensorNoise(black_level=5000), "black_level"),
    ],
)
def test_noise_model_validation(noise, field):
    with pytest.raises(ValueError, match=field):
        simulate_raw(np.zeros((2, 2)), noise)


def test_simulate_raw_rejects_bad_signal():
    with pytest.raises(ValueError, match="signal"):
        simulate_raw(np.array([[np.nan, 0.0]]))
    with pytest.raises(ValueError, match="signal"):
        simulate_raw(np.array([[-1.0, 0.0]]))


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 3), st.integers(0, 3))
def test_every_block_holds_each_angle_once(row, col):
    angles = angle_index_map("mono-polarization", 4, 4, (row, col))
    for r in (0, 2):
        for c in (0, 2):
            assert sorted(angles[r : r + 2, c : c + 2].ravel()) == [0, 1, 2, 3]
