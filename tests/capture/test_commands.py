"""The capture commands: polarface stokes / ingest / calibrate through polarface.cli.main."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from polarface.capture.rig import Rig, paper_rig
from polarface.capture.sensor import mosaic, simulate_raw
from polarface.capture.store import CaptureStore
from polarface.capture.synthetic import stokes_pattern
from polarface.cli import main
from polarface.io import read_exr, read_png, write_png
from polarface.optics.stokes import intensities_from_stokes


def test_stokes_on_real_frame(test_data, tmp_path, capsys):
    out = tmp_path / "out"
    raw = test_data / "polarization" / "polarizer_IMX250MZR_crop.png"
    assert main(["stokes", str(raw), "--sensor", "mono-polarization", "--out", str(out)]) == 0
    for name in ("i0", "i45", "i90", "i135", "dop", "aolp"):
        assert (out / f"{name}.exr").is_file() and (out / f"{name}.png").is_file()
    aolp = read_exr(out / "aolp.exr")["Y"]
    assert aolp.shape == (1344, 1680) and 0 <= aolp.min() and aolp.max() < np.pi
    assert read_png(out / "saturated.png").max() == 255
    summary = json.loads((out / "summary.json").read_text())
    assert 0.2 < summary["saturated_fraction"] < 0.4
    assert "saturated_fraction" in capsys.readouterr().out


def test_stokes_colour_and_errors(tmp_path, capsys):
    stokes = stokes_pattern("face", 32, 48, colour=True)
    raw = simulate_raw(
        mosaic(*np.moveaxis(intensities_from_stokes(stokes), -1, 0), sensor="color-polarization")
    )
    write_png(tmp_path / "raw.png", raw, bit_depth=16)
    out = tmp_path / "out"
    assert (
        main(
            [
                "stokes",
                str(tmp_path / "raw.png"),
                "--sensor",
                "color-polarization",
                "--bit-depth",
                "12",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert set(read_exr(out / "i90.exr")) == {"R", "G", "B"}
    # 8-bit file declared 12-bit, truncated file, odd size: clean errors, exit 2
    write_png(tmp_path / "eight.png", (raw // 16).astype(np.uint8))
    assert (
        main(
            [
                "stokes",
                str(tmp_path / "eight.png"),
                "--sensor",
                "color-polarization",
                "--bit-depth",
                "12",
                "--out",
                str(out),
            ]
        )
        == 2
    )
    assert "8-bit" in capsys.readouterr().err
    data = (tmp_path / "raw.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 3])
    assert (
        main(["stokes", str(tmp_path / "cut.png"), "--sensor", "color-polarization", "--out", str(out)]) == 2
    )
    assert "truncated" in capsys.readouterr().err
    write_png(tmp_path / "odd.png", raw[:31, :47], bit_depth=16)
    assert (
        main(["stokes", str(tmp_path / "odd.png"), "--sensor", "color-polarization", "--out", str(out)]) == 2
    )
    assert "multiples of 4" in capsys.readouterr().err


def test_stokes_all_saturated_warns(tmp_path, capsys):
    write_png(tmp_path / "sat.png", np.full((8, 8), 255, np.uint8))
    assert (
        main(
            [
                "stokes",
                str(tmp_path / "sat.png"),
                "--sensor",
                "mono-polarization",
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 0
    )
    assert "every pixel" in capsys.readouterr().out


def test_ingest_command(tmp_path, capsys):
    rig = paper_rig(width=48, height=32)
    rig.save(tmp_path / "rig.json")
    stokes = stokes_pattern("smooth", 32, 48, colour=True)
    raw = simulate_raw(
        mosaic(*np.moveaxis(intensities_from_stokes(stokes), -1, 0), sensor="color-polarization")
    )
    for frame in range(2):
        for cam in ("pol_upper", "pol_lower"):
            write_png(tmp_path / "raw" / cam / f"{frame}.png", raw, bit_depth=16)
    args = [
        "ingest",
        str(tmp_path / "raw"),
        "--rig",
        str(tmp_path / "rig.json"),
        "--out",
        str(tmp_path / "cap"),
        "--no-progress",
    ]
    assert main(args) == 0
    store = CaptureStore.open(tmp_path / "cap")
    assert len(store.frames) == 2 and store.observation("dop", 1, "pol_lower").shape == (32, 48, 3)
    (tmp_path / "raw" / "pol_lower" / "1.png").unlink()
    assert main(args) == 2
    assert "frame 1 is missing" in capsys.readouterr().err
    assert (
        main(
            [
                "ingest",
                str(tmp_path / "raw"),
                "--rig",
                str(tmp_path / "nope.json"),
                "--out",
                str(tmp_path / "c2"),
            ]
        )
        == 2
    )


def test_calibrate_command_stereo(test_data, tmp_path, capsys):
    folder = tmp_path / "cal"
    shutil.copytree(test_data / "calibration", folder)
    rig = Rig.model_validate(
        {
            "cameras": [
                {
                    "id": cam,
                    "role": "stereo",
                    "sensor": "rgb",
                    "width": 640,
                    "height": 480,
                    "K": [[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]],
                }
                for cam in ("left", "right")
            ]
        }
    )
    rig.save(tmp_path / "rig.json")
    assert (
        main(
            [
                "calibrate",
                "--rig",
                str(tmp_path / "rig.json"),
                "--camera",
                "left",
                "--stereo-camera",
                "right",
                "--list",
                str(folder / "stereo_calib.xml"),
                "--board",
                "chessboard:9x6",
                "--square-mm",
                "25",
                "--out",
                str(tmp_path / "rig_cal.json"),
            ]
        )
        == 0
    )
    calibrated = Rig.load(tmp_path / "rig_cal.json")
    assert calibrated.camera("left").K[0][0] == pytest.approx(536, rel=0.03)
    assert calibrated.camera("right").centre_mm[0] == pytest.approx(83.5, abs=3.0)
    report = json.loads((tmp_path / "calibration.json").read_text())
    assert report["stereo_rms_px"] < 0.6
    assert (
        main(
            [
                "calibrate",
                "--rig",
                str(tmp_path / "rig.json"),
                "--camera",
                "left",
                "--images",
                str(folder / "nothing*.jpg"),
                "--square-mm",
                "25",
            ]
        )
        == 2
    )
    assert (
        main(
            [
                "calibrate",
                "--rig",
                str(tmp_path / "rig.json"),
                "--camera",
                "left",
                "--images",
                str(folder / "left*.jpg"),
                "--board",
                "hexagon:3x3",
                "--square-mm",
                "25",
            ]
        )
        == 2
    )
