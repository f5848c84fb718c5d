"""The ``calibrate-rig`` job (``polarface.pipeline.calibrate_rig``) on a simulated session: the ``lights``
frames of a perturbed rig (``polarface.simulate.calibration_session``) at the tiny preset's stereo size give
the LED modules within 2 mm (the demo's numbers: docs/calibration.md); the command writes the rig and its
report; bad sessions are named and nothing is written."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from polarface.capture.rig import Rig, paper_rig
from polarface.cli import main
from polarface.io import read_png, write_png
from polarface.pipeline.calibrate_rig import calibrate_from_session, calibrate_lights
from polarface.simulate.calibration_session import write_light_frames
from polarface.simulate.rig_perturbation import RigPerturbation

NOMINAL = paper_rig(width=320, height=256)
TRUE = RigPerturbation(seed=5).true_rig(NOMINAL)


def _positions(rig: Rig) -> np.ndarray:
    return np.array([light.position_mm for light in rig.lights])


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    folder = tmp_path_factory.mktemp("session")
    write_light_frames(folder / "lights", TRUE, np.array([0.0, 0.0, 1000.0]), seed=1)
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


@pytest.mark.slow
def test_the_command_writes_the_rig_and_its_report(session, tmp_path, capsys):
    nominal = session.parent / f"{session.name}_nominal.json"
    out = tmp_path / "calibrated.json"
    assert main(["calibrate-rig", str(session), "--rig", str(nominal), "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out.split("\nwrote")[0])
    assert set(report["steps"]) == {"lights"} and report["skipped"] == []
    assert sorted(report["steps"]["lights"]["modules"]) == [light.id for light in NOMINAL.lights]
    calibrated = Rig.load(out)
    assert np.linalg.norm(_positions(calibrated) - _positions(TRUE), axis=1).max() < 2.0
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
    with pytest.raises(ValueError, match="sphere not found at position 03"):
        calibrate_from_session(broken, nominal, out)
    shutil.rmtree(broken / "lights")
    shutil.copytree(session / "lights", broken / "lights")
    frame = broken / "lights" / "05" / "leds" / "led2" / "stereo1_a.png"
    raw = read_png(frame)
    raw[raw > raw.max() * 0.3] = 4095  # the highlight clipped at the white level
    write_png(frame, raw, bit_depth=16)
    with pytest.raises(ValueError, match=r"stereo1_a\.png': the highlight .* is saturated"):
        calibrate_from_session(broken, nominal, out)
    (broken / "lights" / "session.json").unlink()
    with pytest.raises(FileNotFoundError, match=r"session\.json"):
        calibrate_from_session(broken, nominal, out)
    with pytest.raises(FileNotFoundError, match="is not a folder"):
        calibrate_from_session(tmp_path / "absent", nominal, out)
    assert not out.exists()
