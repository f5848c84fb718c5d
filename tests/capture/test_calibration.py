"""polarface.capture.calibration on the real OpenCV sample photos (tests/data/calibration)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from polarface.capture.calibration import (
    CharucoBoardSpec,
    calibrate_intrinsics,
    calibrate_stereo,
    chessboard_object_points,
    detect_charuco,
    detect_chessboard,
    read_gray,
    read_image_list,
    reprojection_rms,
    update_rig,
)
from polarface.capture.rig import Camera, Rig

SQUARE_MM = 25.0  # not documented for the OpenCV samples; any value scales T only


@pytest.fixture(scope="module")
def stereo_views():
    from pathlib import Path

    folder = Path(__file__).parents[1] / "data" / "calibration"
    paths = read_image_list(folder / "stereo_calib.xml")
    obj, left, right = [], [], []
    for a, b in zip(paths[0::2], paths[1::2], strict=True):
        corners_a = detect_chessboard(read_gray(a), (9, 6))
        corners_b = detect_chessboard(read_gray(b), (9, 6))
        assert corners_a is not None and corners_b is not None, (a, b)
        obj.append(chessboard_object_points((9, 6), SQUARE_MM))
        left.append(corners_a)
        right.append(corners_b)
    return paths, obj, left, right


def test_image_list_matches_shipped_pairs(stereo_views):
    paths = stereo_views[0]
    assert len(paths) == 26
    names = [p.name for p in paths]
    assert names[0::2] == [f"left{k:02d}.jpg" for k in (*range(1, 10), 11, 12, 13, 14)]
    assert names[1::2] == [n.replace("left", "right") for n in names[0::2]]


@pytest.mark.slow
def test_intrinsics_and_stereo(stereo_views):
    _, obj, left, right = stereo_views
    intrinsics_left = calibrate_intrinsics(obj, left, (640, 480))
    intrinsics_right = calibrate_intrinsics(obj, right, (640, 480))
    assert intrinsics_left.rms < 0.5 and intrinsics_right.rms < 0.5
    assert intrinsics_left.K[0, 0] == pytest.approx(536, rel=0.02)  # OpenCV tutorial: fx ~ 532..537
    assert intrinsics_left.per_view_rms.shape == (13,)
    stereo = calibrate_stereo(
        obj, left, right, (640, 480), intrinsics_a=intrinsics_left, intrinsics_b=intrinsics_right
    )
    assert stereo.rms < 0.6 and stereo.epipolar_rms < 0.5
    # horizontal stereo pair: baseline along -x of the left camera, ~3.3 squares, small rotation
    assert stereo.T[0] < 0 and abs(stereo.T[0]) > 10 * max(abs(stereo.T[1]), abs(stereo.T[2]))
    assert stereo.baseline_mm / SQUARE_MM == pytest.approx(3.34, abs=0.1)
    assert np.degrees(np.linalg.norm(cv2.Rodrigues(stereo.R)[0])) < 2.0
    # reprojection agrees with the board poses
    rms = reprojection_rms(
        obj[0],
        left[0],
        intrinsics_left.K,
        intrinsics_left.distortion,
        intrinsics_left.rvecs[0],
        intrinsics_left.tvecs[0],
    )
    assert rms == pytest.approx(intrinsics_left.per_view_rms[0])


def test_charuco_detection_and_tutorial_intrinsics(test_data):
    image = read_gray(test_data / "calibration" / "choriginal.jpg")
    spec = CharucoBoardSpec(5, 7, 40.0, 20.0, "DICT_6X6_250")
    obj, img, ids = detect_charuco(image, spec)
    assert len(ids) == 24 and obj.shape == (24, 3)
    storage = cv2.FileStorage(
        str(test_data / "calibration" / "tutorial_camera_charuco.yml"), cv2.FILE_STORAGE_READ
    )
    K, dist = storage.getNode("camera_matrix").mat(), storage.getNode("distortion_coefficients").mat()
    storage.release()
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist)
    assert ok and reprojection_rms(obj, img, K, dist, rvec, tvec) < 0.5
    empty = detect_charuco(np.zeros((100, 100), np.uint8), spec)
    assert empty[0].shape == (0, 3)
    with pytest.raises(ValueError, match="dictionary"):
        CharucoBoardSpec(dictionary="DICT_NOPE").board()


def test_update_rig():
    rig = Rig(
        cameras=[
            Camera(
                id="a",
                role="stereo",
                sensor="rgb",
                width=640,
                height=480,
                K=[[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]],
            )
        ]
    )
    K = np.array([[536.0, 0, 342], [0, 536.0, 235], [0, 0, 1]])
    pose = np.eye(4)
    pose[0, 3] = -83.0
    updated = update_rig(rig, "a", K=K, distortion=np.zeros(5), image_size=(640, 480), world_to_camera=pose)
    assert updated.camera("a").K[0][0] == 536.0 and updated.camera("a").world_to_camera[0][3] == -83.0
    with pytest.raises(ValueError, match="640x480"):
        update_rig(rig, "a", K=K, distortion=np.zeros(5), image_size=(320, 240))
    with pytest.raises(ValueError, match="not in the rig"):
        update_rig(rig, "b", K=K, distortion=np.zeros(5))


def test_calibration_errors(tmp_path):
    with pytest.raises(ValueError, match="at least 3"):
        calibrate_intrinsics([np.zeros((4, 3))], [np.zeros((4, 2))], (64, 64))
    with pytest.raises(FileNotFoundError):
        read_gray(tmp_path / "none.jpg")
    (tmp_path / "bad.jpg").write_bytes(b"nope")
    with pytest.raises(ValueError, match=r"bad\.jpg"):
        read_gray(tmp_path / "bad.jpg")
    assert detect_chessboard(np.zeros((64, 64), np.uint8), (9, 6)) is None


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"images": []}, "--images"),
        ({"board": "chessboard:2x6"}, "--board"),
        ({"board": "chessboard:9x0"}, "--board"),
        ({"board": "charuco:1x7"}, "--board"),
        ({"board": "charuco:5x7", "marker_mm": 0.0}, "--marker-mm"),
        ({"board": "charuco:5x7", "marker_mm": float("inf")}, "--marker-mm"),
    ],
)
def test_calibrate_rig_rejects_bad_arguments_before_reading_images(tmp_path, kwargs, message):
    from polarface.capture.rig import Rig
    from polarface.capture.rig_calibration import calibrate_rig

    K = [[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]
    camera = {"id": "left", "role": "stereo", "sensor": "rgb", "width": 640, "height": 480, "K": K}
    Rig.model_validate({"cameras": [camera]}).save(tmp_path / "rig.json")
    (tmp_path / "bad.jpg").write_bytes(b"not an image: never read")
    arguments = {"square_mm": 25.0, "images": [str(tmp_path / "bad.jpg")], **kwargs}
    with pytest.raises(ValueError, match=message):
        calibrate_rig(tmp_path / "rig.json", "left", out=tmp_path / "out.json", **arguments)
    assert not (tmp_path / "out.json").exists()
