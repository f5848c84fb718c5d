"""The ``calibrate-rig`` job (``polarface.pipeline.calibrate_rig``) on a simulated session of a perturbed
rig (``polarface.simulate.calibration_session``) at the tiny preset's stereo size: the ``lights`` frames
give the LED modules within 2 mm, the ``radiometric`` frames the camera gains within 0.5 % and the modules'
intensities within 1 %, the ``spectral`` files the channel responses' peaks within 2 nm and their shapes
within 3 % (the demo's numbers: docs/calibration.md); the command writes the rig and its
report; bad sessions are named and nothing is written."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from polarface.capture.radiometric_calibration import split_products
from polarface.capture.rig import Rig, paper_rig
from polarface.cli import main
from polarface.io import read_png, write_png
from polarface.pipeline.calibrate_rig import (
    calibrate_from_session,
    calibrate_lights,
    calibrate_radiometric,
    calibrate_spectral,
    response_peaks_nm,
)
from polarface.simulate.calibration_session import (
    write_light_frames,
    write_radiometric_frames,
    write_spectral_frames,
)
from polarface.simulate.rig_perturbation import RigPerturbation

NOMINAL = paper_rig(width=320, height=256)
PERTURBATION = RigPerturbation(seed=5)
TRUE = PERTURBATION.true_rig(NOMINAL)


def _positions(rig: Rig) -> np.ndarray:
    return np.array([light.position_mm for light in rig.lights])


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    folder = tmp_path_factory.mktemp("session")
    write_light_frames(folder / "lights", TRUE, np.array([0.0, 0.0, 1000.0]), seed=1)
    write_radiometric_frames(folder / "radiometric", TRUE, np.array([0.0, 0.0, 1000.0]), seed=1)
    write_spectral_frames(folder / "spectral", TRUE, *PERTURBATION.spectral_parts(NOMINAL), seed=1)
    NOMINAL.save(folder.parent / f"{folder.name}_nominal.json")
    return folder


@pytest.mark.slow
def test_the_lights_come_within_2_mm_of_the_true_rig(session):
    rig, report = calibrate_lights(session / "lights", NOMINAL)
    error = np.linalg.norm(_positions(rig) - _positions(TRUE), axis=1)
    nominal_error = np.linalg.norm(_positions(NOMINAL) - _positions(TRUE), axis=1)
    assert error.max() < 2.0 and np.median(error) < np.median(nominal_error) / 3
    calibration = report.calibration
    assert calibration.highlight_rms_px < 0.05 and calibration.silhouette_rms_px < 0.1
    assert (calibration.highlights == 9 * 8).all()  # every module, every position, every RGB camera
    assert np.all(np.linalg.norm(calibration.positions_std_mm, axis=1) < 3.0)
    # only the module positions change
    assert sorted({d.split(".")[-1] for d in NOMINAL.geometry_differences(rig)}) == ["position_mm"]


def _true_split(rig: Rig) -> tuple[np.ndarray, np.ndarray]:
    """The true rig's gains and intensities per channel, split as the calibration splits them."""
    gains = np.ones(6)
    for camera in rig.cameras:
        for colour, channel in camera.colour_channels.items():
            gains[channel] = camera.channel_gains["RGB".index(colour)]
    intensity = np.array([np.broadcast_to(light.radiant_intensity, (6,)) for light in rig.lights])
    return split_products(intensity * gains, np.full(6, 1.0e6))


@pytest.mark.slow
def test_the_gains_and_intensities_come_within_the_targets(session):
    start = Rig.model_validate({**NOMINAL.model_dump(mode="json"),
                                "lights": [light.model_dump(mode="json") for light in TRUE.lights]})
    rig, report = calibrate_radiometric(session / "radiometric", start)  # the lights where they are
    gains, intensities = _true_split(TRUE)
    assert np.abs(report.gains / gains - 1).max() < 0.005
    assert np.abs(report.intensities / intensities - 1).max() < 0.01
    assert np.abs(1.0 / gains - 1).max() > 0.01  # the nominal rig's gains are off
    assert report.residuals.max() < 0.05
    for camera in rig.cameras:  # into the rig: the polarization cameras' gains, the modules' six values
        channels = [camera.colour_channels[c] for c in "RGB"] if camera.colour_channels else []
        expected = [report.gains[c] for c in channels] or [1.0] * 3
        np.testing.assert_allclose(camera.channel_gains, expected)
    np.testing.assert_allclose([light.radiant_intensity for light in rig.lights], report.intensities)


def test_the_channel_responses_come_within_the_targets(session):
    rig, report = calibrate_spectral(session / "spectral", NOMINAL)
    grid = np.asarray(NOMINAL.spectral.wavelengths_nm)
    true, nominal, measured = (np.asarray(r.spectral.channel_responses) for r in (TRUE, NOMINAL, rig))
    np.testing.assert_allclose(report.peak_nm, response_peaks_nm(measured, grid))
    assert np.abs(report.peak_nm - response_peaks_nm(true, grid)).max() < 2.0

    def shape_error(responses: np.ndarray) -> np.ndarray:  # the channels are white-normalised: shapes count
        return np.sqrt(np.mean((responses / responses.max(1, keepdims=True)
                                - true / true.max(1, keepdims=True)) ** 2, axis=1))

    errors = shape_error(measured)
    assert errors.max() < 0.03 and errors.mean() < 0.75 * shape_error(nominal).mean()
    np.testing.assert_allclose(rig.spectral.led_spd, TRUE.spectral.led_spd, atol=0.01)
    assert NOMINAL.geometry_differences(rig) == ["spectral"]


@pytest.mark.slow
def test_the_command_writes_the_rig_and_its_report(session, tmp_path, capsys):
    nominal = session.parent / f"{session.name}_nominal.json"
    out = tmp_path / "calibrated.json"
    assert main(["calibrate-rig", str(session), "--rig", str(nominal), "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out.split("\nwrote")[0])
    assert set(report["steps"]) == {"lights", "radiometric", "spectral"} and report["skipped"] == []
    assert sorted(report["steps"]["lights"]["modules"]) == [light.id for light in NOMINAL.lights]
    calibrated = Rig.load(out)
    assert np.linalg.norm(_positions(calibrated) - _positions(TRUE), axis=1).max() < 2.0
    gains, _ = _true_split(TRUE)
    measured = [calibrated.camera("pol_upper").channel_gains, calibrated.camera("pol_lower").channel_gains]
    np.testing.assert_allclose(np.concatenate(measured), gains, rtol=0.01)  # after the lights step's 2 mm
    assert main(["calibrate-rig", str(session), "--rig", str(nominal), "--out", str(out)]) != 0  # exists
    assert "--force" in capsys.readouterr().err


@pytest.mark.slow
def test_bad_sessions_are_named_and_nothing_is_written(session, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(session, broken)
    nominal = session.parent / f"{session.name}_nominal.json"
    out = tmp_path / "calibrated.json"
    dark = broken / "lights" / "03" / "ambient"
    for path in dark.iterdir():  # no sphere in any camera at position 03
        write_png(path, np.zeros_like(read_png(path)), bit_depth=16)
    with pytest.raises(ValueError, match=r"sphere not found in .*03.ambient"):
        calibrate_from_session(broken, nominal, out)
    shutil.rmtree(broken / "lights")
    shutil.copytree(session / "lights", broken / "lights")
    frame = broken / "lights" / "05" / "leds" / "led2" / "stereo1_a.png"
    raw = read_png(frame)
    raw[raw > raw.max() * 0.3] = 4095  # the highlight clipped at the white level
    write_png(frame, raw, bit_depth=16)
    with pytest.raises(ValueError, match=r"stereo1_a\.png': the highlight .* is saturated"):
        calibrate_from_session(broken, nominal, out)
    shutil.rmtree(broken / "lights")
    shutil.copytree(session / "lights", broken / "lights")
    led = broken / "spectral" / "led.csv"
    lines = led.read_text().splitlines()
    led.write_text("\n".join(lines[:200]) + "\n")  # 380-578 nm: the grid's red is missing
    with pytest.raises(ValueError, match=r"led\.csv': the wavelengths 380-578 nm miss part of 410-710 nm"):
        calibrate_from_session(broken, nominal, out)
    (broken / "lights" / "session.json").unlink()
    with pytest.raises(FileNotFoundError, match=r"session\.json"):
        calibrate_from_session(broken, nominal, out)
    with pytest.raises(FileNotFoundError, match="is not a folder"):
        calibrate_from_session(tmp_path / "absent", nominal, out)
    assert not out.exists()
