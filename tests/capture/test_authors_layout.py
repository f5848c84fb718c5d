"""The authors' session layout: scan checks (partial downloads named), COLMAP text files, gains, poses,
and the session's rig (the LED ring reproduces the paper rig's lights)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from authors_fixtures import write_fake_session
from polarface.capture import authors_rig, paper_rig, scan_session
from polarface.capture.authors_layout import (
    ColmapCamera,
    read_colmap_cameras,
    read_colmap_images,
    read_icp_poses,
    read_white_balance,
    write_colmap_cameras,
    write_colmap_images,
)
from polarface.capture.authors_rig import led_ring


@pytest.fixture
def session(tmp_path):
    return write_fake_session(tmp_path / "5_Static" / "90", frames=2, resolution=4)


def test_scan_finds_frames_cameras_and_angles(session) -> None:
    scanned = scan_session(session.parent)  # the module's parent folder resolves to its "90"
    assert scanned.root == session and not scanned.dynamic
    assert scanned.frame_names == ("0000", "0001")
    assert len(scanned.observation_paths) == 4 * 2 * 2
    image, visibility = scanned.observation_paths[(135, 2, 1)]
    assert image.name == "img2_0001.exr" and visibility.name == "visible_img2_0001.exr"


def test_missing_angle_folder_is_named(session) -> None:
    shutil.rmtree(session / "texture" / "45")
    with pytest.raises(FileNotFoundError, match=r"texture/45/exr"):
        scan_session(session)


def test_frame_count_mismatch_between_angles_is_named(session) -> None:
    for name in ("img2_0001.exr", "visible_img2_0001.exr"):
        (session / "texture" / "90" / "exr" / name).unlink()
    pattern = r"texture/90/exr' holds 1 img2_\*\.exr frames .* frame 0001 is missing"
    with pytest.raises(ValueError, match=pattern):
        scan_session(session)


def test_missing_visibility_map_is_named(session) -> None:
    (session / "texture" / "0" / "exr" / "visible_img1_0000.exr").unlink()
    with pytest.raises(FileNotFoundError, match=r"visible_img1_0000\.exr"):
        scan_session(session)


def test_missing_camera_file_and_geometry_maps_are_named(session) -> None:
    (session / "texture" / "normal.exr").unlink()
    with pytest.raises(FileNotFoundError, match=r"texture/normal\.exr"):
        scan_session(session)
    (session / "images.txt").unlink()
    with pytest.raises(FileNotFoundError, match=r"images\.txt"):
        scan_session(session)


def test_dynamic_tracked_maps_must_match_the_frames(tmp_path) -> None:
    root = write_fake_session(tmp_path / "6_Dynamic_1" / "90", frames=2, resolution=4, dynamic=True)
    assert scan_session(root).dynamic
    (root / "texture" / "tracked" / "normal_0001.exr").unlink()
    with pytest.raises(ValueError, match=r"tracked' holds 1 normal\*\.exr maps"):
        scan_session(root)


def test_colmap_quaternion_reference_values(tmp_path) -> None:
    # 90 deg about z: q = (cos 45, 0, 0, sin 45) -> x maps to y
    half = np.sqrt(0.5)
    (tmp_path / "images.txt").write_text(f"# comment\n1 {half} 0 0 {half} 1 2 3 1 cam1.png\n\n")
    pose = read_colmap_images(tmp_path / "images.txt")[1]
    np.testing.assert_allclose(pose[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(pose[:3, 3], [1, 2, 3])


def test_colmap_files_round_trip_against_scipy(tmp_path) -> None:
    rotations = Rotation.random(6, random_state=3)
    poses = {}
    for index, rotation in enumerate(rotations, start=1):
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = rotation.as_matrix(), [10.0 * index, -5.0, 900.0]
        poses[index] = pose
    write_colmap_images(tmp_path / "images.txt", poses)
    read = read_colmap_images(tmp_path / "images.txt")
    for index, pose in poses.items():
        np.testing.assert_allclose(read[index], pose, atol=1e-12)
    K = np.array([[9800.0, 0, 1223.5], [0, 9790.0, 1023.5], [0, 0, 1]])
    write_colmap_cameras(tmp_path / "cameras.txt", {1: ColmapCamera(2448, 2048, K, (0.1, -0.2, 1e-3, 2e-3))})
    camera = read_colmap_cameras(tmp_path / "cameras.txt")[1]
    assert (camera.width, camera.height, camera.distortion) == (2448, 2048, (0.1, -0.2, 1e-3, 2e-3))
    np.testing.assert_array_equal(camera.K, K)


def test_bad_camera_model_and_gains_are_refused(tmp_path) -> None:
    (tmp_path / "cameras.txt").write_text("1 SIMPLE_RADIAL 10 10 5 5 5 0.1\n")
    with pytest.raises(ValueError, match=r"cameras\.txt.*SIMPLE_RADIAL"):
        read_colmap_cameras(tmp_path / "cameras.txt")
    (tmp_path / "white_balance.txt").write_text("1 1.0 2.0 3.0\n2 1.0 -1.0 1.0\n")
    with pytest.raises(ValueError, match=r"white_balance\.txt.*camera 2"):
        read_white_balance(tmp_path / "white_balance.txt")
    (tmp_path / "white_balance.txt").write_text("1 1.0 2.0 3.0\n2 0.5 0.25 4.0\n")
    gains = read_white_balance(tmp_path / "white_balance.txt")
    np.testing.assert_array_equal(gains[1], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(gains[2], [0.5, 0.25, 4.0])


def test_icp_poses_count_and_rigidity(tmp_path) -> None:
    folder = tmp_path / "icp-pose"
    folder.mkdir()
    np.savetxt(folder / "0000.txt", np.eye(4))
    with pytest.raises(ValueError, match=r"icp-pose' holds 1 pose files .* 2 frames"):
        read_icp_poses(folder, 2)
    np.savetxt(folder / "0001.txt", 2.0 * np.eye(4))
    with pytest.raises(ValueError, match=r"0001\.txt' is not a rigid"):
        read_icp_poses(folder, 2)


def test_led_ring_reproduces_the_paper_rig_lights() -> None:
    rig = paper_rig()
    cameras = rig.polarimetric_cameras()
    ring = led_ring([c.pose for c in cameras])
    expected = np.array([light.position_mm for light in rig.lights])
    np.testing.assert_allclose(ring, expected, atol=1e-9)


def test_authors_rig_channels_intensity_and_missing_camera(session) -> None:
    cameras = read_colmap_cameras(session / "cameras.txt")
    images = read_colmap_images(session / "images.txt")
    rig = authors_rig(cameras, images, "session")
    assert [c.colour_channels for c in rig.polarimetric_cameras()] == [
        {"R": 0, "G": 1, "B": 2}, {"R": 3, "G": 4, "B": 5}]
    # eight modules of 1e6 / 8: the summed irradiance at 1 m is 1 / (1 m)^2 in mm^2 units
    assert sum(light.radiant_intensity for light in rig.lights) == pytest.approx(1.0e6)
    del images[2]
    with pytest.raises(ValueError, match=r"images\.txt' has no camera 2"):
        authors_rig(cameras, images, "session")
