"""The ``authors-layout`` export: a RESULT's unwrapped observations and geometry written in the layout of
the authors' preprocessed face sessions (``docs/authors_dataset.md``), the inverse of
``polarface import-authors``.

Needs the RESULT's ``unwrap.zarr`` (its ``prepare`` stage), ``rig.json`` (two polarimetric cameras, the
first with channels 0-2) and, for the dynamic frames, ``frames/NNNN/unwrap.zarr`` and the dynamic stage's
alignment. Writes ``OUT/5_Static/90`` and, with dynamic frames, ``OUT/6_Dynamic_1/90``:

* ``texture/{0,45,90,135}/exr/img{1,2}_{FFFF}.exr`` from each view's ``[I_sss, I_zeta, I_s]``:
  ``I90 = I_sss / 2``, ``I0 = I_s + I90``, ``I45 = (I0 + I90 - I_zeta) / 2``,
  ``I135 = (I0 + I90 + I_zeta) / 2``
  (an ideal polarizer: ``I0 + I90 = I45 + I135``), times ``1e6 / sum_k I_L,k`` of the view's channels so
  that the importer's LED ring of total intensity 1e6 (:mod:`polarface.capture.authors_rig`) gives
  the same fit; ``visible_img*`` is the view's ``valid`` (1 / 0 in R, G, B), the same in each angle;
* static: ``texture/vertex.exr`` / ``normal.exr`` (the texel geometry, model frame = the reference
  frame), ``icp-pose/FFFF.txt`` (frame -> reference: the inverse of the frame's pose, recovered from the
  views' light and camera positions by a least-squares rigid fit); dynamic: ``texture/tracked/
  vertex_FFFF.exr`` / ``normal_FFFF.exr`` in the rig world (the alignment applied), ``icp-pose`` identity;
* ``cameras.txt``, ``images.txt`` (COLMAP text), ``white_balance.txt`` (gains 1).

Lost: per-LED shadow masks (the importer casts them again), tangents (recomputed from the vertex map),
held-out flags, the rig's stereo cameras and spectral calibration.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from polarface.capture.authors_layout import (
    AUTHORS_ANGLES,
    ColmapCamera,
    write_colmap_cameras,
    write_colmap_images,  # fmt: skip
)
from polarface.export.formats import ExportOptions
from polarface.export.source import ExportSource, MissingMapError
from polarface.io import atomic_path, write_exr
from polarface.texture import UnwrapStore

__all__ = ["polarizer_images", "write_authors_layout"]

_TOTAL_INTENSITY = 1.0e6


def polarizer_images(obs: np.ndarray) -> np.ndarray:
    """``(4, ..., C)`` I0, I45, I90, I135 of ``obs (..., 3, C)`` = ``[I_sss, I_zeta, I_s]`` (module
    docstring; float64)."""
    obs = np.asarray(obs, dtype=np.float64)
    i_sss, i_zeta, i_s = obs[..., 0, :], obs[..., 1, :], obs[..., 2, :]
    i90 = 0.5 * i_sss
    i0 = i_s + i90
    total = i0 + i90
    return np.stack([i0, 0.5 * (total - i_zeta), i90, 0.5 * (total + i_zeta)])


def _rigid_fit(model: np.ndarray, world: np.ndarray) -> np.ndarray:
    """``(4, 4)`` rigid transform with ``world ~ R model + t`` (least squares, Kabsch)."""
    mean_m, mean_w = model.mean(0), world.mean(0)
    u, _, vt = np.linalg.svd((model - mean_m).T @ (world - mean_w))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rotation = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, mean_w - rotation @ mean_m
    return pose


def _frame_poses(views, rig) -> dict[int, np.ndarray]:
    lights = np.array([light.position_mm for light in rig.lights], dtype=np.float64)
    centres = {c.id: c.centre_mm for c in rig.polarimetric_cameras()}
    poses = {}
    for view in views:
        model = np.vstack([np.asarray(view.light_positions), np.asarray(view.camera_center)[None]])
        world = np.vstack([lights, centres[view.camera_id][None]])
        poses.setdefault(view.frame, _rigid_fit(model, world))
    return poses


def _camera_numbers(rig) -> dict[str, int]:
    cameras = rig.polarimetric_cameras()
    if len(cameras) != 2:
        raise ValueError(f"the authors' layout has two polarimetric cameras; the rig has {len(cameras)}")
    ordered = sorted(cameras, key=lambda c: c.colour_channels.get("R", 0))
    return {camera.id: number for number, camera in enumerate(ordered, start=1)}


def _write_text(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)


def _write_cameras(root: Path, rig, numbers: dict[str, int]) -> None:
    cameras = {numbers[c.id]: c for c in rig.polarimetric_cameras()}
    write_colmap_cameras(root / "cameras.txt", {
        n: ColmapCamera(c.width, c.height, c.intrinsics, tuple(c.distortion)) for n, c in cameras.items()})
    write_colmap_images(root / "images.txt", {n: c.pose for n, c in cameras.items()})
    _write_text(root / "white_balance.txt", "".join(f"{n} 1.0 1.0 1.0\n" for n in sorted(cameras)))


def _write_views(unwrap: UnwrapStore, texture: Path, numbers: dict[str, int], frame_name) -> int:
    """Every view's four images and visibility maps; returns the number of files written."""
    count = 0
    everything = slice(None)
    for index, view in enumerate(unwrap.views):
        obs, valid, _ = unwrap.read(everything, everything, [index])
        scale = _TOTAL_INTENSITY / np.asarray(view.light_intensity, dtype=np.float64).sum(axis=0)
        images = polarizer_images(obs[0]) * scale
        name = f"img{numbers[view.camera_id]}_{frame_name(view.frame)}.exr"
        shown = np.repeat(valid[0][..., None], 3, axis=-1).astype(np.float32)
        for angle, image in zip(AUTHORS_ANGLES, images, strict=True):
            folder = texture / str(angle) / "exr"
            folder.mkdir(parents=True, exist_ok=True)
            write_exr(folder / name, np.where(valid[0][..., None], image, 0.0).astype(np.float32))
            write_exr(folder / f"visible_{name}", shown)
            count += 2
    return count


def _geometry_maps(unwrap: UnwrapStore, transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    geometry = unwrap.geometry()
    mask = geometry.mask[..., None]
    position = geometry.position.astype(np.float64) @ transform[:3, :3].T + transform[:3, 3]
    normal = geometry.normal.astype(np.float64) @ transform[:3, :3].T
    return (np.where(mask, position, 0.0).astype(np.float32), np.where(mask, normal, 0.0).astype(np.float32))


def _open_unwrap(path) -> UnwrapStore:
    if not Path(str(path)).is_dir():
        raise MissingMapError(f"export format 'authors-layout' needs the unwrap store '{path}' (the "
                              "RESULT's prepare stage: run 'polarface reconstruct' on the capture)")
    store = UnwrapStore.open(path)
    if not store.complete:
        raise ValueError(f"unwrap store '{path}' is not complete (resume the reconstruction first)")
    return store


def write_authors_layout(source: ExportSource, out: Path, options: ExportOptions) -> dict[str, Any]:
    """Write the RESULT of ``source`` in the authors' layout under ``out`` (module docstring).

    Raises:
        MissingMapError: no ``unwrap.zarr`` (of the RESULT or of an exported frame). ValueError: a rig
            without exactly two polarimetric cameras.
    """
    folder = source.folder
    rig = folder.read_rig()
    numbers = _camera_numbers(rig)
    unwrap = _open_unwrap(folder.unwrap_path)
    frame_unwraps = [_open_unwrap(folder.frame(f).unwrap_path) for f in source.frames]
    files = 0
    static = out / "5_Static" / "90"
    _write_cameras(static, rig, numbers)
    poses = _frame_poses(unwrap.views, rig)
    order = {frame: k for k, frame in enumerate(sorted(poses))}
    for frame, pose in poses.items():
        _write_text(static / "icp-pose" / f"{order[frame]:04d}.txt",
                    "\n".join(" ".join(repr(float(v)) for v in row) for row in np.linalg.inv(pose)) + "\n")
    vertex, normal = _geometry_maps(unwrap, np.eye(4))
    write_exr(static / "texture" / "vertex.exr", vertex)
    write_exr(static / "texture" / "normal.exr", normal)
    files += 3 + len(poses) + 2
    files += _write_views(unwrap, static / "texture", numbers, lambda f: f"{order[f]:04d}")
    written = ["5_Static/90"]
    if frame_unwraps:
        dynamic = out / "6_Dynamic_1" / "90"
        recorded = folder.stage_record("dynamic").get("alignment", np.eye(4).tolist())
        alignment = np.asarray(recorded, np.float64)
        _write_cameras(dynamic, rig, numbers)
        for k, frame_unwrap in enumerate(frame_unwraps):
            _write_text(dynamic / "icp-pose" / f"{k:04d}.txt", "\n".join(
                " ".join(repr(float(v)) for v in row) for row in np.eye(4)) + "\n")
            vertex, normal = _geometry_maps(frame_unwrap, alignment)
            write_exr(dynamic / "texture" / "tracked" / f"vertex_{k:04d}.exr", vertex)
            write_exr(dynamic / "texture" / "tracked" / f"normal_{k:04d}.exr", normal)
            files += 3 + _write_views(frame_unwrap, dynamic / "texture", numbers, lambda _f, k=k: f"{k:04d}")
        files += 3
        written.append("6_Dynamic_1/90")
    return {"files": written, "file_count": files, "frames": list(source.frames),
            "notes": "import: 'polarface import-authors OUT/5_Static/90 --out DIR' (docs/authors_dataset.md)"}
