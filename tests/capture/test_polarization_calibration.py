"""Estimator of the analyzers' extinction ratio and orientations against simulator ground truth
(tests/polarization_targets.py: AnalyzerModel forward model + mosaic + sensor noise), and on the real
IMX250MZR frames of tests/data/polarization (docs/calibrate_polarization.md, "What the real frames show")."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from polarface.capture.polarization_calibration import (
    PolarizationCalibrationOptions,
    calibrate_analyzers,
    central_roi,
)
from polarface.capture.sensor import SensorNoise
from polarface.io.images import read_png
from polarface.optics.analyzer import AnalyzerModel
from polarization_targets import target_camera, target_frames

ANGLES = np.arange(0.0, 180.0, 15.0)
TRUE = AnalyzerModel(100.0, (0.8, 45.5, 89.3, 134.2))
GAINS = [np.array([1.0, 0.97, 1.03, 1.01])]
POLARIZER_PNG = Path(__file__).parents[1] / "data" / "polarization" / "polarizer_IMX250MZR_crop.png"


def _check(fit, model: AnalyzerModel, ratio_rtol: float = 0.10, angle_tol: float = 0.1) -> None:
    assert abs(fit.extinction_ratio / model.extinction_ratio - 1) < ratio_rtol
    np.testing.assert_allclose(fit.angles_deg, model.angles_deg, atol=angle_tol)


def test_mono_recovers_ratio_angles_and_gains_with_black_level():
    noise = SensorNoise(black_level=64.0)
    camera = target_camera(black_level=64.0)
    frames = target_frames(camera, [TRUE], ANGLES, gains=GAINS, noise=noise, seed=1)
    fit = calibrate_analyzers(frames, ANGLES, camera).fits[None]
    _check(fit, TRUE)
    np.testing.assert_allclose(fit.gains, GAINS[0] / GAINS[0].mean(), atol=2e-3)
    # one-sigma uncertainties are finite, small and consistent with the actual errors
    assert np.all(fit.angles_std_deg > 0) and np.all(fit.angles_std_deg < 0.05)
    assert np.all(np.abs(fit.angles_deg - np.asarray(TRUE.angles_deg)) < 5 * fit.angles_std_deg + 1e-3)
    assert abs(fit.extinction_ratio - 100.0) < 5 * fit.extinction_ratio_std
    lower, upper = fit.extinction_ratio_bounds
    assert lower < fit.extinction_ratio < upper


def test_noiseless_frames_give_the_reference_values():
    """Quantisation only, 16-bit: the linear model is exact, so the fit reproduces the truth."""
    model = AnalyzerModel(300.0, (-1.0, 44.0, 91.0, 136.5))
    noise = SensorNoise(bit_depth=16, full_well_e=1e6)
    camera = target_camera(bit_depth=16)
    angles = [0.0, 60.0, 120.0]  # three angles: exactly determined, no residual
    frames = target_frames(camera, [model], angles, noise=noise, noiseless=True)
    fit = calibrate_analyzers(frames, angles, camera).fits[None]
    assert abs(fit.extinction_ratio / 300.0 - 1) < 0.02
    np.testing.assert_allclose(fit.angles_deg, model.angles_deg, atol=5e-3)
    assert fit.residual_rms < 1e-12


def test_colour_sensor_per_colour_with_pattern_phase():
    models = [
        AnalyzerModel(40.0, (0.3, 45.2, 90.4, 134.9)), TRUE, AnalyzerModel(25.0, (-0.4, 44.6, 89.8, 135.3))
    ]
    camera = target_camera("color-polarization", pattern_phase=(1, 2))
    result = calibrate_analyzers(target_frames(camera, models, ANGLES, seed=2), ANGLES, camera)
    assert list(result.fits) == ["R", "G", "B"]
    for colour, model in zip("RGB", models, strict=True):
        _check(result.fits[colour], model)
    field = result.analyzer_field()
    assert set(field) == {"R", "G", "B"} and field["G"].analyzer_angles_std_deg is not None
    green = PolarizationCalibrationOptions(colours=("G",))
    only_green = calibrate_analyzers(target_frames(camera, models, ANGLES, seed=2), ANGLES, camera, green)
    assert list(only_green.fits) == ["G"]


def test_wrong_pattern_phase_is_caught():
    """A vertically flipped readout swaps 0<->45 and 90<->135 deg: the fit lands 45 deg off and says so."""
    frames = target_frames(target_camera(pattern_phase=(1, 0)), [TRUE], ANGLES)
    with pytest.raises(ValueError, match="pattern_phase"):
        calibrate_analyzers(frames, ANGLES, target_camera())


def test_saturated_super_pixels_are_excluded():
    camera = target_camera()
    shading = np.ones((128, 128))
    shading[:64, :64] = 3.0  # a bright patch that clips at the white level in some frames
    frames = target_frames(camera, [TRUE], ANGLES, shading=shading, seed=3)
    result = calibrate_analyzers(frames, ANGLES, camera, PolarizationCalibrationOptions(roi=(0, 0, 128, 128)))
    _check(result.fits[None], TRUE)
    assert result.fits[None].pixels < 64 * 64  # the clipped quarter was left out
    with pytest.raises(ValueError, match=r"frame 0.*saturates"):
        calibrate_analyzers(frames, ANGLES, camera, PolarizationCalibrationOptions(roi=(0, 0, 60, 60)))


def test_angle_reference_removes_an_unknown_polarizer_zero():
    """The polarizer's zero sits 3 deg from image +x: absolute angles shift by 3 deg, relative ones do not."""
    camera = target_camera()
    frames = target_frames(camera, [TRUE], ANGLES + 3.0, seed=4)
    shifted = calibrate_analyzers(frames, ANGLES, camera).fits[None]
    np.testing.assert_allclose(shifted.angles_deg, np.asarray(TRUE.angles_deg) - 3.0, atol=0.1)
    relative = calibrate_analyzers(
        frames, ANGLES, camera, PolarizationCalibrationOptions(angle_reference="analyzers")
    ).fits[None]
    truth = np.asarray(TRUE.angles_deg)
    np.testing.assert_allclose(relative.angles_deg, truth - (truth - [0, 45, 90, 135]).mean(), atol=0.1)
    assert relative.angle_offset_deg == pytest.approx(-3.0 + (truth - [0, 45, 90, 135]).mean(), abs=0.1)


def test_normalise_frames_handles_a_drifting_source():
    camera = target_camera()
    scales = 1.0 + 0.1 * np.sin(np.arange(ANGLES.size))
    model = AnalyzerModel(100.0, (0.0, 45.0, 90.0, 135.0))
    frames = target_frames(camera, [model], ANGLES, frame_scales=list(scales), seed=5)
    drifting = calibrate_analyzers(frames, ANGLES, camera).fits[None]
    assert drifting.residual_rms > 0.01  # the model does not fit: seen in the residual
    fit = calibrate_analyzers(frames, ANGLES, camera, PolarizationCalibrationOptions(normalise_frames=True))
    _check(fit.fits[None], model)


def test_central_roi():
    assert central_roi(2448, 2048, 4) == (612, 512, 1224, 1024)
    assert central_roi(6, 6, 2) == (2, 2, 2, 2)


@pytest.mark.parametrize(
    ("frames_angles", "options", "camera_kw", "match"),
    [
        ([0.0, 180.0, 90.0], {}, {}, "3 distinct"),
        ([0.0, 45.0, 90.0], {"colours": ("R",)}, {}, "mono-polarization"),
        ([0.0, 45.0, 90.0], {"roi": (0, 0, 500, 10)}, {}, "roi"),
        ([0.0, 45.0, 90.0], {"roi": (3, 3, 1, 1)}, {}, "roi"),
    ],
)
def test_bad_arguments(frames_angles, options, camera_kw, match):
    camera = target_camera(**camera_kw)
    frames = target_frames(camera, [TRUE], frames_angles)
    with pytest.raises(ValueError, match=match):
        calibrate_analyzers(frames, frames_angles, camera, PolarizationCalibrationOptions(**options))


def test_bad_frames_are_named():
    camera = target_camera()
    frames = target_frames(camera, [TRUE], [0.0, 45.0, 90.0])
    dark = [frames[0], frames[1] // 100, frames[2]]
    with pytest.raises(ValueError, match=r"'b\.png' is too dark"):
        calibrate_analyzers(dark, [0.0, 45.0, 90.0], camera, names=["a.png", "b.png", "c.png"])
    with pytest.raises(ValueError, match="'c' has shape"):
        calibrate_analyzers([*frames[:2], frames[2][:64]], [0, 45, 90], camera, names=list("abc"))
    unpolarized = [frames[0]] * 3
    with pytest.raises(ValueError, match="no polarization modulation"):
        calibrate_analyzers([f // 2 + 300 for f in unpolarized], [0, 45, 90], camera)
    with pytest.raises(ValueError, match="not a polarization sensor"):
        calibrate_analyzers(frames, [0, 45, 90], camera.model_copy(update={"sensor": "rgb"}))
    with pytest.raises(ValueError, match="tiles"):
        PolarizationCalibrationOptions(tiles=0)


# ---------------------------------------------------------------------------------------------------------
# Real IMX250MZR frames: three labelled filters (45, "90" reading 0, 135 deg) in front of a window


def _filter_regions(size: int = 240) -> list[np.ndarray]:
    """Three ``size`` x ``size`` crops (even offsets: mosaic phase kept) centred on the filters."""
    raw = read_png(POLARIZER_PNG)
    centres = ((1088, 232), (1088, 784), (1100, 1340))  # 45, "90", 135 deg (data/polarization/README.md)
    crops = []
    for row, col in centres:
        r0, c0 = (row - size // 2) // 2 * 2, (col - size // 2) // 2 * 2
        crops.append(raw[r0 : r0 + size, c0 : c0 + size])
    return crops


def _pair_mismatch(crop: np.ndarray) -> float:
    """(I0 + I90 - I45 - I135) / mean: zero for any linear response of orthogonal, equal-gain analyzers."""
    i90, i45, i135, i0 = (crop[r::2, c::2].astype(float).mean() for r, c in ((0, 0), (0, 1), (1, 0), (1, 1)))
    return (i0 + i90 - i45 - i135) / ((i0 + i90 + i45 + i135) / 4)


def test_real_frames_bound_the_extinction_ratio_from_below():
    crops = _filter_regions()
    camera = target_camera(size=240, bit_depth=8)
    options = PolarizationCalibrationOptions(roi=(0, 0, 240, 240), normalise_frames=True, tiles=4)
    fit = calibrate_analyzers(crops, [45.0, 0.0, 135.0], camera, options).fits[None]
    # physically plausible: every analyzer polarizes (0 < d < 1), orientations near nominal
    assert np.all((fit.diattenuation > 0.2) & (fit.diattenuation < 1.0))
    assert np.all(np.abs(fit.angles_deg - [0, 45, 90, 135]) < 12.0)
    # the light behind the filters is partly polarized, so d is a lower bound: ER >= ~2.3 only
    lower, _ = fit.extinction_ratio_bounds
    assert 2.0 < lower < fit.extinction_ratio < 3.0
    # consistent: the two halves of every filter give the same estimate within their uncertainties
    halves = []
    for part in (slice(0, 120), slice(120, 240)):
        half = calibrate_analyzers(
            [c[part] for c in crops], [45.0, 0.0, 135.0], target_camera(size=240, bit_depth=8).model_copy(
                update={"height": 120}
            ),
            PolarizationCalibrationOptions(roi=(0, 0, 240, 120), normalise_frames=True, tiles=4),
        )
        halves.append(half.fits[None])
    sigma = np.hypot(halves[0].diattenuation_std, halves[1].diattenuation_std)
    assert np.all(np.abs(halves[0].diattenuation - halves[1].diattenuation) < 5 * sigma + 0.03)


def test_real_frames_are_not_a_linear_response():
    """I0 + I90 = I45 + I135 for any linear sensor; the 8-bit frames miss it by ~5 % with the sign of a
    concave tone curve (the extreme pair sums low), which is why they cannot calibrate the ratio."""
    mismatch = [_pair_mismatch(c) for c in _filter_regions()]
    # 45 and 135 deg filters: the 45/135 pair is the extreme pair; "90" (AoLP ~0): the 0/90 pair is
    assert mismatch[0] > 0.03 and mismatch[2] > 0.03 and mismatch[1] < -0.03
