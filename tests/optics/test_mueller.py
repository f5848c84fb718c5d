"""Mueller matrices and Stokes frames: Mitsuba 3 oracle, physics laws, gradients, bad input."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from polarface.optics import (
    analyzer_intensity,
    depolarizer,
    double_angle_cos_sin,
    frame_rotation_angle,
    fresnel_reflectance,
    incidence_frame_angle,
    linear_polarizer,
    mueller_fresnel_reflection,
    mueller_fresnel_transmission,
    plane_azimuth,
    rotator,
    stokes_frame,
)

angles = st.floats(-2 * math.pi, 2 * math.pi, allow_nan=False)


def _physical_stokes(draw_values):
    s0, r, a, b = draw_values
    # uniform direction on the Poincare sphere scaled by DoP r <= 1
    v = np.array([math.cos(a) * math.cos(b), math.sin(a) * math.cos(b), math.sin(b)])
    return np.concatenate([[s0], s0 * r * v])


stokes_strategy = st.tuples(
    st.floats(0.01, 10.0),
    st.floats(0.0, 1.0),
    st.floats(-math.pi, math.pi),
    st.floats(-math.pi / 2, math.pi / 2),
).map(_physical_stokes)


def _is_physical(s: np.ndarray, tol: float = 1e-9) -> bool:
    return s[0] + tol >= math.sqrt(s[1] ** 2 + s[2] ** 2 + s[3] ** 2)


def test_rotator_equation_ccrot():
    theta = 0.3
    c, s = math.cos(0.6), math.sin(0.6)
    expected = np.array([[1, 0, 0, 0], [0, c, s, 0], [0, -s, c, 0], [0, 0, 0, 1]])
    np.testing.assert_allclose(rotator(theta), expected, atol=1e-15)
    assert rotator(np.zeros((2, 5))).shape == (2, 5, 4, 4)
    assert rotator(torch.zeros(3, dtype=torch.float32)).dtype == torch.float32


def test_rotator_semantics_and_group_law():
    theta = 0.4
    polarized_at_theta = np.array([1.0, math.cos(2 * theta), math.sin(2 * theta), 0.0])
    np.testing.assert_allclose(rotator(theta) @ polarized_at_theta, [1, 1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(rotator(0.2) @ rotator(0.5), rotator(0.7), atol=1e-15)
    np.testing.assert_allclose(rotator(math.pi), np.eye(4), atol=1e-15)


def test_mitsuba_oracle_rotator(mi):
    """Mitsuba's ``mueller.rotator`` equals C(theta) on 300 random angles (float32: atol 2e-6)."""
    rng = np.random.default_rng(0)
    for theta in rng.uniform(-4, 4, 300):
        np.testing.assert_allclose(
            rotator(float(theta)), np.array(mi.mueller.rotator(float(theta))), atol=2e-6
        )


def test_mitsuba_oracle_fresnel_matrices(mi):
    """F^R and F^T against ``mi.mueller.specular_reflection`` / ``specular_transmission``.

    400 random (cos, eta) pairs, both sides of the Brewster angle; float32 oracle: atol 3e-6.
    Mitsuba's transmission matrix carries no eta^2 radiance factor either, and T = 1 - R.
    """
    rng = np.random.default_rng(1)
    worst_r = worst_t = 0.0
    for cos, eta in zip(rng.uniform(0.0, 1.0, 400), rng.uniform(1.05, 2.5, 400)):
        ours_r = mueller_fresnel_reflection(float(cos), float(eta))
        ref_r = np.array(mi.mueller.specular_reflection(float(cos), float(eta)))
        ours_t = mueller_fresnel_transmission(float(cos), float(eta))
        ref_t = np.array(mi.mueller.specular_transmission(float(cos), float(eta)))
        worst_r = max(worst_r, float(np.abs(ours_r - ref_r).max()))
        worst_t = max(worst_t, float(np.abs(ours_t - ref_t).max()))
    assert worst_r < 3e-6, worst_r
    assert worst_t < 3e-6, worst_t


def test_fresnel_reflection_phase_rule():
    eta = 1.5
    below = mueller_fresnel_reflection(math.cos(math.radians(30)), eta)
    above = mueller_fresnel_reflection(math.cos(math.radians(70)), eta)
    r_perp, r_par = fresnel_reflectance(math.cos(math.radians(30)), eta)
    assert below[2, 2] == pytest.approx(-math.sqrt(r_perp * r_par))  # cos delta = -1
    assert above[2, 2] > 0 and above[3, 3] > 0  # cos delta = +1
    assert below[2, 3] == 0 and below[3, 2] == 0  # sin delta = 0
    normal = mueller_fresnel_reflection(1.0, eta)
    r = ((eta - 1) / (eta + 1)) ** 2
    np.testing.assert_allclose(normal, np.diag([r, r, -r, -r]), atol=1e-15)


def test_fresnel_transmission_structure():
    m = mueller_fresnel_transmission(0.6, 1.44)
    assert m[0, 1] < 0  # T_par > T_perp
    assert m[2, 2] == pytest.approx(math.sqrt((m[0, 0] + m[0, 1]) * (m[0, 0] - m[0, 1])))
    assert m[2, 3] == 0


def test_linear_polarizer_and_malus():
    for theta in (0.0, 0.3, 1.2):
        p = linear_polarizer(theta)
        out = p @ np.array([1.0, 0, 0, 0])
        assert out[0] == pytest.approx(0.5)
        for analyzer in (0.0, 0.7, 2.0):
            measured = analyzer_intensity(out, analyzer)
            assert measured == pytest.approx(0.5 * math.cos(analyzer - theta) ** 2, abs=1e-12)
    np.testing.assert_allclose(
        linear_polarizer(0.2) @ linear_polarizer(0.2), linear_polarizer(0.2), atol=1e-15
    )
    crossed = linear_polarizer(0.2 + math.pi / 2) @ linear_polarizer(0.2)
    np.testing.assert_allclose(crossed, 0.0, atol=1e-15)


def test_mitsuba_oracle_polarizer(mi):
    """Mitsuba's horizontal polarizer rotated by theta (``rotated_element``) equals ours at theta."""
    for theta in np.linspace(-1.5, 1.5, 13):
        ref = mi.mueller.rotated_element(float(theta), mi.mueller.linear_polarizer(1.0))
        np.testing.assert_allclose(linear_polarizer(float(theta)), np.array(ref), atol=2e-6)


def test_depolarizer():
    np.testing.assert_allclose(depolarizer(0.5), np.diag([0.5, 0, 0, 0]))
    with pytest.raises(ValueError, match="albedo"):
        depolarizer(-0.1)


@settings(max_examples=60, deadline=None)
@given(stokes_strategy, st.floats(0.0, 1.0), st.floats(1.01, 2.5), angles, angles)
def test_model_matrices_keep_stokes_physical(stokes, cos, eta, a, b):
    for matrix in (
        mueller_fresnel_reflection(cos, eta),
        mueller_fresnel_transmission(cos, eta),
        rotator(a) @ mueller_fresnel_reflection(cos, eta) @ rotator(b),
        linear_polarizer(a) @ mueller_fresnel_transmission(cos, eta),
        mueller_fresnel_transmission(cos, eta) @ depolarizer(0.7) @ mueller_fresnel_transmission(cos, eta),
    ):
        assert _is_physical(matrix @ stokes)


@settings(max_examples=40, deadline=None)
@given(stokes_strategy, angles)
def test_stokes_round_trip_rotations(stokes, theta):
    np.testing.assert_allclose(rotator(-theta) @ (rotator(theta) @ stokes), stokes, atol=1e-9)


def test_stokes_frame_camera_convention():
    # OpenCV camera at the origin looking along +z; light reaching it travels along -z.
    up = np.array([0.0, -1.0, 0.0])  # camera up = image -y
    x_axis, y_axis = stokes_frame(np.array([0.0, 0.0, -1.0]), up)
    np.testing.assert_allclose(x_axis, [1, 0, 0], atol=1e-15)  # image +x
    np.testing.assert_allclose(y_axis, [0, -1, 0], atol=1e-15)  # camera up
    # right-handed with the propagation direction
    np.testing.assert_allclose(np.cross(x_axis, y_axis), [0, 0, -1], atol=1e-15)
    # ray parallel to up: documented fallback, still orthonormal
    x_axis, y_axis = stokes_frame(np.array([0.0, 1.0, 0.0]), up)
    assert abs(np.dot(x_axis, y_axis)) < 1e-12 and abs(np.dot(y_axis, [0, 1, 0])) < 1e-12


def test_mitsuba_oracle_frame_rotation(mi):
    """``frame_rotation_angle`` + ``rotator`` equals ``mi.mueller.rotate_stokes_basis`` (200 cases)."""
    rng = np.random.default_rng(5)
    for _ in range(200):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        x_from, y_from = stokes_frame(d, rng.normal(size=3))
        x_to, _ = stokes_frame(d, rng.normal(size=3))
        ours = rotator(frame_rotation_angle(x_from, y_from, x_to))
        ref = np.array(mi.mueller.rotate_stokes_basis(mi.Vector3f(d), mi.Vector3f(x_from), mi.Vector3f(x_to)))
        np.testing.assert_allclose(ours, ref, atol=5e-6)
        # Mitsuba's implicit basis uses the same handedness: y = d x x
        x_mi = np.array(mi.mueller.stokes_basis(mi.Vector3f(d)))
        s = np.array([1.0, 0.3, -0.2, 0.1])
        there = rotator(frame_rotation_angle(x_from, y_from, x_mi)) @ s
        back = rotator(frame_rotation_angle(x_mi, np.cross(d, x_mi), x_from)) @ there
        np.testing.assert_allclose(back, s, atol=5e-6)


def test_plane_azimuth_and_double_angle():
    x_axis, y_axis = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    for phi in (0.0, 0.3, 2.0, -2.5):
        v = np.array([math.cos(phi), math.sin(phi), 0.7])
        assert plane_azimuth(v, x_axis, y_axis) == pytest.approx(phi)
        c, s = double_angle_cos_sin(torch.tensor(v), torch.tensor(x_axis), torch.tensor(y_axis))
        assert float(c) == pytest.approx(math.cos(2 * phi)) and float(s) == pytest.approx(math.sin(2 * phi))
    # degenerate: vector along the propagation axis -> 0 / (1, 0), zero gradient, no NaN
    v = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64, requires_grad=True)
    c, s = double_angle_cos_sin(v, torch.tensor(x_axis), torch.tensor(y_axis))
    phi = plane_azimuth(v, torch.tensor(x_axis), torch.tensor(y_axis))
    (c + s + phi).backward()
    assert float(c.detach()) == 1.0 and float(s.detach()) == 0.0 and float(phi.detach()) == 0.0
    assert torch.isfinite(v.grad).all()


def test_incidence_frame_angle_builds_fresnel_frame():
    """C(phi~_i) then F^R then C(-phi~_o) reproduces the explicit s-axis frame conversion."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        w_i, w_o = rng.normal(size=3), rng.normal(size=3)
        w_i, w_o = w_i / np.linalg.norm(w_i), w_o / np.linalg.norm(w_o)
        h = (w_i + w_o) / np.linalg.norm(w_i + w_o)
        up = rng.normal(size=3)
        x_in, y_in = stokes_frame(-w_i, up)
        s_axis = np.cross(w_i, w_o) / np.linalg.norm(np.cross(w_i, w_o))
        # explicit: rotate the light frame onto the s axis
        explicit = frame_rotation_angle(x_in, y_in, s_axis)
        tilde = incidence_frame_angle(h, x_in, y_in)
        np.testing.assert_allclose(rotator(tilde), rotator(explicit), atol=1e-12)


def test_gradcheck_mueller():
    theta = torch.rand(3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(rotator, (theta,))
    assert torch.autograd.gradcheck(lambda t: linear_polarizer(t), (theta,))
    cos = (torch.rand(3, dtype=torch.float64) * 0.9 + 0.05).requires_grad_(True)
    eta = (torch.rand(3, dtype=torch.float64) + 1.1).requires_grad_(True)
    assert torch.autograd.gradcheck(mueller_fresnel_reflection, (cos, eta))
    assert torch.autograd.gradcheck(mueller_fresnel_transmission, (cos, eta))
    albedo = torch.rand(2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(depolarizer, (albedo,))
    d = torch.nn.functional.normalize(torch.randn(4, 3, dtype=torch.float64), dim=-1).requires_grad_(True)
    up = torch.randn(4, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: stokes_frame(a, b), (d, up))
    x_from, y_from = stokes_frame(d.detach(), up.detach())
    x_to = torch.linalg.cross(x_from, y_from)  # any vector; angle uses projections
    x_to = (x_to + x_from).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda v: frame_rotation_angle(x_from, y_from, v), (x_to,))
    vector = torch.randn(4, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: plane_azimuth(v, x_from, y_from), (vector,))
    assert torch.autograd.gradcheck(lambda v: incidence_frame_angle(v, x_from, y_from), (vector,))
    assert torch.autograd.gradcheck(lambda v: double_angle_cos_sin(v, x_from, y_from), (vector,))


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda: rotator(float("nan")), "theta"),
        (lambda: mueller_fresnel_reflection(1.5, 1.5), "cos_theta_i"),
        (lambda: mueller_fresnel_reflection(0.5, 0.9), "eta"),
        (lambda: mueller_fresnel_transmission(np.zeros(2), np.full(3, 1.5)), "cos_theta_i"),
        (lambda: linear_polarizer(0.1, 1.5), "transmittance"),
        (lambda: stokes_frame(np.array([0.0, 0.0, 2.0]), np.array([0.0, 1.0, 0.0])), "direction"),
        (lambda: stokes_frame(np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0])), "up"),
        (lambda: frame_rotation_angle(np.zeros(3), np.zeros(2), np.zeros(3)), "y_from"),
    ],
)
def test_bad_input(call, name):
    with pytest.raises(ValueError, match=name):
        call()
