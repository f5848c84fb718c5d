"""A small synthetic session in the authors' layout (docs/authors_dataset.md): a textured plane 1 m in
front of the paper rig's two polarimetric cameras, seen by every view, written with known polarizer
images so an import can be checked value by value."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from polarface.capture.authors_layout import ColmapCamera, write_colmap_cameras, write_colmap_images
from polarface.capture.rig import paper_rig
from polarface.io import write_exr

ANGLES = (0, 45, 90, 135)


def plane_maps(resolution: int, spacing_mm: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """``(vertex, normal)`` maps of a plane z = 1000 mm facing the rig (normal -z), row 0 = v 1 = +y up:
    y decreases with the row (the rig world has y down, so the plane is seen upright)."""
    rows, cols = np.mgrid[0:resolution, 0:resolution].astype(np.float64)
    vertex = np.stack([(cols - resolution / 2) * spacing_mm, (rows - resolution / 2) * spacing_mm,
                       np.full_like(rows, 1000.0)], axis=-1)
    normal = np.zeros_like(vertex)
    normal[..., 2] = -1.0
    return vertex.astype(np.float32), normal.astype(np.float32)


def polarizer_stack(frame: int, camera: int, resolution: int) -> np.ndarray:
    """``(4, R, R, 3)`` I0, I45, I90, I135 of an ideal polarizer (Malus: ``(s0 + s1 cos 2t + s2 sin 2t) / 2``)
    with a smooth Stokes field that differs per frame and camera."""
    rows, cols = np.mgrid[0:resolution, 0:resolution].astype(np.float64)
    s0 = 0.4 + 0.05 * frame + 0.02 * camera + 0.01 * rows[..., None] * np.array([1.0, 0.8, 0.6])
    s1 = 0.3 * s0 * np.cos(0.2 * cols)[..., None]
    s2 = 0.1 * s0 * np.sin(0.3 * rows)[..., None]
    angles = np.radians(ANGLES)
    return np.stack([0.5 * (s0 + s1 * np.cos(2 * t) + s2 * np.sin(2 * t)) for t in angles]).astype(np.float32)


def write_fake_session(root: Path, frames: int = 2, resolution: int = 8, dynamic: bool = False) -> Path:
    """Write ``root`` (a module folder) and return it; white balance 1, identity ICP poses."""
    rig = paper_rig(width=48, height=32)
    cameras = rig.polarimetric_cameras()
    write_colmap_cameras(root / "cameras.txt", {
        i + 1: ColmapCamera(c.width, c.height, c.intrinsics, (0.0,) * 4) for i, c in enumerate(cameras)})
    write_colmap_images(root / "images.txt", {i + 1: c.pose for i, c in enumerate(cameras)})
    (root / "white_balance.txt").write_text("1 1.0 1.0 1.0\n2 1.0 1.0 1.0\n3 1.0 1.0 1.0\n")
    (root / "icp-pose").mkdir(parents=True)
    vertex, normal = plane_maps(resolution)
    for frame in range(frames):
        np.savetxt(root / "icp-pose" / f"{frame:04d}.txt", np.eye(4))
        if dynamic:
            write_exr(root / "texture" / "tracked" / f"vertex_{frame:04d}.exr", vertex)
            write_exr(root / "texture" / "tracked" / f"normal_{frame:04d}.exr", normal)
        for camera in (1, 2):
            stack = polarizer_stack(frame, camera, resolution)
            for angle, image in zip(ANGLES, stack, strict=True):
                folder = root / "texture" / str(angle) / "exr"
                write_exr(folder / f"img{camera}_{frame:04d}.exr", image)
                write_exr(folder / f"visible_img{camera}_{frame:04d}.exr", np.ones_like(image))
    if not dynamic:
        write_exr(root / "texture" / "vertex.exr", vertex)
        write_exr(root / "texture" / "normal.exr", normal)
    return root
