"""``polarface calibrate-polarization``: FRAMES folder formats, the rig written, the output policy."""

from __future__ import annotations

import json

import numpy as np
import pytest

from polarface.capture.rig import AnalyzerCalibration, Rig
from polarface.cli import main
from polarface.io import write_png
from polarface.optics.analyzer import AnalyzerModel
from polarface.pipeline.calibrate_polarization import calibrate_polarization, read_polarization_frames
from polarization_targets import target_camera, target_frames

ANGLES = [0.0, 30.0, 60.0, 90.0, 120.0, 150.0]
TRUE = AnalyzerModel(80.0, (0.6, 45.4, 89.5, 134.7))


def _rig(tmp_path, sensor="mono-polarization"):
    camera = target_camera(sensor).model_copy(update={"id": "pol"})
    rig = Rig(cameras=[camera])
    rig.save(tmp_path / "rig.json")
    return camera


def _write(folder, camera, models, names, suffix=".png"):
    folder.mkdir(parents=True, exist_ok=True)
    for name, raw in zip(names, target_frames(camera, models, ANGLES, seed=7), strict=True):
        if suffix == ".npy":
            np.save(folder / f"{name}.npy", raw)
        else:
            write_png(folder / f"{name}{suffix}", raw, bit_depth=16)


def test_named_frames_update_the_rig_in_place(tmp_path, capsys):
    camera = _rig(tmp_path)
    _write(tmp_path / "frames", camera, [TRUE], [f"pol_{a:05.1f}" for a in ANGLES])
    argv = ["calibrate-polarization", str(tmp_path / "frames"), "--rig", str(tmp_path / "rig.json")]
    assert main([*argv, "--camera", "pol"]) == 0
    assert "mono" in capsys.readouterr().out
    analyzer = Rig.load(tmp_path / "rig.json").camera("pol").analyzer
    assert isinstance(analyzer, AnalyzerCalibration)
    assert abs(analyzer.extinction_ratio / 80.0 - 1) < 0.1
    np.testing.assert_allclose(analyzer.analyzer_angles_deg, TRUE.angles_deg, atol=0.1)
    assert analyzer.extinction_ratio_std > 0 and all(s > 0 for s in analyzer.analyzer_angles_std_deg)


def test_frames_json_npy_and_out_policy(tmp_path, capsys):
    camera = _rig(tmp_path)
    names = [f"shot{i}" for i in range(len(ANGLES))]
    _write(tmp_path / "frames", camera, [TRUE], names, suffix=".npy")
    entries = [{"file": f"{n}.npy", "polarizer_deg": a} for n, a in zip(names, ANGLES, strict=True)]
    listing = {"frames": entries}
    (tmp_path / "frames" / "frames.json").write_text(json.dumps(listing))
    out = tmp_path / "calibrated.json"
    argv = ["calibrate-polarization", str(tmp_path / "frames"), "--rig", str(tmp_path / "rig.json")]
    argv += ["--camera"]
    assert main([*argv, "pol", "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["colours"]["mono"]["analyzer_gains"] is not None
    assert Rig.load(tmp_path / "rig.json").camera("pol").analyzer is None  # --rig untouched
    assert Rig.load(out).camera("pol").analyzer is not None
    before = out.read_bytes()
    assert main([*argv, "pol", "--out", str(out)]) == 2  # an existing other file needs --force
    assert out.read_bytes() == before
    assert main([*argv, "pol", "--out", str(out), "--force"]) == 0


def test_angles_argument_and_colour_subset_keep_other_colours(tmp_path):
    camera = _rig(tmp_path, "color-polarization")
    models = [TRUE, AnalyzerModel(150.0, (0.2, 45.1, 90.3, 135.2)), TRUE]
    _write(tmp_path / "frames", camera, models, [f"f{i:02d}" for i in range(len(ANGLES))], suffix=".tiff")
    old = AnalyzerCalibration(extinction_ratio=30.0)
    rig = Rig.load(tmp_path / "rig.json")
    rig.cameras[0] = rig.cameras[0].model_copy(update={"analyzer": old})
    rig.save(tmp_path / "rig.json")
    from polarface.capture.polarization_calibration import PolarizationCalibrationOptions

    result = calibrate_polarization(
        tmp_path / "frames", tmp_path / "rig.json", "pol", angles_deg=ANGLES,
        options=PolarizationCalibrationOptions(colours=("G",)),
    )
    assert list(result.fits) == ["G"]
    analyzer = Rig.load(tmp_path / "rig.json").camera("pol").analyzer
    assert analyzer["R"] == old and analyzer["B"] == old
    assert abs(analyzer["G"].extinction_ratio / 150.0 - 1) < 0.1


@pytest.mark.parametrize(
    ("setup", "angles", "match"),
    [
        ("empty", None, "no raw frames"),
        ("unnamed", None, "carries no polarizer angle"),
        ("named", [0.0, 45.0], "gives 2 angles"),
        ("listing-missing-file", None, "does not exist"),
        ("listing-bad", None, "polarizer_deg"),
        ("listing", [0.0, 45.0, 90.0], "conflicts"),
    ],
)
def test_bad_frames_folders(tmp_path, setup, angles, match):
    folder = tmp_path / "frames"
    folder.mkdir()
    if setup == "unnamed":
        (folder / "a.png").write_bytes(b"")
    if setup == "named":
        for a in (0, 45, 90):
            (folder / f"pol_{a}.png").write_bytes(b"")
    if setup.startswith("listing"):
        entry = {"file": "gone.png", "polarizer_deg": "north" if setup == "listing-bad" else 0.0}
        (folder / "frames.json").write_text(json.dumps({"frames": [entry]}))
    with pytest.raises((ValueError, FileNotFoundError), match=match):
        read_polarization_frames(folder, angles)
    with pytest.raises(FileNotFoundError, match="nope"):
        read_polarization_frames(tmp_path / "nope")
