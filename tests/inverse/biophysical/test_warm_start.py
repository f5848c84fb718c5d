"""Tests of polarface.inverse.biophysical.warm_start: a previous fit as the start of a frame's fit."""

from __future__ import annotations

import pytest
import torch

from polarface.inverse.biophysical import (
    BiophysicalConfig,
    BiophysicalStart,
    blurred_channel_albedo,
    fit_biophysical,
    median_shapes,
    start_parameters,
)

TEXEL_MM = 0.4


def _static_truth(size: int = 32) -> tuple[torch.Tensor, torch.Tensor]:
    """Smooth chromophore maps with a dark spot (freckle) and a masked border."""
    y, x = torch.meshgrid(torch.linspace(0, 1, size), torch.linspace(0, 1, size), indexing="ij")
    params = torch.stack(
        [0.03 + 0.05 * x, 0.05 + 0.1 * y, 0.02 + 0.03 * x * y, 0.03 + 0.08 * (1 - x) * y], -1
    )
    params[20:23, 6:9, 0] = 0.15
    mask = torch.ones(size, size, dtype=torch.bool)
    mask[:3] = False
    return params, mask


@pytest.fixture(scope="module")
def frame_problem(setup):
    """A static fit (exact maps and shapes) and a frame in which a pressed patch lost 60 % of its outer
    haemoglobin (the simulator's dynamic sequence), seen through the blurred model."""
    table, weights = setup
    static, mask = _static_truth()
    shapes, _ = median_shapes(static, mask, table)
    frame = static.clone()
    patch = torch.zeros(mask.shape, dtype=torch.bool)
    patch[8:20, 12:26] = True
    frame[..., 3] = torch.where(patch, 0.4 * static[..., 3], static[..., 3])
    observed = blurred_channel_albedo(frame, table, weights, shapes, TEXEL_MM, mask).clamp(0, 1)
    start = BiophysicalStart(static * mask[..., None], mask, shapes)
    return static, frame, mask, patch, observed, start


def test_warm_start_recovers_the_frame_change_without_a_coarse_search(setup, frame_problem):
    table, weights = setup
    static, frame, mask, patch, observed, start = frame_problem
    config = BiophysicalConfig(coarse_factor=4)
    warm = fit_biophysical(observed, mask, table, weights, TEXEL_MM, config, start=start)
    scratch = fit_biophysical(observed, mask, table, weights, TEXEL_MM, config)
    error = {name: (fit.parameters - frame).abs()[mask].median(0).values for name, fit in
             (("warm", warm), ("scratch", scratch))}
    # The change in the pressed patch is recovered (it is what the sequence is about) ...
    recovered = warm.parameters[..., 3][patch & mask] - static[..., 3][patch & mask]
    truth = frame[..., 3][patch & mask] - static[..., 3][patch & mask]
    assert float((recovered - truth).abs().median()) < 0.1 * float(truth.abs().median())
    # ... every chromophore at least as well as a fit from scratch, beta_m and C_h_in (held by the
    # temporal prior) better, and the shapes are the start's.
    assert bool((error["warm"] <= error["scratch"] + 2e-4).all()), error
    assert float(error["warm"][1]) < float(error["scratch"][1]) and float(error["warm"][2]) < float(
        error["scratch"][2]
    )
    assert torch.equal(warm.shapes.r_in_f, start.shapes.r_in_f)
    assert warm.residual_rmse < 0.01


def test_unchanged_frame_stays_at_the_static_fit(setup, frame_problem):
    """The static fit's own input: the warm fit starts at its fixed point and does not move."""
    table, weights = setup
    static, _, mask, _, _, start = frame_problem
    observed = blurred_channel_albedo(static, table, weights, start.shapes, TEXEL_MM, mask).clamp(0, 1)
    warm = fit_biophysical(observed, mask, table, weights, TEXEL_MM, BiophysicalConfig(), start=start)
    assert float((warm.parameters - static).abs()[mask].max()) < 2e-3
    assert warm.timings_s["coarse_s"] < 0.05


def test_start_without_shapes_fits_them(setup, frame_problem):
    table, weights = setup
    _, frame, mask, _, observed, start = frame_problem
    no_shapes = BiophysicalStart(start.parameters, start.valid)
    fit = fit_biophysical(observed, mask, table, weights, TEXEL_MM, BiophysicalConfig(), start=no_shapes)
    expected, _ = median_shapes(fit.parameters, mask, table)
    assert torch.allclose(fit.shapes.r_out_f, expected.r_out_f)
    assert float((fit.parameters - frame).abs()[mask].median()) < 0.01


def test_start_parameters_fill_and_order(frame_problem):
    static, _, mask, _, _, start = frame_problem
    smaller = start.valid.clone()
    smaller[10:12] = False  # texels of the frame without a static value get the static median
    partial = BiophysicalStart(start.parameters, smaller)
    values = start_parameters(partial, mask)
    assert values.shape == (int(mask.sum()), 4) and values.dtype == torch.float32
    filled = torch.zeros_like(mask)
    filled[10:12] = True
    median = static[smaller].median(0).values
    assert torch.allclose(values[filled[mask]], median.expand(int(filled.sum()), 4))
    assert torch.allclose(values[~filled[mask]], static[mask & ~filled].float())


def test_bad_starts_are_refused(setup, frame_problem):
    table, weights = setup
    static, _, mask, _, observed, _ = frame_problem
    with pytest.raises(ValueError, match=r"parameters must be \(H, W, 4\)"):
        BiophysicalStart(static[..., :3], mask)
    with pytest.raises(ValueError, match="valid must be a bool"):
        BiophysicalStart(static, mask.float())
    with pytest.raises(ValueError, match="no valid texel"):
        BiophysicalStart(static, torch.zeros_like(mask))
    with pytest.raises(ValueError, match="c_m"):
        BiophysicalStart(static.clone().fill_(0.9), mask)
    other = BiophysicalStart(static[:16, :16], mask[:16, :16])
    with pytest.raises(ValueError, match="same texture atlas"):
        fit_biophysical(observed, mask, table, weights, TEXEL_MM, BiophysicalConfig(), start=other)
