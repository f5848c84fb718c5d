"""polarface.capture.rig: schema validation, load/save, the paper rig."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from polarface.capture.rig import Camera, LightModule, Rig, paper_rig
from polarface.geometry.camera import look_at


def _camera(**overrides):
    data = {
        "id": "cam0",
        "role": "polarimetric",
        "sensor": "mono-polarization",
        "width": 64,
        "height": 48,
        "K": [[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]],
    }
    data.update(overrides)
    return data


def test_paper_rig_structure():
    rig = paper_rig()
    assert len(rig.polarimetric_cameras()) == 2 and len(rig.cameras) == 10 and len(rig.lights) == 8
    upper, lower = rig.camera("pol_upper"), rig.camera("pol_lower")
    assert sorted([*upper.colour_channels.values(), *lower.colour_channels.values()]) == list(range(6))
    assert upper.sensor == "color-polarization" and upper.width == 2448 and upper.height == 2048
    # 250 mm field at 1 m
    assert upper.intrinsics[0, 0] * 0.25 == pytest.approx(2448)
    # lights: 100 mm radius around the lens axis -> 5.72 deg at 1 m
    for light in rig.lights:
        radius = math.hypot(*light.position_mm[:2])
        assert math.degrees(math.atan2(radius, 1000.0)) == pytest.approx(5.71, abs=0.02)
        assert light.stokes == (1.0, 1.0, 0.0, 0.0)
    # cameras verge on the face centre
    face = np.array([0.0, 0.0, 1000.0, 1.0])
    for camera in rig.cameras:
        point = camera.pose @ face
        pixel = camera.intrinsics @ (point[:3] / point[2])
        assert pixel[:2] == pytest.approx([(camera.width - 1) / 2, (camera.height - 1) / 2], abs=1e-6)


def test_paper_rig_presets_scale():
    small = paper_rig(scale=2.0, width=64, height=48)
    assert small.camera("pol_upper").K[0][0] == pytest.approx(256.0)
    assert small.camera("pol_upper").K[0][2] == pytest.approx(31.5)
    assert math.hypot(*small.lights[0].position_mm[:2]) == pytest.approx(200.0)
    with pytest.raises(ValueError, match="multiples of 4"):
        paper_rig(width=30, height=48)
    with pytest.raises(ValueError, match="scale"):
        paper_rig(scale=0)


def test_save_load_roundtrip(tmp_path):
    rig = paper_rig(width=64, height=48)
    path = rig.save(tmp_path / "rig.json")
    assert Rig.load(path) == rig
    assert not list(tmp_path.glob(".tmp-*"))


@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        ({"K": [[1, 0], [0, 1]]}, "K"),
        ({"K": [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]}, "K"),
        ({"world_to_camera": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, "world_to_camera"),
        ({"sensor": "thermal"}, "sensor"),
        ({"role": "hero"}, "role"),
        ({"width": 0}, "width"),
        ({"bit_depth": 12, "white_level": 5000}, "white_level"),
        ({"black_level": -1}, "black_level"),
        ({"distortion": [0.1, 0.2, 0.3]}, "distortion"),
        ({"colour_channels": {"R": 7}}, "colour_channels"),
        ({"colour_channels": {"R": 1}}, "mono-polarization"),
        ({"unknown": 1}, "unknown"),
        ({"analyzer": {"extinction_ratio": 0.5}}, "analyzer(.|\n)*extinction_ratio: Input should be greater"),
        ({"analyzer": {"analyzer_angles_deg": [0, 45, 90]}}, "analyzer(.|\n)*analyzer_angles_deg"),
        ({"analyzer": {"analyzer_angles_deg": [90, 45, 0, 135]}}, "within 22.5 deg"),
        ({"analyzer": {"R": {"extinction_ratio": 100}}}, "color-polarization"),
        ({"sensor": "color-polarization", "analyzer": {"G": {"extinction_ratio": 1}}},
         "analyzer(.|\n)*G: extinction_ratio"),
        ({"channel_gains": [1.0, 0.0, 1.0]}, "channel_gains"),
        ({"channel_gains": [1.0, 1.0]}, "channel_gains"),
    ],
)
def test_camera_errors_name_field(overrides, field):
    with pytest.raises(ValueError, match=field):
        Camera.model_validate(_camera(**overrides))


def test_analyzer_calibration_round_trips_and_defaults_to_ideal(tmp_path):
    rig = paper_rig(width=64, height=48)
    camera = rig.polarimetric_cameras()[0]
    assert camera.analyzer is None and camera.analyzer_model("R").is_ideal
    per_colour = {"R": {"extinction_ratio": 80.0, "analyzer_angles_deg": [0.5, 45.2, 89.1, 135.0],
                        "extinction_ratio_std": 4.0, "analyzer_angles_std_deg": [0.02, 0.02, 0.03, 0.02]}}
    payload = json.loads(json.dumps(rig.model_dump()))
    payload["cameras"][0]["analyzer"] = per_colour
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(payload))
    loaded = Rig.load(path)
    model = loaded.cameras[0].analyzer_model("R")
    assert model.extinction_ratio == 80.0 and model.angles_deg == (0.5, 45.2, 89.1, 135.0)
    assert loaded.cameras[0].analyzer_model("G").is_ideal  # a colour left out is ideal
    with pytest.raises(ValueError, match="colour must be R, G or B"):
        loaded.cameras[0].analyzer_model(None)
    assert Rig.load(loaded.save(tmp_path / "again.json")) == loaded


def test_rig_errors(tmp_path):
    with pytest.raises(ValueError, match="unique"):
        Rig.model_validate({"cameras": [_camera(), _camera()]})
    with pytest.raises(ValueError, match="stokes"):
        LightModule(id="l", position_mm=(0, 0, 0), stokes=(1.0, 2.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="radiant_intensity"):
        LightModule(id="l", position_mm=(0, 0, 0), radiant_intensity=[1.0, 2.0])
    with pytest.raises(ValueError, match="not in the rig"):
        Rig.model_validate({"cameras": [_camera()]}).camera("nope")
    with pytest.raises(FileNotFoundError, match=r"missing\.json"):
        Rig.load(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match=r"bad\.json"):
        Rig.load(bad)
    wrong = tmp_path / "wrong.json"
    wrong.write_text(json.dumps({"cameras": [_camera(width=-3)]}))
    with pytest.raises(ValueError, match=r"wrong.json(.|\n)*width"):
        Rig.load(wrong)


def test_look_at_is_opencv():
    pose = look_at(np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 10.0]))
    np.testing.assert_allclose(pose, np.eye(4), atol=1e-12)


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (
            lambda d: d["lights"][3].__setitem__("position_mm", [0.0, float("inf"), 1000.0]),
            "lights[3].position_mm",
        ),
        (lambda d: d["lights"][0].__setitem__("polarizer_angle", float("nan")), "lights[0].polarizer_angle"),
        (lambda d: d["cameras"][1].__setitem__("exposure", float("inf")), "cameras[1].exposure"),
        (lambda d: d["cameras"][0].__setitem__("black_level", float("nan")), "cameras[0].black_level"),
        (lambda d: d["cameras"][0]["K"][0].__setitem__(2, float("inf")), "cameras[0].K"),
        (lambda d: d["spectral"]["led_spd"].__setitem__(0, float("nan")), "spectral.led_spd"),
        (lambda d: d["cameras"][0].__setitem__("pattern_phase", [5, -1]), "pattern_phase"),
    ],
)
def test_rig_load_rejects_non_finite_numbers_naming_the_field(tmp_path, edit, field):
    """Infinity/NaN (valid to Python's json) and an out-of-period mosaic phase are rejected, on one line."""
    data = json.loads(paper_rig(width=64, height=48).model_dump_json())
    edit(data)
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"rig\.json") as info:
        Rig.load(path)
    assert field in str(info.value)
    assert "\n" not in str(info.value)


def test_stereo_camera_pairs():
    rig = paper_rig(width=64, height=48)
    pairs = rig.stereo_camera_pairs()
    assert [(a.id, b.id) for a, b in pairs] == [(f"stereo{k}_a", f"stereo{k}_b") for k in range(4)]
    # without the explicit list the <module>_a / _b names pair them
    by_name = Rig.model_validate({**rig.model_dump(mode="json"), "stereo_pairs": []})
    assert [(a.id, b.id) for a, b in by_name.stereo_camera_pairs()] == [(a.id, b.id) for a, b in pairs]
    data = rig.model_dump(mode="json")
    with pytest.raises(ValueError, match="stereo_pairs"):
        Rig.model_validate({**data, "stereo_pairs": [["stereo0_a", "nope"]]})
    with pytest.raises(ValueError, match="stereo_pairs"):
        Rig.model_validate({**data, "stereo_pairs": [["stereo0_a", "stereo0_a"]]})
    lonely = {**data, "stereo_pairs": [], "cameras": [c for c in data["cameras"] if c["id"] != "stereo2_b"]}
    with pytest.raises(ValueError, match=r"stereo2_a.*no partner"):
        Rig.model_validate(lonely).stereo_camera_pairs()
    only_polarimetric = {**lonely, "cameras": [c for c in data["cameras"] if c["role"] == "polarimetric"]}
    with pytest.raises(ValueError, match="--mesh MESH --poses POSES"):
        Rig.model_validate(only_polarimetric).stereo_camera_pairs()


def test_geometry_differences_name_the_fields_that_differ():
    from polarface.capture.rig import paper_rig

    rig = paper_rig(width=64, height=48)
    assert rig.geometry_differences(paper_rig(width=64, height=48)) == []
    other = rig.model_copy(deep=True)
    other.cameras[0].K[0][0] += 1.0
    other.cameras[1].exposure = 3.0  # sensor settings may differ between captures
    other.lights[2].position_mm = (1.0, 2.0, 3.0)
    other.cameras[2].channel_gains = (1.0, 1.02, 1.0)
    differences = rig.geometry_differences(other)
    assert differences == [f"cameras[{rig.cameras[0].id}].K", f"cameras[{rig.cameras[2].id}].channel_gains",
                           f"lights[{rig.lights[2].id}].position_mm"]
    resized = rig.geometry_differences(paper_rig(width=128, height=96))
    assert "cameras[pol_upper].width" in resized and "cameras[pol_upper].K" in resized
