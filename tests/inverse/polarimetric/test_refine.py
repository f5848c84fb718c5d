"""Lobe refinement (Levenberg-Marquardt on alpha_s, alpha_ss, rho_s, rho_ss): residual form of the data
loss, smoothness Hessian, noise-free recovery from a biased start, objective consistency, errors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from polarface.capture.rig import paper_rig
from polarface.geometry.poses import rigid_transform
from polarface.inverse.polarimetric import (
    LossWeights,
    PatchProblem,
    PolarimetricConfig,
    SamplePrediction,
    data_losses,
    maps_from_raw,
    precompute_samples,
    raw_from_maps,
    refine_lobes,
    refine_patch_lobes,
    render_samples,
    smoothness_hessian,
    smoothness_penalty,
    weighted_residuals,
)
from polarface.texture import TexelGeometry, build_views

TRUTH = {"eta": 1.47, "alpha_s": 0.35, "alpha_ss": 0.9, "rho_s": 0.6, "rho_ss": 0.25}
RHO_SSS = np.array([0.55, 0.4, 0.3, 0.5, 0.35, 0.25])
START = {"alpha_s": 0.5, "alpha_ss": 0.8, "rho_s": 0.3, "rho_ss": 0.15}


def _patch(side=1, dtype=torch.float64, noise=0.0, seed=0, vary=True):
    """A flat ``side x side`` patch at the model origin (normal +z) seen over chair yaws/pitches by both
    cameras; per-texel truth = TRUTH (with ``vary``: alpha_s/rho_s varied over the texels); noise
    relative to the mean observed I_sss."""
    rig = paper_rig(width=256, height=212)
    poses = []
    for yaw in np.radians(np.linspace(-50, 50, 7)):
        for pitch in np.radians((-25.0, 0.0, 25.0)):
            place = np.diag([1.0, -1.0, -1.0, 1.0])
            place[:3, 3] = (0.0, 0.0, 1000.0)
            poses.append(place @ rigid_transform(yaw=float(yaw), pitch=float(pitch)))
    views = build_views(rig, list(range(len(poses))), np.stack(poses))
    texels = side * side

    def pick(attr):
        table = np.array([getattr(v, attr) for v in views])
        return np.tile(table, (texels,) + (1,) * (table.ndim - 1))

    count = len(views) * texels
    texel = np.repeat(np.arange(texels), len(views))
    batch = precompute_samples(
        np.zeros((count, 3)),
        texel,
        np.tile(np.arange(len(views)), texels),
        pick("camera_center"),
        pick("camera_up"),
        pick("reference_up"),
        pick("light_positions"),
        pick("light_intensity"),
        pick("channels"),
        np.ones((count, 8), bool),
        np.zeros((count, 3, 3)),
        dtype=dtype,
    )
    variation = torch.linspace(0.0, 1.0, texels, dtype=dtype) * float(vary)
    truth = {k: torch.full((texels,), v, dtype=dtype) for k, v in TRUTH.items()}
    truth["alpha_s"] = truth["alpha_s"] + 0.05 * variation
    truth["rho_s"] = truth["rho_s"] + 0.2 * variation
    t = batch.texel
    normal = torch.tensor([[0.0, 0.0, 1.0]], dtype=dtype).expand(texels, 3)
    with torch.no_grad():
        p = render_samples(
            batch,
            normal[t],
            truth["eta"][t],
            truth["alpha_s"][t],
            truth["alpha_ss"][t],
            truth["rho_s"][t],
            truth["rho_ss"][t],
            torch.as_tensor(RHO_SSS, dtype=dtype)[batch.channels],
        )
    observed = torch.stack([p.i_sss, p.i_zeta, p.i_s], dim=1)
    scale = float(observed[:, 0].mean())
    if noise > 0:
        g = torch.Generator().manual_seed(seed)
        observed = observed + noise * scale * torch.randn(observed.shape, generator=g, dtype=dtype)
    batch = dataclasses.replace(batch, observed=observed)
    mask = torch.ones((side, side), dtype=torch.bool)
    return batch, normal.contiguous(), truth, scale, mask


def _start(texels, dtype=torch.float64):
    return {k: torch.full((texels,), v, dtype=dtype) for k, v in START.items()}


def _fixed(truth, texels, dtype=torch.float64):
    return truth["eta"], torch.as_tensor(RHO_SSS, dtype=dtype).expand(texels, 6).contiguous()


def test_weighted_residuals_reproduce_the_data_loss_and_gradcheck():
    g = torch.Generator().manual_seed(1)
    count = 7
    pred = [torch.rand(count, 3, generator=g, dtype=torch.float64) + 0.05 for _ in range(4)]
    observed = torch.rand(count, 3, 3, generator=g, dtype=torch.float64)
    observed[:, 1] -= 0.5
    observed[0, 0, 0] = -0.01  # W_phi clamp and the 5 % floor of the DoP denominators
    weights = LossWeights()
    prediction = SamplePrediction(*pred)
    r = weighted_residuals(prediction, observed, 0.6, weights)
    assert r.shape == (count, 15) and r.dtype == torch.float64
    terms = data_losses(prediction, observed, 0.6)
    expected = sum(getattr(weights, k) * terms[k] for k in ("sss", "s", "phi", "psi"))
    assert float((r * r).sum()) == pytest.approx(float(expected), rel=1e-12)

    def squared(*stack):
        return weighted_residuals(SamplePrediction(*stack), observed, 0.6, weights)

    leaves = tuple(p.clone().requires_grad_(True) for p in pred)
    assert torch.autograd.gradcheck(squared, leaves)
    with pytest.raises(ValueError, match="scale"):
        weighted_residuals(prediction, observed, 0.0, weights)
    with pytest.raises(ValueError, match="observed"):
        weighted_residuals(prediction, observed[:3], 0.6, weights)


def test_smoothness_hessian_matches_the_penalty():
    g = torch.Generator().manual_seed(2)
    mask = torch.ones((6, 7), dtype=torch.bool)
    mask[0, :3] = False
    mask[4, 5] = False
    x = torch.rand(6, 7, generator=g, dtype=torch.float64)
    hessian = smoothness_hessian(mask.numpy())
    assert hessian.shape == (42, 42)
    flat = x.reshape(-1).numpy()
    assert 0.5 * flat @ (hessian @ flat) == pytest.approx(float(smoothness_penalty(x, mask)), rel=1e-10)
    leaf = x.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(smoothness_penalty(leaf, mask), leaf)
    np.testing.assert_allclose(hessian @ flat, grad.reshape(-1).numpy(), rtol=1e-10, atol=1e-12)
    # a constant map costs nothing: the collective mode the refinement must be free to move
    np.testing.assert_allclose(hessian @ np.ones(42), 0.0, atol=1e-12)
    with pytest.raises(ValueError, match="mask"):
        smoothness_hessian(np.ones(5, bool))
    with pytest.raises(ValueError, match="window"):
        smoothness_hessian(np.ones((3, 3), bool), window=4)


def test_noise_free_single_texel_recovers_exact_lobes_from_a_biased_start():
    batch, normal, truth, scale, mask = _patch()
    eta, rho_sss = _fixed(truth, 1)
    result = refine_lobes(batch, normal, eta, rho_sss, _start(1), mask, scale=scale, iterations=40)
    assert result.objective[-1] < 1e-10 * result.objective[0]
    assert float(result.alpha_s[0]) == pytest.approx(TRUTH["alpha_s"], abs=1e-4)
    assert float(result.rho_s[0]) == pytest.approx(TRUTH["rho_s"], rel=1e-3)
    assert float(result.alpha_ss[0]) == pytest.approx(TRUTH["alpha_ss"], abs=1e-3)
    assert float(result.rho_ss[0]) == pytest.approx(TRUTH["rho_ss"], rel=1e-2)


def test_objective_is_the_fit_loss_and_never_increases():
    batch, normal, truth, scale, mask = _patch(side=3, noise=0.02)
    eta, rho_sss = _fixed(truth, 9)
    result = refine_lobes(batch, normal, eta, rho_sss, _start(9), mask, scale=scale, iterations=12)
    assert all(b <= a for a, b in zip(result.objective, result.objective[1:], strict=False))
    assert result.accepted[-4:] == [True] * 4
    # from the biased start down to (below: noise) the objective of the true lobes
    at_truth = refine_lobes(
        batch, normal, eta, rho_sss, {k: truth[k] for k in START}, mask, scale=scale, iterations=0
    )
    assert result.objective[-1] <= at_truth.objective[0] < 0.6 * result.objective[0]
    # the refined objective is the fit's loss (data + alpha smoothness; H = 0 and eta constant)
    config = PolarimetricConfig()
    geometry = TexelGeometry(
        np.zeros((3, 3, 3), np.float32),
        np.broadcast_to(np.array([0.0, 0.0, 1.0], np.float32), (3, 3, 3)).copy(),
        np.broadcast_to(np.array([1.0, 0.0, 0.0], np.float32), (3, 3, 3)).copy(),
        np.broadcast_to(np.array([0.0, 1.0, 0.0], np.float32), (3, 3, 3)).copy(),
        np.ones((3, 3), np.float32),
        np.ones((3, 3), np.float32),
        np.ones((3, 3), bool),
    )
    problem = PatchProblem(batch, geometry, config, scale, torch.float64, torch.device("cpu"))
    maps = {k: getattr(result, k).reshape(3, 3, 1).numpy() for k in START}
    maps["eta"] = np.full((3, 3, 1), TRUTH["eta"])
    maps["rho_sss_bar"] = np.broadcast_to(RHO_SSS, (3, 3, 6)).copy()
    maps["displacement_mm"] = np.zeros((3, 3, 1))
    raw = {k: torch.from_numpy(v) for k, v in raw_from_maps(maps, config).items()}
    with torch.no_grad():
        total = float(problem.loss(raw)[0]) * problem.texel_count
    assert total == pytest.approx(result.objective[-1], rel=1e-6)


def test_shapes_dtypes_and_zero_iterations():
    batch, normal, truth, scale, mask = _patch(side=2, dtype=torch.float32)
    eta, rho_sss = _fixed(truth, 4, torch.float32)
    start = _start(4, torch.float32)
    start["alpha_ss"] = torch.full((4,), 0.1)  # below alpha_s: projected above it (no lobe swap)
    result = refine_lobes(batch, normal, eta[:, None], rho_sss, start, mask, scale=scale, iterations=0)
    assert result.objective and not result.accepted
    for name in START:
        value = getattr(result, name)
        assert value.shape == (4,) and value.dtype == torch.float32
    assert bool((result.alpha_ss > result.alpha_s).all())
    assert torch.allclose(result.rho_s, start["rho_s"])
    refined = refine_lobes(batch, normal, eta, rho_sss, _start(4, torch.float32), mask, scale=scale)
    assert refined.objective[-1] <= refined.objective[0] and refined.alpha_s.dtype == torch.float32


@pytest.mark.parametrize(
    "change,match",
    [
        ({"normal": torch.zeros(4, 2)}, "normal"),
        ({"mask": torch.ones(3, 3, dtype=torch.bool)}, "mask"),
        ({"rho_sss_bar": torch.zeros(4, 3)}, "rho_sss_bar"),
        ({"eta": torch.ones(3)}, "eta"),
        ({"scale": 0.0}, "scale"),
        ({"iterations": -1}, "iterations"),
        ({"damping": 0.0}, "damping"),
        ({"alpha_range": (0.5, 0.1)}, "alpha_range"),
        ({"rho_max": -1.0}, "rho_max"),
    ],
)
def test_errors(change, match):
    batch, normal, truth, scale, mask = _patch(side=2)
    eta, rho_sss = _fixed(truth, 4)
    args = {"normal": normal, "eta": eta, "rho_sss_bar": rho_sss, "mask": mask, "scale": scale}
    args.update(change)
    kwargs = {k: args.pop(k) for k in list(args) if k not in ("normal", "eta", "rho_sss_bar", "mask")}
    with pytest.raises(ValueError, match=match):
        refine_lobes(
            batch, args["normal"], args["eta"], args["rho_sss_bar"], _start(4), args["mask"], **kwargs
        )


def test_bad_lobe_inputs():
    batch, normal, truth, scale, mask = _patch(side=2)
    eta, rho_sss = _fixed(truth, 4)
    lobes = _start(4)
    lobes["rho_s"] = torch.tensor([0.3, float("nan"), 0.3, 0.3], dtype=torch.float64)
    with pytest.raises(ValueError, match="rho_s"):
        refine_lobes(batch, normal, eta, rho_sss, lobes, mask, scale=scale)
    with pytest.raises(ValueError, match="lacks"):
        refine_lobes(batch, normal, eta, rho_sss, {"alpha_s": lobes["alpha_s"]}, mask, scale=scale)
    with pytest.raises(ValueError, match="alpha_ss"):
        refine_lobes(batch, normal, eta, rho_sss, {**_start(4), "alpha_ss": torch.ones(3)}, mask, scale=scale)


def test_refine_patch_lobes_on_raw_variables_and_config():
    batch, normal, truth, scale, mask = _patch(side=2, vary=False)
    config = PolarimetricConfig(refine_lobes_iterations=40)
    maps = {k: np.full((2, 2, 1), v) for k, v in START.items()}
    maps["eta"] = np.full((2, 2, 1), TRUTH["eta"])
    maps["rho_sss_bar"] = np.broadcast_to(RHO_SSS, (2, 2, 6)).copy()
    maps["displacement_mm"] = np.zeros((2, 2, 1))
    raw = {k: torch.from_numpy(v) for k, v in raw_from_maps(maps, config).items()}
    out = refine_patch_lobes(batch, raw, normal, mask, config, scale)
    assert set(out) == set(raw)
    for name in raw:
        assert out[name].shape == raw[name].shape and out[name].dtype == raw[name].dtype
    for name in ("eta", "rho_sss_bar", "displacement_mm"):
        assert torch.equal(out[name], raw[name])
    before, after = maps_from_raw(raw, config), maps_from_raw(out, config)
    error = lambda m: float((m["rho_s"].reshape(-1) - truth["rho_s"]).abs().max())  # noqa: E731
    assert error(after) < 0.01 * error(before)
    off = dataclasses.replace(config, refine_lobes_iterations=0)
    assert refine_patch_lobes(batch, raw, normal, mask, off, scale) is raw
    with pytest.raises(ValueError, match="refine_lobes_iterations"):
        PolarimetricConfig(refine_lobes_iterations=-1)
    with pytest.raises(ValueError, match="refine_lobes_damping"):
        PolarimetricConfig(refine_lobes_damping=0.0)
