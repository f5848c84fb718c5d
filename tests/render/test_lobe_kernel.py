"""polarface.render.lobe_kernel.add_lobes_fused against the differentiable reference
polarface.optics.lobes.add_lobes (itself the bits of render_polarimetric, tests/optics/test_lobes.py):
the same Stokes to float rounding (a few ulps whatever the CPU: _assert_rounding) for every component
count, dtype, per-light intensities and polarizer states, per-channel albedos, eager and lazy visibility
(the same shadow rays asked), no light lit; the cases the loop does not take go through add_lobes (same
bits, gradients); the same errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lobe_fixtures import lobe_fragments as _fragments
from polarface._validation import trusted_inputs
from polarface.optics.lobes import add_lobes
from polarface.render.lobe_kernel import add_lobes_fused


def _both(geometry, params, lights, visible, intensity, stokes, **kwargs):
    """``(add_lobes, add_lobes_fused)`` of the same arguments."""
    arguments = (stokes, geometry["normal"], geometry["position"], geometry["camera_center"],
                 geometry["camera_up"], lights, intensity, params["eta"], params["alpha_s"],
                 params["alpha_ss"], params["rho_s"], params["rho_ss"], visible)
    return add_lobes(*arguments, **kwargs), add_lobes_fused(*arguments, **kwargs)


def _assert_rounding(got: torch.Tensor, reference: torch.Tensor, ulps: float = 8.0) -> None:
    """Equal to rounding: every Stokes component within ``ulps`` units in the last place of its Stokes
    vector's largest component (per fragment and channel, the ``(..., S)`` rows).

    Why this tolerance and not a share of identical bits: the two evaluate the same expressions, but
    torch's vectorised elementwise kernels (and its scalar tails) are picked for the CPU it runs on (AVX2,
    AVX-512) and some of them are not correctly rounded, while numba's are IEEE's; so which values come
    out the same bits depends on the CPU (93.9 % in float32 on an AMD EPYC without AVX-512 against more
    than 95 % on Intel), not on either implementation. What the renderer needs is that the fused loop
    computes the reference's numbers to float rounding: the lobes are sums of non-negative terms of some
    twenty operations each, every one within one ulp, so a few ulps of the vector's magnitude. The row's
    largest component is the scale because s1..s3 are signed sums that may cancel (their own relative
    error is meaningless near 0) while their rounding follows the magnitude of what was summed. Measured
    on that AMD CPU: at most 2.4 ulps (float32) and 1.2 ulps (float64)."""
    assert got.shape == reference.shape and got.dtype == reference.dtype
    info = torch.finfo(reference.dtype)
    ulp = info.eps * reference.abs().amax(-1, keepdim=True).clamp_min(info.tiny)
    in_ulps = (got - reference).abs() / ulp
    assert float(in_ulps.max()) <= ulps, float(in_ulps.max())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_every_component_count_equals_the_reference(dtype):
    geometry, params, lights, visible, start = _fragments(dtype, count=3000)
    intensity = torch.full((1, 1), 2.5e6, dtype=dtype)
    for components in (1, 2, 3, 4):
        stokes = start[..., :components]
        reference, got = _both(geometry, params, lights, visible, intensity, stokes)
        _assert_rounding(got, reference)
        assert torch.equal(stokes, start[..., :components])  # the input is not written to
    # s0 alone is the full vector's s0, bit for bit (an RGB camera renders s0 alone)
    _, s0 = _both(geometry, params, lights, visible, intensity, start[..., :1])
    _, full = _both(geometry, params, lights, visible, intensity, start)
    assert torch.equal(s0[..., 0], full[..., 0])


def test_per_light_intensities_polarizers_and_channel_albedos_equal_the_reference():
    geometry, params, lights, visible, start = _fragments(torch.float32, count=2000, seed=3)
    rng = np.random.default_rng(4)
    per_light = torch.from_numpy(rng.uniform(1e6, 3e6, (5, 3))).float()
    states = torch.tensor([[1, 1, 0, 0], [1, -1, 0, 0], [1, 0, 1, 0], [1, 0, 0, 1], [1, 0.3, -0.4, 0.2]])
    channel_albedos = dict(params, rho_s=torch.from_numpy(rng.uniform(0, 1, (2000, 3))).float())
    reference, got = _both(geometry, channel_albedos, lights, visible, per_light, start, light_stokes=states)
    _assert_rounding(got, reference)


def test_lazy_visibility_asks_the_references_rays():
    geometry, params, lights, visible, start = _fragments(torch.float32, count=1500, seed=5)
    asked: dict[str, dict[int, np.ndarray]] = {"reference": {}, "fused": {}}

    def test_for(name):
        def shadow_test(k: int, rows: np.ndarray) -> np.ndarray:
            asked[name][k] = rows
            return visible[rows, k]
        return shadow_test

    intensity = torch.ones(1, 1)
    arguments = (start[..., :3], geometry["normal"], geometry["position"], geometry["camera_center"],
                 geometry["camera_up"], lights, intensity, params["eta"], params["alpha_s"],
                 params["alpha_ss"], params["rho_s"], params["rho_ss"])
    reference = add_lobes(*arguments, test_for("reference"))
    got = add_lobes_fused(*arguments, test_for("fused"))
    _assert_rounding(got, reference)
    assert asked["reference"].keys() == asked["fused"].keys() == set(range(len(lights)))
    for k, rows in asked["reference"].items():
        assert np.array_equal(asked["fused"][k], rows)
    assert sum(len(rows) for rows in asked["fused"].values()) < len(start) * len(lights)


def test_unlit_lights_and_no_fragments():
    geometry, params, lights, _, start = _fragments(torch.float32, count=400, seed=6)
    intensity = torch.ones(1, 1)
    dark = np.zeros((400, len(lights)), bool)
    reference, got = _both(geometry, params, lights, dark, intensity, start)
    assert torch.equal(got, start) and torch.equal(reference, start)
    some = dark.copy()
    some[::7, 2] = True  # one light lights a few fragments; skip_unlit=False adds 0 * terms of the others
    reference, got = _both(geometry, params, lights, some, intensity, start, skip_unlit=False)
    _assert_rounding(got, reference)
    empty = {name: value[:0] for name, value in params.items()}
    geometry_empty = dict(geometry, normal=geometry["normal"][:0], position=geometry["position"][:0])
    reference, got = _both(geometry_empty, empty, lights, dark[:0], intensity, start[:0])
    assert got.shape == reference.shape == (0, 3, 4)


def test_what_the_loop_does_not_take_goes_through_the_reference():
    geometry, params, lights, visible, start = _fragments(torch.float64, count=300, seed=7)
    intensity = torch.ones(1, 1, dtype=torch.float64)
    per_channel_eta = dict(params, eta=params["eta"].expand(300, 3).contiguous())
    reference, got = _both(geometry, per_channel_eta, lights, visible, intensity, start)
    assert torch.equal(got, reference)  # (N, C) eta: add_lobes itself
    eta = params["eta"].clone().requires_grad_(True)
    reference, got = _both(geometry, dict(params, eta=eta), lights, visible, intensity, start)
    assert torch.equal(got, reference) and got.requires_grad
    (grad,) = torch.autograd.grad(got.sum(), eta)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0
    wider = torch.ones(1, 2, dtype=torch.float64)  # an intensity of 2 channels for 3: add_lobes's error
    with pytest.raises(RuntimeError):
        _both(geometry, params, lights, visible, wider, start)


def test_bad_input_is_refused_as_by_the_reference():
    geometry, params, lights, visible, start = _fragments(torch.float32, count=20)
    intensity = torch.ones(1, 1)

    def fused(geometry=geometry, params=params, visible=visible, intensity=intensity, stokes=start):
        return add_lobes_fused(stokes, geometry["normal"], geometry["position"], geometry["camera_center"],
                               geometry["camera_up"], lights, intensity, params["eta"], params["alpha_s"],
                               params["alpha_ss"], params["rho_s"], params["rho_ss"], visible)

    with pytest.raises(ValueError, match="'stokes'"):
        fused(stokes=torch.zeros(20, 3, 5))
    with pytest.raises(ValueError, match="'visible'"):
        fused(visible=visible[:, :2])
    with pytest.raises(ValueError, match="'visible'"):
        fused(visible=lambda k, rows: np.ones(len(rows) + 1, bool))
    with pytest.raises(ValueError, match="'light_intensity'"):
        fused(intensity=torch.ones(3, 1))
    bad = dict(params, eta=torch.full((20, 1), 0.9))
    with pytest.raises(ValueError, match="'eta'"):
        fused(params=bad)
    with pytest.raises(ValueError, match="'normal'"):
        fused(geometry=dict(geometry, normal=2 * geometry["normal"]))
    with trusted_inputs():  # value checks skipped, shape checks kept
        fused(params=bad)
        with pytest.raises(ValueError, match="'visible'"):
            fused(visible=visible[:, :2])
