"""Fused numba data loss: value and analytic gradient against the autograd reference, float32 vs
float64, thread-count determinism, gradcheck, bad input."""

from __future__ import annotations

import dataclasses

import numba
import numpy as np
import pytest
import torch

from polarface.capture.rig import paper_rig
from polarface.inverse.polarimetric import (
    LossWeights,
    build_fused_samples,
    data_losses,
    fused_data_loss,
    fused_loss_and_grad,
    pack_parameters,
    precompute_samples,
    render_samples,
)
from polarface.simulate.sphere_capture import sphere_placement
from polarface.texture import build_views

NAMES = ("normal", "eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss", "rho_sss_bar")


@dataclasses.dataclass
class Problem:
    batch: object
    fused: object
    leaves: list
    observed: torch.Tensor
    scale: float


def _problem(seed: int = 0, texels: int = 30, frames: int = 5, empty_texels: int = 2) -> Problem:
    """Random texels (some normals facing away from lights or camera, some lights shadowed, some texels
    without samples) seen by both polarimetric cameras; noisy observations of the model itself."""
    rng = np.random.default_rng(seed)
    rig = paper_rig(width=256, height=212)
    poses = np.stack([sphere_placement(float(y)) for y in np.radians(np.linspace(-40, 40, frames))])
    views = build_views(rig, list(range(frames)), poses)
    table = {a: np.array([getattr(v, a) for v in views], dtype=np.float64) for a in (
        "camera_center", "camera_up", "reference_up", "light_positions", "light_intensity"
    )}  # fmt: skip
    channels = np.array([v.channels for v in views])
    directions = rng.normal(size=(texels, 3))
    directions[:, 2] = np.abs(directions[:, 2]) + 0.8
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    position = 80.0 * directions
    texel, view = np.meshgrid(np.arange(texels - empty_texels), np.arange(len(views)), indexing="ij")
    texel, view = texel.ravel(), view.ravel()
    keep = rng.random(texel.size) < 0.8
    texel, view = texel[keep], view[keep]
    lit = rng.random((texel.size, table["light_positions"].shape[1])) < 0.85
    batch = precompute_samples(
        position[texel], texel, view, table["camera_center"][view], table["camera_up"][view],
        table["reference_up"][view], table["light_positions"][view], table["light_intensity"][view],
        channels[view], lit, np.zeros((texel.size, 3, 3)), dtype=torch.float64,
    )  # fmt: skip
    normal = directions + 0.45 * rng.normal(size=(texels, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)

    def uniform(lo, hi, shape=(texels,)):
        return torch.tensor(rng.uniform(lo, hi, shape), requires_grad=True)

    leaves = [
        torch.tensor(normal, requires_grad=True),
        uniform(1.2, 1.9),
        uniform(0.15, 0.6),
        uniform(0.7, 1.1),
        uniform(0.1, 0.8),
        uniform(0.05, 0.4),
        uniform(0.1, 0.9, (texels, 6)),
    ]
    with torch.no_grad():
        clean = _predict(batch, leaves)
        observed = torch.stack([clean.i_sss, clean.i_zeta, clean.i_s], dim=1)
        generator = torch.Generator().manual_seed(seed)
        observed = observed * (
            1 + 0.2 * torch.randn(observed.shape, generator=generator, dtype=torch.float64)
        )
    batch = dataclasses.replace(batch, observed=observed)
    fused = build_fused_samples(
        position, texel, view, lit, observed.numpy(), table["camera_center"], table["camera_up"],
        table["reference_up"], table["light_positions"], table["light_intensity"], channels,
        dtype=np.float64,
    )  # fmt: skip
    return Problem(batch, fused, leaves, observed, float(observed[:, 0].mean()))


def _predict(batch, leaves):
    normal, eta, alpha_s, alpha_ss, rho_s, rho_ss, rho = leaves
    t = batch.texel
    return render_samples(
        batch,
        normal[t],
        eta[t],
        alpha_s[t],
        alpha_ss[t],
        rho_s[t],
        rho_ss[t],
        torch.gather(rho[t], 1, batch.channels),
    )


def _reference_loss(problem: Problem, weights: LossWeights, leaves=None) -> torch.Tensor:
    terms = data_losses(_predict(problem.batch, leaves or problem.leaves), problem.observed, problem.scale)
    return (
        weights.sss * terms["sss"]
        + weights.s * terms["s"]
        + weights.phi * terms["phi"]
        + weights.psi * terms["psi"]
    )


@pytest.fixture(scope="module")
def problem() -> Problem:
    return _problem()


def test_smoke_shapes_and_empty_texels(problem):
    params = pack_parameters(*problem.leaves).detach().numpy()
    f = problem.fused
    loss, grad, terms = fused_loss_and_grad(f, params, (1.0, 1.0, 1.0, 0.002), problem.scale)
    assert loss.shape == (30,) and grad.shape == (30, 14) and terms.shape == (4,)
    assert np.all(loss[-2:] == 0) and np.all(grad[-2:] == 0)  # texels without samples
    assert np.all(np.isfinite(grad)) and np.all(loss >= 0)


@pytest.mark.parametrize(
    "weights",
    [LossWeights(), LossWeights(sss=0, s=0, phi=0, psi=1.0), LossWeights(sss=0, s=0, phi=1.0, psi=0)],
    ids=["paper", "psi-only", "phi-only"],
)
def test_value_and_gradient_match_autograd_reference(problem, weights):
    reference = _reference_loss(problem, weights)
    expected = torch.autograd.grad(reference, problem.leaves)
    value = fused_data_loss(pack_parameters(*problem.leaves), problem.fused, weights, problem.scale)
    got = torch.autograd.grad(value, problem.leaves)
    assert float(value.detach()) == pytest.approx(float(reference.detach()), rel=1e-12)
    for name, a, b in zip(NAMES, expected, got):
        np.testing.assert_allclose(
            b.numpy(), a.numpy(), rtol=1e-9, atol=1e-11 * float(a.abs().max()), err_msg=name
        )


def test_specular_only_and_subsurface_only_paths(problem):
    zero = torch.zeros(30, dtype=torch.float64)
    for variant in ({4: zero, 5: zero}, {6: torch.zeros(30, 6, dtype=torch.float64)}):
        leaves = [variant.get(i, leaf) for i, leaf in enumerate(problem.leaves)]
        reference = _reference_loss(problem, LossWeights(), leaves)
        expected = torch.autograd.grad(reference, problem.leaves[0])[0]
        value = fused_data_loss(pack_parameters(*leaves), problem.fused, LossWeights(), problem.scale)
        got = torch.autograd.grad(value, problem.leaves[0])[0]
        np.testing.assert_allclose(
            got.numpy(), expected.numpy(), rtol=1e-9, atol=1e-11 * float(expected.abs().max())
        )


def test_float32_kernel_agrees_with_float64(problem):
    params = pack_parameters(*problem.leaves).detach()
    leaf64 = params.clone().requires_grad_(True)
    value64 = fused_data_loss(leaf64, problem.fused, LossWeights(), problem.scale)
    (g64,) = torch.autograd.grad(value64, leaf64)
    leaf32 = params.float().requires_grad_(True)
    value32 = fused_data_loss(leaf32, problem.fused.astype(np.float32), LossWeights(), problem.scale)
    (g32,) = torch.autograd.grad(value32, leaf32)
    assert float(value32.detach()) == pytest.approx(float(value64.detach()), rel=1e-4)
    np.testing.assert_allclose(
        g32.double().numpy(), g64.numpy(), rtol=2e-3, atol=2e-4 * float(g64.abs().max())
    )


def test_result_does_not_depend_on_thread_count(problem):
    params = pack_parameters(*problem.leaves).detach().numpy()
    f = problem.fused
    args = (f, params, (1.0, 1.0, 1.0, 0.002), problem.scale)
    previous = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = fused_loss_and_grad(*args, chunks=7)
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        two = fused_loss_and_grad(*args, chunks=7)
    finally:
        numba.set_num_threads(previous)
    for a, b in zip(one, two):
        np.testing.assert_array_equal(a, b)


def test_gradcheck():
    small = _problem(seed=3, texels=4, frames=3, empty_texels=1)
    params = pack_parameters(*small.leaves).detach().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda p: fused_data_loss(p, small.fused, LossWeights(), small.scale), (params,), eps=1e-7, atol=1e-5
    )


def test_bad_input(problem):
    f = problem.fused
    params = pack_parameters(*problem.leaves).detach()
    with pytest.raises(ValueError, match="params"):
        fused_data_loss(params[:, :10], f, LossWeights(), problem.scale)
    with pytest.raises(ValueError, match="params"):
        fused_data_loss(params[:5], f, LossWeights(), problem.scale)
    with pytest.raises(ValueError, match="scale"):
        fused_data_loss(params, f, LossWeights(), 0.0)
    count = f.count
    views = f.view_center.shape[0]
    base = dict(
        position=f.position, texel=np.zeros(count, int), view=np.zeros(count, int),
        lit=np.ones((count, 8), bool), observed=np.ones((count, 3, 3)), view_center=f.view_center,
        view_up=f.view_up, view_ref_up=f.view_ref_up, light_pos=np.ones((views, 8, 3)),
        light_intensity=np.ones((views, 8, 3)), view_channels=f.view_channels,
    )  # fmt: skip
    observed = base["observed"].copy()
    observed[0, 1, 2] = np.nan
    for change, match in (
        ({"observed": observed}, "observed"),
        ({"observed": np.ones((count, 3))}, "observed"),
        ({"lit": np.ones((count, 7), bool)}, "lit"),
        ({"view": np.full(count, views)}, "view"),
        ({"texel": np.full(count, 10_000)}, "texel"),
        ({"light_pos": np.ones((views, 64, 3)), "light_intensity": np.ones((views, 64, 3)),
          "lit": np.ones((count, 64), bool)}, "light_pos"),
    ):  # fmt: skip
        with pytest.raises(ValueError, match=match):
            build_fused_samples(**{**base, **change})
    with pytest.raises(ValueError, match="float32 or float64"):
        fused_loss_and_grad(f, params.numpy().astype(np.float16), (1.0, 1.0, 1.0, 0.002), 1.0)
