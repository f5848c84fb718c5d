"""Fused per texel-view forward model: equals the library's render_polarimetric, shapes, errors, gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from polarface.inverse.polarimetric import precompute_samples, render_samples
from polarface.optics import render_polarimetric


def _scene(count: int = 24, seed: int = 0, same_up: bool = True):
    rng = np.random.default_rng(seed)
    position = rng.normal(size=(count, 3)) * 30 + np.array([0.0, 0.0, 1000.0])
    normal = rng.normal(size=(count, 3))
    normal[:, 2] = -np.abs(normal[:, 2]) - 1.5
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    centre = np.array([-30.0, 0.0, 0.0])
    up = np.array([0.0, -1.0, 0.1])
    up /= np.linalg.norm(up)
    reference = up if same_up else np.array([0.0, -1.0, 0.0])
    angle = np.arange(8) * 2 * np.pi / 8
    lights = np.stack([100 * np.cos(angle), 100 * np.sin(angle), np.zeros(8)], axis=1)
    params = {
        "eta": rng.uniform(1.15, 2.4, count),
        "alpha_s": rng.uniform(0.1, 0.6, count),
        "alpha_ss": rng.uniform(0.5, 1.0, count),
        "rho_s": rng.uniform(0, 1, count),
        "rho_ss": rng.uniform(0, 0.5, count),
        "rho_sss_bar": rng.uniform(0, 1, (count, 3)),
    }
    return position, normal, centre, up, reference, lights, params


def _batch(position, centre, up, reference, lights, lit=None, dtype=torch.float64, observed=None):
    count = len(position)
    lit = np.ones((count, len(lights)), bool) if lit is None else lit
    observed = np.zeros((count, 3, 3)) if observed is None else observed
    return precompute_samples(
        position,
        np.arange(count),
        np.zeros(count),
        np.tile(centre, (count, 1)),
        np.tile(up, (count, 1)),
        np.tile(reference, (count, 1)),
        lights,
        np.full((len(lights), 3), 1.0e6),
        np.tile([0, 1, 2], (count, 1)),
        lit,
        observed,
        dtype=dtype,
    )


def _render(batch, normal, params, dtype=torch.float64):
    t = lambda a: torch.as_tensor(a, dtype=dtype)  # noqa: E731
    return render_samples(
        batch,
        t(normal),
        *(t(params[k]) for k in ("eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss", "rho_sss_bar")),
    )


def test_matches_render_polarimetric_exactly():
    position, normal, centre, up, reference, lights, params = _scene()
    prediction = _render(_batch(position, centre, up, reference, lights), normal, params)
    t = torch.from_numpy
    ref = render_polarimetric(
        t(normal),
        t(position),
        t(centre),
        t(up),
        t(lights),
        torch.full((8, 3), 1.0e6),
        t(params["eta"])[:, None],
        t(params["alpha_s"])[:, None],
        t(params["alpha_ss"])[:, None],
        t(params["rho_s"])[:, None],
        t(params["rho_ss"])[:, None],
        t(params["rho_sss_bar"]),
    )
    for mine, theirs in (
        (prediction.i_sss, ref.i_sss),
        (prediction.i_zeta, ref.i_zeta),
        (prediction.i_s, ref.i_s),
    ):
        torch.testing.assert_close(mine, theirs, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(prediction.specular_s1, (ref.specular + ref.single_scattering)[..., 1])


def test_shadowed_lights_drop_out_and_shapes():
    position, normal, centre, up, reference, lights, params = _scene(count=10)
    lit = np.ones((10, 8), bool)
    lit[:, 3] = False
    prediction = _render(_batch(position, centre, up, reference, lights, lit=lit), normal, params)
    t = torch.from_numpy
    keep = [k for k in range(8) if k != 3]
    ref = render_polarimetric(
        t(normal),
        t(position),
        t(centre),
        t(up),
        t(lights[keep]),
        torch.full((7, 3), 1.0e6),
        t(params["eta"])[:, None],
        t(params["alpha_s"])[:, None],
        t(params["alpha_ss"])[:, None],
        t(params["rho_s"])[:, None],
        t(params["rho_ss"])[:, None],
        t(params["rho_sss_bar"]),
    )
    assert prediction.i_sss.shape == (10, 3)
    torch.testing.assert_close(prediction.i_s, ref.i_s)


def test_float32_batch_is_float32():
    position, normal, centre, up, reference, lights, params = _scene(count=5)
    batch = _batch(position, centre, up, reference, lights, dtype=torch.float32)
    prediction = _render(batch, normal, params, dtype=torch.float32)
    assert prediction.i_sss.dtype == torch.float32 and batch.light_vectors.shape == (5, 8, 4, 3)


def test_errors_name_the_argument():
    position, _, centre, up, reference, lights, _ = _scene(count=4)
    bad = np.zeros((4, 3, 3))
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="observed"):
        _batch(position, centre, up, reference, lights, observed=bad)
    with pytest.raises(ValueError, match="lit"):
        _batch(position, centre, up, reference, lights, lit=np.ones((4, 3), bool))
    with pytest.raises(ValueError, match="camera_center"):
        precompute_samples(
            position,
            np.arange(4),
            np.zeros(4),
            np.zeros((3, 3)),
            np.tile(up, (4, 1)),
            np.tile(reference, (4, 1)),
            lights,
            np.ones((8, 3)),
            np.zeros((4, 3)),
            np.ones((4, 8), bool),
            np.zeros((4, 3, 3)),
        )


def test_gradcheck_float64():
    position, normal, centre, up, reference, lights, params = _scene(count=3, seed=2, same_up=False)
    batch = _batch(position, centre, up, reference, lights)
    inputs = [torch.tensor(normal, requires_grad=True)] + [
        torch.tensor(params[k], requires_grad=True)
        for k in ("eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss", "rho_sss_bar")
    ]

    def func(*args):
        p = render_samples(batch, *args)
        return p.i_sss, p.i_zeta, p.i_s

    assert torch.autograd.gradcheck(func, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)
