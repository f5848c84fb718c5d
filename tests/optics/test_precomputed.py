"""Precomputed-geometry forward model equals render_polarimetric; kinds, gradients, bad input."""

import numpy as np
import pytest
import torch

from polarface.optics import precompute_geometry, render_polarimetric, render_precomputed

F64 = torch.float64


def _setup(count=30, seed=1):
    gen = torch.Generator().manual_seed(seed)
    normal = torch.nn.functional.normalize(
        torch.randn(count, 3, generator=gen, dtype=F64) + torch.tensor([0, 0, -1.5], dtype=F64), dim=-1
    )
    position = torch.randn(count, 3, generator=gen, dtype=F64) * 30 + torch.tensor([0, 0, 1000.0], dtype=F64)
    lights = torch.randn(4, 3, generator=gen, dtype=F64) * 150
    stokes = torch.tensor(
        [[1.0, 1.0, 0, 0], [1.0, 0, 0.6, 0.3], [1.0, -0.2, 0.1, 0], [1.0, 1.0, 0, 0]], dtype=F64
    )
    intensity = torch.rand(4, 3, generator=gen, dtype=F64) * 1e6
    return (
        normal,
        position,
        torch.tensor([3.0, 2.0, 0.0], dtype=F64),
        torch.tensor([0.1, -1, 0], dtype=F64),
        lights,
        stokes,
        intensity,
    )


@pytest.mark.parametrize("per_channel", [False, True])
def test_equals_render_polarimetric(per_channel):
    normal, position, camera, up, lights, stokes, intensity = _setup()
    if per_channel:
        params = (
            torch.tensor([1.4, 1.45, 1.5], dtype=F64),
            torch.tensor([0.3, 0.4, 0.5], dtype=F64),
            0.9,
            torch.rand(30, 3, dtype=F64),
            0.3,
            torch.rand(30, 3, dtype=F64),
        )
    else:
        params = (1.44, torch.full((30, 1), 0.45, dtype=F64), 0.95, 1.0, torch.rand(30, 1, dtype=F64), 0.5)
    reference = render_polarimetric(
        normal, position, camera, up, lights, intensity, *params, light_stokes=stokes
    )
    geometry = precompute_geometry(normal, position, camera, up, lights, stokes)
    assert geometry.light_count == 4
    fast = render_precomputed(geometry, intensity, *params)
    scale = float(reference.stokes.abs().max())
    for name in ("stokes", "specular", "single_scattering", "subsurface", "i0", "i135"):
        torch.testing.assert_close(getattr(fast, name), getattr(reference, name), atol=1e-13 * scale, rtol=0)
    exitance = torch.rand(30, 3, dtype=F64)
    a = render_polarimetric(
        normal,
        position,
        camera,
        up,
        lights,
        intensity,
        *params,
        light_stokes=stokes,
        diffused_exitance=exitance,
    )
    b = render_precomputed(geometry, intensity, *params, diffused_exitance=exitance)
    torch.testing.assert_close(a.stokes, b.stokes, atol=1e-13 * scale, rtol=0)


def test_numpy_kind_and_image_shapes():
    normal, position, camera, up, lights, _, intensity = _setup(12)
    geometry = precompute_geometry(
        normal.numpy().reshape(3, 4, 3),
        position.numpy().reshape(3, 4, 3),
        camera.numpy(),
        up.numpy(),
        lights.numpy(),
    )
    out = render_precomputed(geometry, intensity.numpy(), 1.44, 0.45, 0.95, 1.0, 0.3, 0.5)
    assert isinstance(out.i0, np.ndarray) and out.i0.shape == (3, 4, 3)
    assert np.isfinite(out.stokes).all()


def test_gradcheck():
    normal, position, camera, up, lights, stokes, intensity = _setup(4)
    geometry = precompute_geometry(normal, position, camera, up, lights, stokes)
    leaves = [
        torch.tensor(v, dtype=F64, requires_grad=True)
        for v in ([[1.4]] * 4, [0.4], [0.9], [0.8], [0.3], [0.5, 0.6, 0.4])
    ]

    def forward(*params):
        out = render_precomputed(geometry, intensity / 1e6, *params)
        return out.i0, out.i45, out.i90

    assert torch.autograd.gradcheck(forward, tuple(leaves))


@pytest.mark.parametrize(
    ("change", "name"),
    [
        ({"eta": 0.9}, "eta"),
        ({"rho_sss_bar": -0.1}, "rho_sss_bar"),
        ({"light_intensity": torch.ones(5, 3)}, "light_intensity"),
        ({"alpha_s": torch.ones(7, 1)}, "alpha_s"),
        ({"diffused_exitance": -torch.ones(1)}, "diffused_exitance"),
    ],
)
def test_bad_input(change, name):
    normal, position, camera, up, lights, stokes, intensity = _setup(5)
    geometry = precompute_geometry(normal, position, camera, up, lights, stokes)
    kwargs = {
        "light_intensity": intensity,
        "eta": 1.44,
        "alpha_s": 0.45,
        "alpha_ss": 0.95,
        "rho_s": 1.0,
        "rho_ss": 0.3,
        "rho_sss_bar": 0.5,
    }
    kwargs.update(change)
    with pytest.raises(ValueError, match=name):
        render_precomputed(geometry, **kwargs)
    with pytest.raises(ValueError, match="normal"):
        precompute_geometry(normal * 2, position, camera, up, lights)
