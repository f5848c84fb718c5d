"""polarface.geometry.heights: normals from a displacement map (supplement, normals from heights)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from polarface.geometry import (
    height_gradients,
    normals_from_height_gradients,
    normals_from_heights,
    rasterize_uv,
)
from polarface.geometry.heights import HeightNormals

H, W = 12, 16


def flat_frame(dtype=torch.float64, s_u=0.3, s_v=0.5):
    t_u = torch.zeros(H, W, 3, dtype=dtype)
    t_u[..., 0] = 1
    t_v = torch.zeros(H, W, 3, dtype=dtype)
    t_v[..., 1] = 1
    n = torch.zeros(H, W, 3, dtype=dtype)
    n[..., 2] = 1
    return t_u, t_v, n, torch.full((H, W), s_u, dtype=dtype), torch.full((H, W), s_v, dtype=dtype)


def plane_heights(a: float, b: float, s_u: float, s_v: float, dtype=torch.float64) -> torch.Tensor:
    """H = a x + b y (mm) with x = column * s_u, y = (H - 1 - row) * s_v (row 0 at the top, +v up)."""
    cols = torch.arange(W, dtype=dtype) * s_u
    rows = (H - 1 - torch.arange(H, dtype=dtype)) * s_v
    return a * cols[None, :] + b * rows[:, None]


def test_flat_height_returns_base_normal():
    t_u, t_v, n, s_u, s_v = flat_frame()
    out = normals_from_heights(torch.full((H, W), 0.7, dtype=torch.float64), t_u, t_v, n, s_u, s_v)
    torch.testing.assert_close(out, n)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tilted_plane_analytic_normal_with_anisotropic_texels(dtype):
    # s_u != s_v: the supplement's matrix form (s_u, s_v swapped) would fail this
    s_u, s_v, a, b = 0.2, 0.6, 0.35, -0.2
    t_u, t_v, n, su, sv = flat_frame(dtype, s_u, s_v)
    out = normals_from_heights(plane_heights(a, b, s_u, s_v, dtype), t_u, t_v, n, su, sv)
    expected = torch.tensor([-a, -b, 1.0], dtype=dtype) / np.sqrt(1 + a * a + b * b)
    assert out.dtype == dtype and out.shape == (H, W, 3)
    torch.testing.assert_close(out, expected.expand(H, W, 3), atol=1e-6, rtol=0)


def test_gradients_central_masked_and_v_up():
    s_u, s_v = 1.0, 1.0
    height = plane_heights(2.0, 3.0, s_u, s_v)
    dh_du, dh_dv = height_gradients(height)
    torch.testing.assert_close(dh_du, torch.full((H, W), 2.0, dtype=torch.float64))
    torch.testing.assert_close(dh_dv, torch.full((H, W), 3.0, dtype=torch.float64))  # +v is up
    # quadratic: central differences are exact inside, one-sided at borders
    quad = (torch.arange(W, dtype=torch.float64) ** 2).expand(H, W)
    du, _ = height_gradients(quad)
    torch.testing.assert_close(du[:, 1:-1], 2 * torch.arange(1, W - 1, dtype=torch.float64).expand(H, W - 2))
    assert float(du[0, 0]) == 1.0 and float(du[0, -1]) == (W - 1) ** 2 - (W - 2) ** 2
    # a masked neighbour is not used: one-sided difference instead
    mask = torch.ones(H, W, dtype=torch.bool)
    mask[:, 5] = False
    du_m, _ = height_gradients(quad, mask)
    assert float(du_m[0, 4]) == 16 - 9 and float(du_m[0, 6]) == 49 - 36 and float(du_m[0, 5]) == 0.0
    # isolated texel: zero gradient
    lone = torch.zeros(H, W, dtype=torch.bool)
    lone[3, 3] = True
    du_l, dv_l = height_gradients(quad, lone)
    assert float(du_l.abs().sum()) == 0 and float(dv_l.abs().sum()) == 0


def test_masked_texels_keep_base_normal_and_no_nan():
    t_u, t_v, n, s_u, s_v = flat_frame()
    mask = torch.zeros(H, W, dtype=torch.bool)
    mask[2:8, 3:10] = True
    s_u = torch.where(mask, s_u, torch.zeros_like(s_u))  # raster-style zeros outside the atlas
    height = torch.randn(H, W, dtype=torch.float64)
    out = normals_from_heights(height, t_u, t_v, n, s_u, s_v, mask)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out[~mask], n[~mask])
    torch.testing.assert_close(
        torch.linalg.vector_norm(out[mask], dim=-1), torch.ones(int(mask.sum()), dtype=torch.float64)
    )


def test_mirrored_chart_and_non_orthogonal_tangents():
    # mirrored UVs (t_u x t_v = -n) still give a normal on the side of n; a tangent with a normal
    # component is projected out so that flat H returns n exactly
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    t_u = torch.tensor([-1.0, 0.0, 0.0], dtype=torch.float64)
    t_v = torch.tensor([0.0, 0.8, 0.6], dtype=torch.float64)
    zero = torch.zeros((), dtype=torch.float64)
    flat = normals_from_height_gradients(zero, zero, t_u, t_v, n, torch.tensor(0.3), torch.tensor(0.4))
    torch.testing.assert_close(flat, n)
    bumped = normals_from_height_gradients(
        torch.tensor(0.1, dtype=torch.float64), zero, t_u, t_v, n, torch.tensor(0.3), torch.tensor(0.3)
    )
    assert float(bumped[2]) > 0 and float(bumped[0]) > 0  # rising towards -x tilts the normal to +x


def test_gradcheck_float64():
    gen = torch.Generator().manual_seed(3)
    height = torch.randn(5, 6, dtype=torch.float64, generator=gen, requires_grad=True)
    t_u = torch.nn.functional.normalize(torch.randn(5, 6, 3, dtype=torch.float64, generator=gen), dim=-1)
    n = torch.nn.functional.normalize(torch.randn(5, 6, 3, dtype=torch.float64, generator=gen), dim=-1)
    t_v = torch.nn.functional.normalize(torch.linalg.cross(n, t_u), dim=-1)
    s_u = torch.rand(5, 6, dtype=torch.float64, generator=gen) + 0.1
    s_v = torch.rand(5, 6, dtype=torch.float64, generator=gen) + 0.1
    mask = torch.ones(5, 6, dtype=torch.bool)
    mask[0, 0] = False

    def fn(h, su):
        return normals_from_heights(h, t_u, t_v, n, su, s_v, mask)

    assert torch.autograd.gradcheck(fn, (height, s_u.requires_grad_()))
    dh_du = torch.randn(4, dtype=torch.float64, requires_grad=True)
    dh_dv = torch.randn(4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda a, b: normals_from_height_gradients(
            a, b, t_u[0, :4], t_v[0, :4], n[0, :4], s_u[0, :4], s_v[0, :4]
        ),
        (dh_du, dh_dv),
    )


def test_numpy_in_numpy_out_and_batch():
    t_u, t_v, n, s_u, s_v = (x.numpy() for x in flat_frame())
    batch = np.zeros((2, H, W))
    out = normals_from_heights(batch, t_u, t_v, n, s_u, s_v)
    assert isinstance(out, np.ndarray) and out.shape == (2, H, W, 3)


def test_errors():
    t_u, t_v, n, s_u, s_v = flat_frame()
    height = torch.zeros(H, W, dtype=torch.float64)
    with pytest.raises(ValueError, match="height"):
        normals_from_heights(torch.zeros(W, dtype=torch.float64), t_u, t_v, n, s_u, s_v)
    with pytest.raises(ValueError, match="tangent_u"):
        normals_from_heights(height, t_u[:, :-1], t_v, n, s_u, s_v)
    with pytest.raises(ValueError, match="mask"):
        normals_from_heights(height, t_u, t_v, n, s_u, s_v, torch.ones(3, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match="height"):
        normals_from_heights(torch.full((H, W), float("nan"), dtype=torch.float64), t_u, t_v, n, s_u, s_v)
    with pytest.raises(ValueError, match="texel_size_u"):
        normals_from_heights(height, t_u, t_v, n, -s_u, s_v)
    with pytest.raises(ValueError, match="normal"):
        normals_from_height_gradients(0.0, 0.0, [1.0, 0, 0], [0, 1.0, 0], [0, 1.0], 1.0, 1.0)


@settings(max_examples=25, deadline=None)
@given(st.floats(-1.5, 1.5), st.floats(-1.5, 1.5), st.floats(0.05, 2.0), st.floats(0.05, 2.0))
def test_property_plane_normal(a, b, s_u, s_v):
    t_u, t_v, n, su, sv = flat_frame(torch.float64, s_u, s_v)
    out = normals_from_heights(plane_heights(a, b, s_u, s_v), t_u, t_v, n, su, sv)
    expected = torch.tensor([-a, -b, 1.0], dtype=torch.float64) / np.sqrt(1 + a * a + b * b)
    torch.testing.assert_close(out, expected.expand(H, W, 3), atol=1e-9, rtol=0)


def test_sphere_atlas_bump_normals(uv_sphere_factory):
    # H = 0 on the raster of a sphere gives the interpolated normals; a constant H too
    sphere = uv_sphere_factory(50.0, 64, 32)
    raster = rasterize_uv(sphere, 64)
    args = (raster.tangent_u, raster.tangent_v, raster.normal, raster.texel_size_u, raster.texel_size_v)
    out = normals_from_heights(np.full((64, 64), 0.2, dtype=np.float32), *args, mask=raster.mask)
    np.testing.assert_allclose(out[raster.mask], raster.normal[raster.mask], atol=1e-5)


def _random_frame(seed: int, shape=(9, 11), dtype=torch.float64):
    generator = torch.Generator().manual_seed(seed)
    normal = torch.nn.functional.normalize(
        torch.randn(*shape, 3, generator=generator, dtype=dtype) * 0.2
        + torch.tensor([0.0, 0.0, 1.0], dtype=dtype),
        dim=-1,
    )
    tangent_u = torch.nn.functional.normalize(
        torch.randn(*shape, 3, generator=generator, dtype=dtype), dim=-1
    )
    tangent_v = torch.nn.functional.normalize(
        torch.randn(*shape, 3, generator=generator, dtype=dtype), dim=-1
    )
    size_u = torch.rand(shape, generator=generator, dtype=dtype) + 0.2
    size_v = torch.rand(shape, generator=generator, dtype=dtype) + 0.2
    size_u[0, 3] = 0.0  # degenerate texel keeps its base normal
    mask = torch.rand(shape, generator=generator) > 0.25
    height = torch.randn(shape, generator=generator, dtype=dtype) * 0.3
    return height, tangent_u, tangent_v, normal, size_u, size_v, mask


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_height_normals_operator_matches_normals_from_heights(seed):
    height, *frame, mask = _random_frame(seed)
    operator = HeightNormals.build(*frame, mask)
    expected = normals_from_heights(height, *frame, mask)
    torch.testing.assert_close(operator(height), expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(
        operator(torch.zeros_like(height)), normals_from_heights(height * 0, *frame, mask)
    )


def test_height_normals_operator_gradcheck_and_errors():
    height, *frame, mask = _random_frame(5, shape=(5, 6))
    operator = HeightNormals.build(*frame, mask)
    assert torch.autograd.gradcheck(operator, (height.clone().requires_grad_(True),))
    with pytest.raises(ValueError, match="texel_size_u"):
        HeightNormals.build(frame[0], frame[1], frame[2], -frame[3], frame[4], mask)
    with pytest.raises(ValueError, match="mask"):
        HeightNormals.build(*frame, mask[:-1])
    with pytest.raises(ValueError, match="normal"):
        HeightNormals.build(frame[0], frame[1], frame[2][..., :2], frame[3], frame[4], mask)
