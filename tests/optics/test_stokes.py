"""Stokes helpers: Malus' law, round trips, DoP bounds, AoLP range, gradients, bad input."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from polarface.optics import (
    ANALYZER_ANGLES,
    analyzer_intensity,
    aolp,
    intensities_from_stokes,
    linear_dop,
    linear_polarizer,
    stokes_from_intensities,
)

linear_stokes = st.tuples(st.floats(0.01, 10), st.floats(0, 1), st.floats(-math.pi, math.pi)).map(
    lambda v: np.array([v[0], v[0] * v[1] * math.cos(v[2]), v[0] * v[1] * math.sin(v[2])])
)


@settings(max_examples=50, deadline=None)
@given(st.floats(-math.pi, math.pi), st.floats(-math.pi, math.pi), st.floats(0.01, 5))
def test_malus_law(polarization, analyzer, power):
    stokes = power * np.array([1.0, math.cos(2 * polarization), math.sin(2 * polarization)])
    assert analyzer_intensity(stokes, analyzer) == pytest.approx(
        power * math.cos(analyzer - polarization) ** 2
    )
    # same through the Mueller polarizer
    full = np.append(stokes, 0.0)
    assert (linear_polarizer(analyzer) @ full)[0] == pytest.approx(
        power * math.cos(analyzer - polarization) ** 2
    )


@settings(max_examples=50, deadline=None)
@given(linear_stokes)
def test_round_trips_and_bounds(stokes):
    intensities = intensities_from_stokes(stokes)
    for k, angle in enumerate(ANALYZER_ANGLES):
        assert intensities[k] == pytest.approx(analyzer_intensity(stokes, angle))
    back = stokes_from_intensities(*intensities)
    np.testing.assert_allclose(back, stokes, atol=1e-12)
    dop = linear_dop(stokes)
    assert 0.0 <= dop <= 1.0 + 1e-12
    angle = aolp(stokes)
    assert 0.0 <= angle < math.pi


def test_reference_values():
    assert aolp(np.array([1.0, 0.0, 1.0])) == pytest.approx(math.pi / 4)
    assert aolp(np.array([1.0, -1.0, 0.0])) == pytest.approx(math.pi / 2)
    assert aolp(np.array([1.0, 1.0, -1e-20])) == 0.0
    assert linear_dop(np.array([0.0, 0.0, 0.0])) == 0.0
    assert linear_dop(np.array([2.0, 1.0, 0.0, 0.5])) == pytest.approx(0.5)


def test_gradcheck():
    stokes = torch.tensor([[1.0, 0.3, 0.2], [2.0, -0.5, 0.1]], dtype=torch.float64, requires_grad=True)
    theta = torch.tensor([0.2, 1.1], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(analyzer_intensity, (stokes, theta))
    assert torch.autograd.gradcheck(linear_dop, (stokes,))
    assert torch.autograd.gradcheck(aolp, (stokes,))
    assert torch.autograd.gradcheck(intensities_from_stokes, (stokes,))
    images = [torch.rand(3, dtype=torch.float64, requires_grad=True) for _ in range(4)]
    assert torch.autograd.gradcheck(stokes_from_intensities, tuple(images))
    unpolarized = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64, requires_grad=True)
    linear_dop(unpolarized).backward()
    assert torch.isfinite(unpolarized.grad).all()


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda: analyzer_intensity(np.zeros(2), 0.0), "stokes"),
        (lambda: linear_dop(np.array([1.0, np.nan, 0.0])), "stokes"),
        (lambda: aolp(np.zeros((3, 5))), "stokes"),
        (lambda: stokes_from_intensities(1.0, 1.0, float("inf"), 1.0), "i90"),
    ],
)
def test_bad_input(call, name):
    with pytest.raises(ValueError, match=name):
        call()
