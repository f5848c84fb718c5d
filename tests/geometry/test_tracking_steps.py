"""The flows of one tracking propagation on an image crop (polarface.geometry.tracking_steps).

The synthetic images carry a random multi-scale texture; the second image is the first translated by a
known sub-pixel shift.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from polarface.geometry.tracking import TrackingConfig
from polarface.geometry.tracking.config import DIS_PRESETS
from polarface.geometry.tracking.flow import MIN_CROP_PX, flow_crop, sampled_flow

WIDTH, HEIGHT = 320, 240
SHIFT = np.array([3.4, -2.3])  # px, image b = image a moved by SHIFT


def _texture(shift: np.ndarray, seed: int = 0) -> np.ndarray:
    """``(HEIGHT, WIDTH)`` uint8 random multi-scale texture (white noise blurred at 1.5, 4 and 12 px)
    whose content is moved by ``shift`` (x, y) pixels (exactly, by a Fourier phase ramp: the texture is
    periodic over the image)."""
    rng = np.random.default_rng(seed)
    noise = np.fft.fft2(rng.standard_normal((HEIGHT, WIDTH)))
    fy = np.fft.fftfreq(HEIGHT)[:, None]
    fx = np.fft.fftfreq(WIDTH)[None, :]
    radius2 = fx**2 + fy**2
    spectrum = sum(np.exp(-2 * (np.pi * sigma) ** 2 * radius2) for sigma in (1.5, 4.0, 12.0))
    moved = noise * spectrum * np.exp(-2j * np.pi * (fx * shift[0] + fy * shift[1]))
    value = np.fft.ifft2(moved).real
    reference = np.fft.ifft2(noise * spectrum).real
    return np.clip(128.0 + 40.0 * value / reference.std(), 0, 255).astype(np.uint8)


def _flow() -> cv2.DISOpticalFlow:
    config = TrackingConfig()
    flow = cv2.DISOpticalFlow_create(DIS_PRESETS[config.flow_preset])
    flow.setFinestScale(config.flow_finest_scale)
    flow.setVariationalRefinementIterations(config.variational_iterations)
    return flow


def _grid(x0: float, y0: float, x1: float, y1: float, step: float = 3.7) -> np.ndarray:
    gx, gy = np.meshgrid(np.arange(x0, x1, step), np.arange(y0, y1, step))
    return np.stack([gx.ravel(), gy.ravel()], -1)


def test_crop_is_the_box_of_the_pixels_expanded_by_the_margin_and_clipped():
    pixels = np.array([[100.2, 80.7], [180.9, 150.1], [140.0, 120.0]])
    assert flow_crop(pixels, 20.0, WIDTH, HEIGHT) == (80, 60, 202, 172)
    # clipped to the image
    assert flow_crop(np.array([[10.0, 5.0], [120.0, 100.0]]), 30.0, WIDTH, HEIGHT) == (0, 0, 151, 131)
    # clipped, then grown to 4 x margin per side inside the image
    corner = np.array([[250.0, 200.0], [310.0, 235.0]])
    assert flow_crop(corner, 30.0, WIDTH, HEIGHT) == (200, 120, WIDTH, HEIGHT)
    # a small box grows about its centre to 4 x margin per side (DIS's pyramid reaches the margin)
    x0, y0, x1, y1 = flow_crop(np.array([[150.0, 100.0]]), 10.0, WIDTH, HEIGHT)
    assert (x1 - x0, y1 - y0) == (40, 40) and x0 <= 150 < x1 and y0 <= 100 < y1
    # ... and to at least MIN_CROP_PX, kept inside the image at its border
    assert flow_crop(np.array([[1.0, 238.5]]), 0.0, WIDTH, HEIGHT) == (0, HEIGHT - MIN_CROP_PX, MIN_CROP_PX,
                                                                    HEIGHT)
    # None or no pixels: the whole image
    assert flow_crop(pixels, None, WIDTH, HEIGHT) == (0, 0, WIDTH, HEIGHT)
    assert flow_crop(np.zeros((0, 2)), 20.0, WIDTH, HEIGHT) == (0, 0, WIDTH, HEIGHT)
    # a crop larger than the image is the image
    assert flow_crop(pixels, 1000.0, WIDTH, HEIGHT) == (0, 0, WIDTH, HEIGHT)


def test_flow_sampled_in_a_crop_equals_the_whole_image_flow_on_a_translation():
    image_a, image_b = _texture(np.zeros(2)), _texture(SHIFT)
    start = _grid(120.0, 90.0, 200.0, 150.0)
    flow = _flow()
    full = sampled_flow(flow, image_a, image_b, start, None)
    crop = sampled_flow(flow, image_a, image_b, start, 16.0)
    assert flow_crop(start, 16.0, WIDTH, HEIGHT) == (104, 74, 215, 167)  # 13 % of the image
    for moved, error, inside in (full, crop):
        assert inside.all()
        # the true motion to 0.05 px, forward and backward consistent
        assert np.abs(moved - (start + SHIFT)).max() < 0.05
        assert np.median(error) < 0.05
    assert np.abs(crop[0] - full[0]).max() < 0.02  # measured 0.009 px


def test_crop_covering_the_image_is_the_whole_image_flow_bit_for_bit():
    image_a, image_b = _texture(np.zeros(2), seed=1), _texture(SHIFT, seed=1)
    start = _grid(20.0, 20.0, 300.0, 220.0, step=9.1)
    full = sampled_flow(_flow(), image_a, image_b, start, None)
    covering = sampled_flow(_flow(), image_a, image_b, start, 500.0)
    for a, b in zip(full, covering, strict=True):
        np.testing.assert_array_equal(a, b)


def test_positions_flowed_out_of_the_crop_are_flagged():
    """A margin smaller than the motion: the points near the crop's left and bottom edges move out of
    the crop (as points moving out of the image do); ``inside`` is exactly "moved lies in the crop"."""
    image_a, image_b = _texture(np.zeros(2), seed=2), _texture(np.array([-6.0, 5.0]), seed=2)
    start = _grid(100.0, 80.0, 220.0, 160.0)
    moved, _, inside = sampled_flow(_flow(), image_a, image_b, start, 0.0)
    x0, y0, x1, y1 = flow_crop(start, 0.0, WIDTH, HEIGHT)
    within = (moved[:, 0] >= x0) & (moved[:, 0] <= x1 - 1) & (moved[:, 1] >= y0) & (moved[:, 1] <= y1 - 1)
    np.testing.assert_array_equal(inside, within)
    assert 0 < (~inside).sum() < len(start) // 4
    # deep inside the crop the flow is still the translation
    interior = (start[:, 0] > x0 + 20) & (start[:, 1] < y1 - 20)
    assert np.median(np.abs(moved[interior] - (start[interior] + [-6.0, 5.0]))) < 0.1


@pytest.mark.parametrize("margin", [-1.0, float("nan"), float("inf"), True, "50"])
def test_bad_crop_margin_is_refused(margin):
    with pytest.raises(ValueError, match="flow_crop_margin_px"):
        TrackingConfig(flow_crop_margin_px=margin)


def test_median_over_cameras_is_numpys_nanmedian():
    """The merge's per-vertex median of the cameras' hits: numpy's ``nanmedian`` bit for bit, odd and even
    camera counts, all-NaN vertices NaN."""
    import warnings

    from polarface.geometry.tracking.propagation import _median_over_cameras

    rng = np.random.default_rng(3)
    for cameras, missing in ((10, 0.5), (7, 0.2), (2, 0.6), (1, 0.3)):
        values = rng.normal(0.0, 100.0, (cameras, 500, 3))
        values[rng.random((cameras, 500)) < missing] = np.nan
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            want = np.nanmedian(values, axis=0)
        got = _median_over_cameras(values)
        np.testing.assert_array_equal(got, want)
        assert np.isnan(got[np.isnan(values).all(axis=(0, 2))]).all()
    two = np.array([[[1.0, 2.0, 3.0]], [[2.0, 4.0, 5.0]]])
    assert _median_over_cameras(two).tolist() == [[1.5, 3.0, 4.0]]


def test_window_ncc_of_equal_inverted_unrelated_and_flat_windows():
    from polarface.geometry.tracking.images import window_ncc

    image = _texture(np.zeros(2))
    other = _texture(np.zeros(2), seed=5)
    pixels = _grid(40, 40, 280, 200, step=11.0)
    np.testing.assert_allclose(window_ncc(image, pixels, image, pixels, 3), 1.0, atol=1e-6)
    np.testing.assert_allclose(window_ncc(image, pixels, 255 - image, pixels, 3), -1.0, atol=1e-6)
    assert abs(float(np.median(window_ncc(image, pixels, other, pixels, 3)))) < 0.2
    flat = np.full_like(image, 77)
    assert np.all(window_ncc(image, pixels, flat, pixels, 3) == 0.0)
    shifted = _texture(SHIFT)  # the content moved by SHIFT: its windows match at the moved pixels
    assert np.median(window_ncc(image, pixels, shifted, pixels + SHIFT, 3)) > 0.95


def _sheet(count: int = 30, step: float = 2.0):
    from polarface.geometry import TriangleMesh

    xs = np.arange(count) * step
    gx, gy = np.meshgrid(xs, xs)
    vertices = np.stack([gx, gy, 0.05 * (gx - 30.0) ** 2 / 10.0], -1).reshape(-1, 3)
    index = np.arange(count * count).reshape(count, count)
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, 1:], index[1:, :-1]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return TriangleMesh.from_arrays(vertices, faces, vertices[:, :2] / xs[-1])


def test_untracked_vertices_follow_the_rigid_motion_of_the_tracked_ones():
    """A curved sheet turned by 4 deg and moved by 5 mm; a third of it (one side: extrapolation) was not
    tracked. The screened fill puts it where the rigid motion takes it; the harmonic fill of the
    displacement (fill_screening 0) leaves the far side behind by millimetres."""
    from scipy.spatial.transform import Rotation

    from polarface.geometry.tracking.regularisation import MeshGraph, regularise

    mesh = _sheet()
    rotation = Rotation.from_euler("z", 4.0, degrees=True).as_matrix()
    moved = mesh.vertices @ rotation.T + np.array([5.0, -2.0, 1.0])
    tracked = mesh.vertices[:, 0] < 38.0
    estimate = np.where(tracked[:, None], moved, np.nan)
    graph = MeshGraph(mesh)
    config = TrackingConfig(smoothing_iterations=0)
    filled = regularise(estimate, tracked, mesh.vertices, graph, mesh, config)
    np.testing.assert_allclose(filled, moved, atol=1e-6)
    harmonic = regularise(estimate, tracked, mesh.vertices, graph, mesh,
                          TrackingConfig(smoothing_iterations=0, fill_screening=0.0))
    assert np.abs(harmonic - moved)[~tracked].max() > 1.0


def test_the_rigid_motion_ignores_an_expression_and_the_residual_fades():
    """Tracked: the sheet still but one corner lifted 6 mm (an expression). The rigid part stays the
    identity (trimmed fit), and the lift carried into the untracked rest fades within ~10 edges."""
    from polarface.geometry.tracking.regularisation import MeshGraph, regularise

    mesh = _sheet()
    lifted = mesh.vertices.copy()
    corner = (mesh.vertices[:, 0] < 10.0) & (mesh.vertices[:, 1] < 10.0)
    lifted[corner, 2] += 6.0
    tracked = mesh.vertices[:, 1] < 20.0
    estimate = np.where(tracked[:, None], lifted, np.nan)
    config = TrackingConfig(smoothing_iterations=0)
    filled = regularise(estimate, tracked, mesh.vertices, MeshGraph(mesh), mesh, config)
    far = mesh.vertices[:, 1] > 44.0  # 12 edges beyond the tracked rows
    assert np.abs(filled - mesh.vertices)[far].max() < 0.1
    np.testing.assert_allclose(filled[tracked], lifted[tracked], atol=1e-9)


def test_tracking_support_keeps_a_lone_miss_and_empties_a_wide_untracked_region():
    from polarface.geometry.tracking import tracking_support

    mesh = _sheet()
    confidence = np.ones(len(mesh.vertices))
    lone = 15 * 30 + 15
    centre = np.linalg.norm(mesh.vertices[:, :2] - np.array([44.0, 44.0]), axis=1)
    confidence[lone] = 0.0
    confidence[centre < 12.0] = 0.0
    support = tracking_support(mesh, confidence, 4)
    assert support[lone] > 0.5
    assert np.all(support[centre < 4.0] < 0.05)
    np.testing.assert_array_equal(tracking_support(mesh, confidence, 0), confidence)
    with pytest.raises(ValueError, match="confidence"):
        tracking_support(mesh, confidence[:-1], 4)


@pytest.mark.parametrize("field, value", [("min_window_ncc", 1.0), ("min_window_ncc", True),
                                          ("ncc_radius_px", 0), ("ncc_radius_px", 2.5),
                                          ("fill_screening", -0.1)])
def test_bad_check_and_fill_settings_are_refused(field, value):
    with pytest.raises(ValueError, match=field):
        TrackingConfig(**{field: value})
