"""Full pBSSRDF Mueller matrices: Mitsuba pplastic oracle, Eq. p_sss structure, coaxial model, laws."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from polarface.optics import (
    fresnel_terms,
    linear_polarizer,
    pbssrdf_coaxial_mueller,
    pbssrdf_mueller,
    pbssrdf_specular_mueller,
    pbssrdf_subsurface_mueller,
    plane_azimuth,
    rotator,
    stokes_frame,
)

from .conftest import random_unit


def _geometry(rng, count):
    """Random local geometry around n = +z: (normal, w_i, w_o, up), float64 numpy."""
    w_i = random_unit(rng, 4 * count, min_z=0.05)[:count]
    w_o = random_unit(rng, 4 * count, min_z=0.05)[:count]
    up = rng.normal(size=(count, 3))
    normal = np.tile([0.0, 0.0, 1.0], (count, 1))
    return normal, w_i, w_o, up


def _mitsuba_in_our_frames(mi, bsdf, w_i, w_o, up):
    """Mitsuba's pBSDF Mueller matrix (times cos theta_light) re-expressed in polarface's frames."""
    si = mi.SurfaceInteraction3f()
    si.p = [0.0, 0.0, 0.0]
    si.n = [0.0, 0.0, 1.0]
    si.sh_frame = mi.Frame3f([0.0, 0.0, 1.0])
    si.wi = mi.Vector3f(w_o)  # Mitsuba: si.wi points to the sensor
    si.wavelengths = [500.0, 550.0, 600.0, 650.0]
    ctx = mi.BSDFContext()
    matrix = bsdf.eval(ctx, si, mi.Vector3f(w_i))  # light arrives along -w_i
    x_in, _ = stokes_frame(-w_i, up)
    x_out, _ = stokes_frame(w_o, up)
    converted = mi.mueller.rotate_mueller_basis(
        matrix,
        mi.Vector3f(-w_i),
        mi.mueller.stokes_basis(mi.Vector3f(-w_i)),
        mi.Vector3f(x_in),
        mi.Vector3f(w_o),
        mi.mueller.stokes_basis(mi.Vector3f(w_o)),
        mi.Vector3f(x_out),
    )
    array = np.array(converted)
    return array[..., 0] if array.ndim == 3 else array  # wavelength-independent material


def _mitsuba_polarized_light(mi, bsdf, w_i, w_o, up, polarizer_angle):
    """Python wrapper giving Mitsuba a polarized emitter: unpolarized light through a linear polarizer
    at ``polarizer_angle`` from our light-frame x axis, then Mitsuba's pBSDF; Stokes in our camera frame."""
    x_in, _ = stokes_frame(-w_i, up)
    x_mi = np.array(mi.mueller.stokes_basis(mi.Vector3f(-w_i)))
    # polarizer in our light frame, re-expressed in Mitsuba's implicit basis of -w_i
    to_mi = np.array(mi.mueller.rotate_stokes_basis(mi.Vector3f(-w_i), mi.Vector3f(x_in), mi.Vector3f(x_mi)))
    light = to_mi @ linear_polarizer(polarizer_angle) @ np.array([2.0, 0.0, 0.0, 0.0])
    si_matrix = _mitsuba_in_our_frames(mi, bsdf, w_i, w_o, up)
    from_mi = np.linalg.inv(to_mi)
    return si_matrix @ (from_mi @ light)


@pytest.fixture(scope="module")
def plastic(mi):
    def make(eta, alpha, diffuse, specular):
        return mi.load_dict(
            {
                "type": "pplastic",
                "distribution": "ggx",
                "alpha": alpha,
                "int_ior": eta,
                "ext_ior": 1.0,
                "diffuse_reflectance": {"type": "uniform", "value": diffuse},
                "specular_reflectance": {"type": "uniform", "value": specular},
            }
        )

    return make


def test_mitsuba_oracle_pplastic_specular(mi, plastic):
    """P_s (x cos theta_i) equals Mitsuba 3 pplastic's specular lobe, 20 materials x 15 geometries.

    Absolute tolerance 2e-5 relative to the largest entry (Mitsuba evaluates in float32).
    """
    rng = np.random.default_rng(11)
    worst = 0.0
    for _ in range(20):
        eta, alpha = float(rng.uniform(1.2, 2.0)), float(rng.uniform(0.1, 0.9))
        bsdf = plastic(eta, alpha, 0.0, 1.0)
        normal, w_i, w_o, up = _geometry(rng, 15)
        ours = pbssrdf_specular_mueller(normal, w_i, w_o, up, eta, alpha, 1.0) * w_i[:, 2, None, None]
        for k in range(len(w_i)):
            ref = _mitsuba_in_our_frames(mi, bsdf, w_i[k], w_o[k], up[k])
            worst = max(worst, float(np.abs(ours[k] - ref).max() / np.abs(ref).max()))
    assert worst < 2e-5, worst


def test_mitsuba_oracle_pplastic_diffuse_structure(mi, plastic):
    """The local P_sss (rho / pi) equals pplastic's diffuse lobe (T_o D T_i between the frames).

    Tolerance 5e-5 relative to the largest entry (float32 oracle; its exit Fresnel is evaluated from
    the refracted internal angle, ours from the air angle by reciprocity).
    """
    rng = np.random.default_rng(12)
    worst = 0.0
    for _ in range(20):
        eta, albedo = float(rng.uniform(1.2, 2.0)), float(rng.uniform(0.1, 1.0))
        bsdf = plastic(eta, 0.3, albedo, 0.0)
        normal, w_i, w_o, up = _geometry(rng, 15)
        ours = pbssrdf_subsurface_mueller(normal, w_i, normal, w_o, up, eta, eta, albedo / math.pi)
        ours = ours * w_i[:, 2, None, None]
        for k in range(len(w_i)):
            ref = _mitsuba_in_our_frames(mi, bsdf, w_i[k], w_o[k], up[k])
            worst = max(worst, float(np.abs(ours[k] - ref).max() / np.abs(ref).max()))
    assert worst < 5e-5, worst


def test_mitsuba_oracle_polarized_light(mi, plastic):
    """Output Stokes for polarized LEDs ([1, 1, 0, 0] and a 30 deg polarizer) through the full local
    model vs Mitsuba with the Python polarizer wrapper (specular + diffuse lobes together)."""
    rng = np.random.default_rng(13)
    eta, alpha, albedo = 1.44, 0.45, 0.6
    bsdf = plastic(eta, alpha, albedo, 1.0)
    normal, w_i, w_o, up = _geometry(rng, 40)
    full = pbssrdf_mueller(normal, w_i, w_o, up, eta, alpha, alpha, 1.0, 0.0, albedo) * w_i[:, 2, None, None]
    for angle in (0.0, math.radians(30)):
        s_in = linear_polarizer(angle) @ np.array([2.0, 0, 0, 0])
        for k in range(len(w_i)):
            ref = _mitsuba_polarized_light(mi, bsdf, w_i[k], w_o[k], up[k], angle)
            np.testing.assert_allclose(full[k] @ s_in, ref, atol=3e-5 * np.abs(ref).max())


def test_psss_matches_printed_matrix():
    """Main paper Eq. p_sss: the product equals the printed rank-1 matrix with xi, zeta = cos, sin 2 phi."""
    rng = np.random.default_rng(4)
    normal_i = random_unit(rng, 400, min_z=0.3)[:50]
    normal_o = random_unit(rng, 400, min_z=0.3)[:50]
    w_i = random_unit(rng, 400, min_z=0.2)[:50]
    w_o = random_unit(rng, 400, min_z=0.2)[:50]
    up = np.array([0.1, 1.0, 0.2])
    keep = (np.sum(normal_i * w_i, -1) > 0.05) & (np.sum(normal_o * w_o, -1) > 0.05)
    normal_i, normal_o, w_i, w_o = normal_i[keep], normal_o[keep], w_i[keep], w_o[keep]
    eta_i, eta_o, profile = 1.4, 1.5, 0.37
    matrix = pbssrdf_subsurface_mueller(normal_i, w_i, normal_o, w_o, up, eta_i, eta_o, profile)
    x_in, y_in = stokes_frame(-w_i, up)
    x_out, y_out = stokes_frame(w_o, up)
    phi_i = plane_azimuth(normal_i, x_in, y_in)
    phi_o = plane_azimuth(normal_o, x_out, y_out)
    xi_i, zeta_i, xi_o, zeta_o = np.cos(2 * phi_i), np.sin(2 * phi_i), np.cos(2 * phi_o), np.sin(2 * phi_o)
    ti = fresnel_terms(np.sum(normal_i * w_i, -1), eta_i)
    to = fresnel_terms(np.sum(normal_o * w_o, -1), eta_o)
    zero = np.zeros_like(xi_i)
    printed = profile * np.stack(
        [
            np.stack(
                [
                    ti.t_plus * to.t_plus,
                    -ti.t_minus * to.t_plus * xi_i,
                    -ti.t_minus * to.t_plus * zeta_i,
                    zero,
                ],
                -1,
            ),
            np.stack(
                [
                    -ti.t_plus * to.t_minus * xi_o,
                    ti.t_minus * to.t_minus * xi_i * xi_o,
                    ti.t_minus * to.t_minus * zeta_i * xi_o,
                    zero,
                ],
                -1,
            ),
            np.stack(
                [
                    -ti.t_plus * to.t_minus * zeta_o,
                    ti.t_minus * to.t_minus * xi_i * zeta_o,
                    ti.t_minus * to.t_minus * zeta_i * zeta_o,
                    zero,
                ],
                -1,
            ),
            np.stack([zero, zero, zero, zero], -1),
        ],
        -2,
    )
    np.testing.assert_allclose(matrix, printed, atol=1e-14)
    assert np.all(np.linalg.matrix_rank(matrix) == 1)


def test_coaxial_simplification_equals_full_model_at_coaxial_geometry():
    rng = np.random.default_rng(6)
    normal = random_unit(rng, 400, min_z=0.1)[:100]
    w = random_unit(rng, 400, min_z=0.1)[:100]
    keep = np.sum(normal * w, -1) > 0.02
    normal, w = normal[keep], w[keep]
    up = np.array([0.0, 1.0, 0.0])
    params = {
        "eta": 1.44,
        "alpha_s": 0.45,
        "alpha_ss": 0.95,
        "rho_s": 0.8,
        "rho_ss": 0.3,
        "rho_sss_bar": 0.55,
    }
    full = pbssrdf_mueller(normal, w, w, up, **params)
    exact = pbssrdf_coaxial_mueller(normal, w, up, **params, keep_t_minus_squared=True)
    np.testing.assert_allclose(exact, full, atol=1e-13)
    simplified = pbssrdf_coaxial_mueller(normal, w, up, **params)
    # the only difference is the dropped r T-^2 block, bounded by rho_sss_bar / pi * T-^2
    t_minus = fresnel_terms(np.sum(normal * w, -1), 1.44).t_minus
    bound = params["rho_sss_bar"] / math.pi * t_minus**2
    assert np.all(np.abs(full - simplified).max(axis=(-1, -2)) <= bound + 1e-15)
    assert np.abs(full - simplified)[:, 0].max() < 1e-15  # first row (and I90-relevant s0) untouched
    # the supplement's coaxial relations between the in/out azimuths
    x_in, y_in = stokes_frame(-w, up)
    x_out, y_out = stokes_frame(w, up)
    total = plane_azimuth(normal, x_in, y_in) + plane_azimuth(normal, x_out, y_out)
    np.testing.assert_allclose(np.cos(total), -1.0, atol=1e-12)  # phi_i = pi - phi_o (mod 2 pi)


def test_coaxial_specular_keeps_led_state():
    """Under exactly coaxial polarized light the specular stays [k, k, 0, 0]: no specular in I90."""
    rng = np.random.default_rng(8)
    normal = random_unit(rng, 100, min_z=0.3)
    w = np.tile([0.0, 0.0, 1.0], (len(normal), 1))
    p_s = pbssrdf_specular_mueller(normal, w, w, np.array([0.0, 1.0, 0.0]), 1.44, 0.45, 1.0)
    out = p_s @ np.array([1.0, 1.0, 0.0, 0.0])
    np.testing.assert_allclose(out[:, 1], out[:, 0], atol=1e-15)
    np.testing.assert_allclose(out[:, 2:], 0.0, atol=1e-15)


st_unit = st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(0.05, 1)).map(
    lambda v: np.array(v) / np.linalg.norm(v)
)


@settings(max_examples=50, deadline=None)
@given(
    st_unit,
    st_unit,
    st_unit,
    st.floats(1.05, 2.0),
    st.floats(0.05, 1.0),
    st.tuples(st.floats(0.01, 5), st.floats(0, 1), st.floats(-3, 3), st.floats(-1.5, 1.5)),
)
def test_full_model_keeps_stokes_physical(normal, w_i, w_o, eta, alpha, stokes_params):
    s0, dop, a, b = stokes_params
    s_in = s0 * np.array(
        [1.0, dop * math.cos(a) * math.cos(b), dop * math.sin(a) * math.cos(b), dop * math.sin(b)]
    )
    up = np.array([0.2, 1.0, -0.3])
    matrix = pbssrdf_mueller(normal, w_i, w_o, up, eta, alpha, 2 * alpha, 0.7, 0.4, 0.5)
    out = matrix @ s_in
    assert np.all(np.isfinite(out))
    assert out[0] + 1e-12 >= math.sqrt(out[1] ** 2 + out[2] ** 2 + out[3] ** 2)


def test_frames_rotate_consistently():
    """Changing the camera up vector only rotates the output Stokes vector (and the input frame)."""
    rng = np.random.default_rng(9)
    normal, w_i, w_o, _ = _geometry(rng, 20)
    up_a, up_b = np.array([0.0, 1.0, 0.0]), np.array([0.6, 0.8, 0.0])
    m_a = pbssrdf_mueller(normal, w_i, w_o, up_a, 1.44, 0.45, 0.95, 1.0, 0.3, 0.5)
    m_b = pbssrdf_mueller(normal, w_i, w_o, up_b, 1.44, 0.45, 0.95, 1.0, 0.3, 0.5)
    from polarface.optics import frame_rotation_angle

    xa_in, ya_in = stokes_frame(-w_i, up_a)
    xb_in, _ = stokes_frame(-w_i, up_b)
    xa_out, ya_out = stokes_frame(w_o, up_a)
    xb_out, _ = stokes_frame(w_o, up_b)
    rot_in = rotator(frame_rotation_angle(xa_in, ya_in, xb_in))
    rot_out = rotator(frame_rotation_angle(xa_out, ya_out, xb_out))
    np.testing.assert_allclose(rot_out @ m_a @ np.linalg.inv(rot_in), m_b, atol=1e-14)


def test_back_facing_and_degenerate_no_nan():
    normal = torch.tensor([[0.0, 0.0, 1.0]] * 4, dtype=torch.float64, requires_grad=True)
    w_i = torch.tensor(
        [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.6, -0.8], [0.6, 0.0, 0.8]], dtype=torch.float64
    )
    w_o = torch.tensor(
        [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.6, 0.0, 0.8]], dtype=torch.float64
    )
    w_i.requires_grad_(True)
    w_o.requires_grad_(True)
    eta = torch.tensor(1.44, dtype=torch.float64, requires_grad=True)
    matrix = pbssrdf_mueller(
        normal, w_i, w_o, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), eta, 0.45, 0.95, 1.0, 0.3, 0.5
    )
    assert torch.isfinite(matrix).all()
    assert float(matrix[2].detach().abs().max()) == 0.0  # light below the horizon
    matrix.sum().backward()
    for grad in (normal.grad, w_i.grad, w_o.grad, eta.grad):
        assert torch.isfinite(grad).all()


def test_gradcheck_full_matrices():
    rng = np.random.default_rng(10)
    normal, w_i, w_o, up = (torch.tensor(a) for a in _geometry(rng, 3))
    leaves = [t.clone().requires_grad_(True) for t in (normal, w_i, w_o)]
    eta = torch.tensor([1.3, 1.5, 1.7], dtype=torch.float64, requires_grad=True)
    alpha = torch.tensor([0.3, 0.5, 0.9], dtype=torch.float64, requires_grad=True)
    rho = torch.tensor([0.4, 0.6, 0.8], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda n, a, b, e, al, r: pbssrdf_specular_mueller(n, a, b, up, e, al, r), (*leaves, eta, alpha, rho)
    )
    assert torch.autograd.gradcheck(
        lambda n, a, b, e, r: pbssrdf_subsurface_mueller(n, a, n, b, up, e, e, r), (*leaves, eta, rho)
    )
    assert torch.autograd.gradcheck(
        lambda n, a, b, e, al, r: pbssrdf_mueller(n, a, b, up, e, al, 2 * al, r, r, r / 2),
        (*leaves, eta, alpha, rho),
    )
    assert torch.autograd.gradcheck(
        lambda n, b, e, al, r: pbssrdf_coaxial_mueller(n, b, up, e, al, 2 * al, r, r, r),
        (leaves[0], leaves[2], eta, alpha, rho),
    )


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda g: pbssrdf_specular_mueller(g[0], g[1] * 2, g[2], g[3], 1.4, 0.3, 1.0), "w_i"),
        (lambda g: pbssrdf_specular_mueller(g[0], g[1], g[2], g[3], 0.9, 0.3, 1.0), "eta"),
        (lambda g: pbssrdf_specular_mueller(g[0], g[1], g[2], g[3], 1.4, 0.0, 1.0), "alpha"),
        (lambda g: pbssrdf_specular_mueller(g[0], g[1], g[2], g[3], 1.4, 0.3, -1.0), "rho"),
        (lambda g: pbssrdf_mueller(g[0], g[1], g[2], g[3], 1.4, 0.3, 0.9, 1.0, 0.3, 1.5), "rho_sss_bar"),
        (lambda g: pbssrdf_mueller(g[0], g[1], g[2], g[3], np.full(7, 1.4), 0.3, 0.9, 1.0, 0.3, 0.5), "eta"),
        (lambda g: pbssrdf_mueller(g[0][:2], g[1], g[2], g[3], 1.4, 0.3, 0.9, 1.0, 0.3, 0.5), "normal"),
        (lambda g: pbssrdf_coaxial_mueller(g[0], g[2], g[3][:, :2], 1.4, 0.3, 0.9, 1.0, 0.3, 0.5), "up"),
        (
            lambda g: pbssrdf_subsurface_mueller(g[0], g[1], g[0], g[2], g[3], 1.4, 1.4, float("nan")),
            "profile",
        ),
    ],
)
def test_bad_input(call, name):
    geometry = _geometry(np.random.default_rng(0), 3)
    with pytest.raises(ValueError, match=name):
        call(geometry)
