"""Rigid poses: 4x4 transforms from yaw/pitch/roll + translation, the static chair sequence, JSON/NPY I/O.

Frames and conventions (``docs/geometry.md``):

* World frame of the bundled head: millimetres, +y up, the face looks towards +z, +x is the subject's
  left (right-handed).
* A pose ``T`` is a ``(4, 4)`` float64 matrix mapping head (model) coordinates to world coordinates:
  ``p_world = R p_model + t``; sequences are ``(N, 4, 4)``.
* Euler angles, radians: ``R = R_y(yaw) @ R_x(pitch) @ R_z(roll)`` (intrinsic yaw, then pitch, then roll).
  Positive yaw turns the face from +z towards +x; positive pitch (rotation about +x) tilts the face
  down (chin towards the chest); positive roll rotates about +z (the viewing axis).

The static capture (paper Sec. 4 and 5.1: the subject turns on a revolving chair, ~200 frames, neutral
face) is modelled as a yaw sweep about a vertical axis through the neck plus a slow pitch nod.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path

import numpy as np

from polarface.io.atomic import atomic_path, write_json_atomic

__all__ = [
    "StaticSequenceConfig",
    "check_rigid",
    "euler_from_rotation",
    "invert_rigid",
    "load_poses",
    "rigid_transform",
    "rotation_from_euler",
    "save_poses",
    "static_sequence_poses",
]


def rotation_from_euler(yaw: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """Rotation ``(3, 3)`` float64 ``R_y(yaw) @ R_x(pitch) @ R_z(roll)``; angles in radians."""
    for name, value in (("yaw", yaw), ("pitch", pitch), ("roll", roll)):
        if not math.isfinite(float(value)):
            raise ValueError(f"argument '{name}' must be finite; got {value}")
    cy, sy = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    r_y = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    r_x = np.array([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])
    r_z = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]])
    return r_y @ r_x @ r_z


def euler_from_rotation(rotation: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`rotation_from_euler`: ``(yaw, pitch, roll)`` in radians, pitch in [-pi/2, pi/2]."""
    r = np.asarray(rotation, dtype=np.float64)
    pitch = math.asin(float(np.clip(-r[1, 2], -1.0, 1.0)))
    yaw = math.atan2(float(r[0, 2]), float(r[2, 2]))
    roll = math.atan2(float(r[1, 0]), float(r[1, 1]))
    return yaw, pitch, roll


def rigid_transform(
    yaw: float = 0.0,
    pitch: float = 0.0,
    roll: float = 0.0,
    translation: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
    pivot: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> np.ndarray:
    """4x4 rigid transform: rotate about ``pivot`` (mm) by yaw/pitch/roll (radians), then translate (mm).

    ``p' = R (p - pivot) + pivot + translation``.
    """
    translation = np.asarray(translation, dtype=np.float64).reshape(3)
    pivot = np.asarray(pivot, dtype=np.float64).reshape(3)
    if not (np.isfinite(translation).all() and np.isfinite(pivot).all()):
        raise ValueError("arguments 'translation' and 'pivot' must be finite")
    rotation = rotation_from_euler(yaw, pitch, roll)
    matrix = np.eye(4)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = pivot - rotation @ pivot + translation
    return matrix


def check_rigid(transform: np.ndarray, name: str = "transform", atol: float = 1e-6) -> np.ndarray:
    """Return ``transform`` as float64 ``(..., 4, 4)`` after checking it is a proper rigid motion.

    Raises:
        ValueError: naming ``name`` if the shape is wrong, values are not finite, the rotation block is
            not orthonormal with determinant +1, or the last row is not ``[0, 0, 0, 1]`` (tolerance ``atol``).
    """
    matrix = np.asarray(transform, dtype=np.float64)
    if matrix.ndim < 2 or matrix.shape[-2:] != (4, 4):
        raise ValueError(f"argument '{name}' must have shape (..., 4, 4); got {matrix.shape}")
    if not np.isfinite(matrix).all():
        raise ValueError(f"argument '{name}' contains NaN or infinite values")
    rotation = matrix[..., :3, :3]
    gram = np.swapaxes(rotation, -1, -2) @ rotation
    if np.abs(gram - np.eye(3)).max() > atol:
        raise ValueError(f"argument '{name}' has a rotation block that is not orthonormal")
    if np.abs(np.linalg.det(rotation) - 1.0).max() > atol:
        raise ValueError(f"argument '{name}' has a rotation block with determinant != +1 (a reflection)")
    if np.abs(matrix[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max() > atol:
        raise ValueError(f"argument '{name}' must have last row [0, 0, 0, 1]")
    return matrix


def invert_rigid(transform: np.ndarray) -> np.ndarray:
    """Exact inverse ``(..., 4, 4)`` of rigid transforms: ``[R^T, -R^T t]``."""
    matrix = check_rigid(transform)
    rotation_t = np.swapaxes(matrix[..., :3, :3], -1, -2)
    out = np.zeros_like(matrix)
    out[..., :3, :3] = rotation_t
    out[..., :3, 3] = -(rotation_t @ matrix[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


@dataclasses.dataclass(frozen=True)
class StaticSequenceConfig:
    """The static capture: the subject turns on a revolving chair (paper Sec. 4, ~200 frames at 20 fps).

    Attributes:
        frame_count: number of frames N (the paper captures about 200).
        yaw_range: half range of the yaw sweep in radians (+-60 deg): yaw goes from -yaw_range to
            +yaw_range following a smooth (half-cosine) profile, so the chair slows at the ends.
        pitch_amplitude: amplitude of a slow nod in radians (5 deg), one full period over the sequence.
        pivot: point on the vertical rotation axis in model coordinates, mm (through the neck, behind the
            face; the bundled head's pivot is :attr:`HeadAsset.neck_pivot`).
        translation: constant offset applied after rotation, mm.
    """

    frame_count: int = 200
    yaw_range: float = math.radians(60.0)
    pitch_amplitude: float = math.radians(5.0)
    pivot: tuple[float, float, float] = (0.0, -90.0, -35.0)
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if int(self.frame_count) < 1:
            raise ValueError(f"frame_count must be >= 1; got {self.frame_count}")
        if not (0.0 <= self.yaw_range <= math.pi and abs(self.pitch_amplitude) <= math.pi / 2):
            raise ValueError("yaw_range must lie in [0, pi] and |pitch_amplitude| <= pi/2 (radians)")


def static_sequence_poses(config: StaticSequenceConfig | None = None) -> np.ndarray:
    """Poses ``(N, 4, 4)`` float64 of the static rotation sequence (model -> world, mm).

    Frame ``k`` of N has phase ``s = k / (N - 1)`` (0 for N = 1): ``yaw = -yaw_range cos(pi s)`` and
    ``pitch = pitch_amplitude sin(2 pi s)``; the rotation is about the vertical axis through ``pivot``.
    """
    config = config or StaticSequenceConfig()
    count = int(config.frame_count)
    phase = np.arange(count) / max(count - 1, 1)
    yaws = -config.yaw_range * np.cos(np.pi * phase) if count > 1 else np.zeros(1)
    pitches = config.pitch_amplitude * np.sin(2.0 * np.pi * phase)
    return np.stack(
        [
            rigid_transform(float(y), float(p), 0.0, config.translation, config.pivot)
            for y, p in zip(yaws, pitches, strict=True)
        ]
    )


def save_poses(path: str | os.PathLike[str], poses: np.ndarray) -> Path:
    """Save rigid poses ``(N, 4, 4)`` (or one ``(4, 4)``) as ``.json`` or ``.npy``, atomically.

    JSON layout: ``{"units": "mm", "convention": "model_to_world, p' = R p + t", "poses": [4x4, ...]}``.
    """
    matrix = check_rigid(poses, "poses")
    stacked = matrix.reshape(-1, 4, 4)
    path = Path(path)
    if path.suffix.lower() == ".json":
        payload = {
            "units": "mm",
            "convention": "model_to_world 4x4, p_world = R p_model + t",
            "poses": stacked.tolist(),
        }
        return write_json_atomic(path, payload)
    if path.suffix.lower() == ".npy":
        with atomic_path(path) as tmp, open(tmp, "wb") as handle:
            np.save(handle, stacked)
        return path
    raise ValueError(f"pose file '{path}': unsupported suffix (use .json or .npy)")


def load_poses(path: str | os.PathLike[str]) -> np.ndarray:
    """Load poses ``(N, 4, 4)`` float64 from ``.json`` (layout of :func:`save_poses`, or a bare list of
    4x4 matrices) or ``.npy``; checks they are rigid.

    Raises:
        FileNotFoundError: if missing. ValueError: naming the file on bad content.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"pose file '{path}' does not exist")
    try:
        if path.suffix.lower() == ".json":
            payload = json.loads(path.read_text(encoding="utf-8"))
            if isinstance(payload, dict):
                units = payload.get("units", "mm")
                if units != "mm":
                    raise ValueError(f"units must be 'mm', got {units!r}")
                payload = payload["poses"]
            array = np.asarray(payload, dtype=np.float64)
        elif path.suffix.lower() == ".npy":
            array = np.load(path, allow_pickle=False).astype(np.float64)
        else:
            raise ValueError("unsupported suffix (use .json or .npy)")
        array = array.reshape(-1, 4, 4) if array.size % 16 == 0 and array.size else array
        return check_rigid(array, "poses").reshape(-1, 4, 4)
    except (ValueError, KeyError, TypeError, json.JSONDecodeError) as exc:
        raise ValueError(f"pose file '{path}': {exc}") from exc
