"""polarface.capture.demosaic: synthetic Stokes ground truth, polanalyser cross-check, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polarface.capture.demosaic import applied_gains, demosaic, demosaic_camera
from polarface.capture.rig import paper_rig
from polarface.capture.sensor import SensorNoise, mosaic, simulate_raw
from polarface.capture.synthetic import measure_demosaic, stokes_pattern
from polarface.optics.stokes import intensities_from_stokes

SENSORS = ("mono-polarization", "color-polarization")
METHODS = ("bilinear", "residual")


def _truth(kind, sensor, size=64):
    stokes = stokes_pattern(kind, size, size, colour=sensor == "color-polarization")
    return stokes, np.moveaxis(intensities_from_stokes(stokes), -1, 0)


@pytest.mark.parametrize("sensor", SENSORS)
@pytest.mark.parametrize("method", METHODS)
def test_smoke_shapes_dtype(sensor, method):
    _, truth = _truth("constant", sensor, 16)
    stack = demosaic(mosaic(*truth, sensor=sensor), sensor, method=method, white_level=1.0)
    assert stack.intensities.dtype == np.float32
    assert stack.intensities.shape == truth.shape
    assert stack.saturated.shape == (16, 16) and stack.defects.shape == (16, 16)
    assert stack.i0.shape == truth.shape[1:] and stack.valid.all()


@pytest.mark.parametrize("sensor", SENSORS)
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("kind", ["constant", "affine"])
def test_affine_fields_recovered_to_float32_precision(sensor, method, kind):
    _, truth = _truth(kind, sensor, 96)
    stack = demosaic(
        mosaic(*truth, sensor=sensor), sensor, method=method, white_level=1.0, defect_threshold=None
    )
    error = np.abs(stack.intensities - truth)
    # bilinear: exact one lattice period from the border; residual: beyond the guided-filter windows
    period = 2 if sensor == SENSORS[0] else 4
    margin = period if method == "bilinear" else 6 * period
    inner = error[:, margin:-margin, margin:-margin]
    assert inner.max() < 5e-7  # float32 output of values ~ 0.5
    if kind == "constant":
        assert error.max() < 1e-6  # the border too


@pytest.mark.parametrize("sensor", SENSORS)
@pytest.mark.parametrize("method", METHODS)
def test_noise_free_dop_aolp_bounded(sensor, method):
    errors = {
        kind: measure_demosaic(stokes_pattern(kind, 128, 128, colour=sensor != SENSORS[0]), sensor, method)
        for kind in ("smooth", "face")
    }
    assert errors["smooth"].dop_rms < 2e-3 and errors["smooth"].aolp_rms_deg < 0.3
    assert errors["face"].dop_rms < 0.03 and errors["face"].aolp_rms_deg < 5.0


@pytest.mark.parametrize("sensor", SENSORS)
@pytest.mark.parametrize("method", METHODS)
def test_noisy_errors_bounded_by_shot_noise(sensor, method):
    err = measure_demosaic(
        stokes_pattern("smooth", 128, 128, colour=sensor != SENSORS[0]),
        sensor,
        method,
        noise=SensorNoise(black_level=32.0),
    )
    # shot noise at ~0.2 full well: intensity sigma ~ 1 %, DoP sigma ~ 1.4 % of s0
    assert 0.004 < err.intensity_rms < 0.012
    assert err.dop_rms < 0.015 and err.aolp_rms_deg < 2.5


@pytest.mark.parametrize("sensor", SENSORS)
def test_residual_beats_bilinear_on_edges(sensor):
    stokes = stokes_pattern("face", 128, 128, colour=sensor != SENSORS[0])
    bilinear = measure_demosaic(stokes, sensor, "bilinear")
    residual = measure_demosaic(stokes, sensor, "residual")
    assert residual.intensity_rms < 0.9 * bilinear.intensity_rms
    assert residual.aolp_rms_deg < bilinear.aolp_rms_deg


@pytest.mark.parametrize("sensor", SENSORS)
def test_phase_roundtrip(sensor):
    _, truth = _truth("smooth", sensor, 32)
    for phase, method in [
        ((0, 0), "bilinear"),
        ((1, 0), "residual"),
        ((1, 3), "bilinear"),
        ((2, 1), "residual"),
    ]:
        raw = mosaic(*truth, sensor=sensor, phase=phase)
        good = demosaic(raw, sensor, method=method, phase=phase, white_level=1.0)
        wrong = demosaic(raw, sensor, method="bilinear", phase=(phase[0], phase[1] + 1), white_level=1.0)
        assert np.abs(good.intensities - truth)[:, 4:-4, 4:-4].max() < 0.02
        assert np.abs(wrong.intensities - truth)[:, 4:-4, 4:-4].max() > 0.02


@settings(max_examples=15, deadline=None)
@given(
    sensor=st.sampled_from(SENSORS),
    method=st.sampled_from(METHODS),
    phase=st.tuples(st.integers(0, 3), st.integers(0, 3)),
    s0=st.floats(0.05, 0.9),
    dop=st.floats(0.0, 1.0),
    angle=st.floats(0.0, 3.14),
)
def test_any_constant_stokes_recovered_exactly(sensor, method, phase, s0, dop, angle):
    stokes = np.array([s0, s0 * dop * np.cos(2 * angle), s0 * dop * np.sin(2 * angle)])
    colour = sensor == "color-polarization"
    field = np.broadcast_to(stokes, (24, 24, 3, 3) if colour else (24, 24, 3))
    truth = np.moveaxis(intensities_from_stokes(field), -1, 0)
    raw = mosaic(*truth, sensor=sensor, phase=phase)
    stack = demosaic(raw, sensor, method=method, phase=phase, white_level=1.0, defect_threshold=None)
    np.testing.assert_allclose(stack.intensities, truth, atol=2e-6)


def test_black_level_and_exposure_normalisation():
    _, truth = _truth("affine", "mono-polarization", 32)
    noise = SensorNoise(bit_depth=16, black_level=100.0, exposure=0.5, full_well_e=1e9, read_noise_e=0.0)
    raw = simulate_raw(mosaic(*truth, sensor="mono-polarization"), noise, noiseless=True)
    stack = demosaic(raw, method="bilinear", black_level=100.0, bit_depth=16, exposure=0.5)
    assert np.abs(stack.intensities - truth)[:, 4:-4, 4:-4].max() < 1e-4


@pytest.mark.parametrize("sensor", SENSORS)
def test_saturation_mask(sensor):
    _, truth = _truth("constant", sensor, 32)
    raw = simulate_raw(mosaic(*truth, sensor=sensor), noiseless=True)
    raw[10, 10] = 4095
    stack = demosaic(raw, sensor, bit_depth=12)
    period = 2 if sensor == SENSORS[0] else 4
    assert stack.saturated[10, 10] and stack.saturated[10, 10 + period - 1]
    assert not stack.saturated[10, 10 + period] and not stack.saturated[0, 0]
    # the residual method falls back to bilinear near saturation: no ringing far from it
    assert np.abs(stack.intensities - truth)[:, ~stack.saturated].max() < 2e-3
    assert not stack.defects.any()  # a saturated pixel is not a defect


def test_all_saturated_frame_is_fully_masked():
    raw = np.full((16, 16), 4095, dtype=np.uint16)
    stack = demosaic(raw, "color-polarization", bit_depth=12)
    assert stack.saturated.all() and np.isfinite(stack.intensities).all()


@pytest.mark.parametrize("method", METHODS)
def test_hot_and_dead_pixels_repaired(method):
    _, truth = _truth("smooth", "mono-polarization", 64)
    raw = simulate_raw(mosaic(*truth, sensor="mono-polarization"), noiseless=True)
    clean = demosaic(raw, method=method, bit_depth=12)
    raw[20, 21] = 4000  # hot
    raw[40, 30] = 0  # dead
    stack = demosaic(raw, method=method, bit_depth=12)
    assert stack.defects[20, 21] and stack.defects[40, 30] and stack.defects.sum() == 2
    assert np.abs(stack.intensities - clean.intensities).max() < 0.02
    off = demosaic(raw, method=method, bit_depth=12, defect_threshold=None)
    assert np.abs(off.intensities - clean.intensities).max() > 0.2
    given = demosaic(raw, method=method, bit_depth=12, defect_threshold=None, defect_mask=stack.defects)
    np.testing.assert_allclose(given.intensities, stack.intensities, atol=1e-6)


@pytest.mark.parametrize("sensor", SENSORS)
def test_no_false_defects_on_noisy_edges(sensor):
    stokes = stokes_pattern("disk", 128, 128, colour=sensor != SENSORS[0])
    raw = simulate_raw(
        mosaic(*np.moveaxis(intensities_from_stokes(stokes), -1, 0), sensor=sensor), SensorNoise()
    )
    assert demosaic(raw, sensor, bit_depth=12).defects.sum() == 0


@pytest.mark.parametrize(
    ("raw", "kwargs", "message"),
    [
        (np.zeros((7, 8), np.uint16), {}, "multiples of 2"),
        (np.zeros((8, 10), np.uint16), {"sensor": "color-polarization"}, "multiples of 4"),
        (np.zeros((8, 8, 3), np.uint16), {}, r"\(H, W\)"),
        (np.full((8, 8), np.nan, np.float32), {"white_level": 1.0}, "NaN"),
        (np.zeros((8, 8), np.uint8), {"bit_depth": 12}, "8-bit"),
        (np.full((8, 8), 5000, np.uint16), {"bit_depth": 12}, "white_level"),
        (np.zeros((8, 8), np.uint16), {"method": "vng"}, "method"),
        (np.zeros((8, 8), np.uint16), {"exposure": 0.0}, "exposure"),
        (np.zeros((8, 8), np.uint16), {"black_level": 70000.0}, "black_level"),
        (np.zeros((8, 8), np.uint16), {"sensor": "rgb"}, "sensor"),
    ],
)
def test_bad_input(raw, kwargs, message):
    with pytest.raises(ValueError, match=message):
        demosaic(raw, **{"sensor": "mono-polarization", **kwargs})


def test_demosaic_camera_uses_rig_settings():
    rig = paper_rig(width=32, height=16)
    camera = rig.camera("pol_upper")
    _, truth = _truth("constant", "color-polarization", 32)
    raw = simulate_raw(mosaic(*truth[:, :16], sensor="color-polarization"), noiseless=True)
    stack = demosaic_camera(raw, camera)
    assert np.abs(stack.intensities - truth[:, :16]).max() < 1e-3
    with pytest.raises(ValueError, match="shape"):
        demosaic_camera(raw[:8], camera)
    with pytest.raises(ValueError, match="not a polarization sensor"):
        demosaic_camera(raw, rig.camera("stereo0_a"))
    # the camera's channel gains are divided out, colour by colour, and recorded as applied
    gains = (0.9, 1.05, 1.2)
    gained = camera.model_copy(update={"channel_gains": gains})
    signal = mosaic(*(truth[:, :16] * np.float32(gains)), sensor="color-polarization")
    scaled = demosaic_camera(simulate_raw(signal, noiseless=True), gained)
    assert np.abs(scaled.intensities - truth[:, :16]).max() < 2e-3
    assert applied_gains(rig) is None
    assert applied_gains(rig.model_copy(update={"cameras": [gained, *rig.cameras[1:]]})) == {
        "pol_upper": list(gains)}


# ---------------------------------------------------------------------------- polanalyser oracle
def _polanalyser():
    import polanalyser  # oracle: a missing package must fail, not skip

    return polanalyser


def test_bilinear_matches_polanalyser_mono():
    pa = _polanalyser()
    rng = np.random.default_rng(1)
    raw = rng.integers(0, 4096, size=(64, 80)).astype(np.uint16)
    theirs = pa.demosaicing(raw, pa.COLOR_PolarMono)  # I0, I45, I90, I135, rounded to integers
    ours = demosaic(raw, method="bilinear", bit_depth=16, defect_threshold=None).intensities * 65535.0
    for k in range(4):
        difference = np.abs(ours[k][2:-2, 2:-2] - theirs[k][2:-2, 2:-2].astype(np.float64))
        assert difference.max() <= 0.5 + 1e-3, k


def test_bilinear_matches_polanalyser_colour_on_smooth_field():
    pa = _polanalyser()
    _, truth = _truth("smooth", "color-polarization", 96)
    raw = simulate_raw(mosaic(*truth, sensor="color-polarization"), SensorNoise(bit_depth=16), noiseless=True)
    theirs = pa.demosaicing(raw, pa.COLOR_PolarRGB)  # BGR channel order
    ours = demosaic(raw, "color-polarization", method="bilinear", bit_depth=16).intensities * 65535.0
    for k in range(4):
        difference = np.abs(ours[k][8:-8, 8:-8] - theirs[k][8:-8, 8:-8, ::-1].astype(np.float64))
        assert np.median(difference) / np.median(ours[k]) < 2e-3, k
        assert difference.max() / ours[k].max() < 0.02, k


# ------------------------------------------------------------------------------------ real data
def _real(test_data, name):
    from polarface.io import read_png

    return read_png(test_data / "polarization" / f"{name}_IMX250MZR_crop.png")


@pytest.mark.parametrize("name", ["polarizer", "fruits"])
@pytest.mark.parametrize("method", METHODS)
def test_real_frames_consistency(test_data, name, method):
    raw = _real(test_data, name)
    stack = demosaic(raw, method=method, bit_depth=8)
    i0, i45, i90, i135 = stack.intensities.astype(np.float64)
    s0 = 0.5 * (i0 + i45 + i90 + i135)
    usable = stack.valid & (s0 > 0.02)
    relative = np.abs((i0 + i90) - (i45 + i135)) / s0
    assert np.median(relative[usable]) <= 0.03


def test_real_polarizer_filters_aolp_and_sky(test_data):
    from polarface.optics.stokes import aolp, stokes_from_intensities

    raw = _real(test_data, "polarizer")
    stack = demosaic(raw, bit_depth=8)
    stokes = stokes_from_intensities(*stack.intensities.astype(np.float64))
    rows, cols = np.mgrid[0 : raw.shape[0], 0 : raw.shape[1]]
    centres = {45.0: (1088, 232), 135.0: (1100, 1340), 90.0: (1088, 784)}
    measured = {}
    for label, (r, c) in centres.items():
        disk = ((rows - r) ** 2 + (cols - c) ** 2 < 120**2) & stack.valid
        measured[label] = np.degrees(aolp(stokes[disk].mean(axis=0)))
    for label in (45.0, 135.0):
        assert abs(measured[label] - label) < 3.0, measured
    # the "90" filter reads ~175 deg: its label is rotated by 90 deg (PROVENANCE.md)
    assert min(abs(measured[90.0] - 180.0), measured[90.0]) < 10.0
    assert stack.saturated[raw == 255].all()  # every saturated raw sample is masked
    assert stack.saturated[:200, 600:].mean() > 0.95  # the sky is masked as a region
    assert stack.saturated.mean() < 0.4 and not stack.saturated[1000:1200, 150:300].any()
