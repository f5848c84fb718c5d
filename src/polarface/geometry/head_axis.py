"""The head's vertical axis for the cylindrical atlas of :mod:`polarface.geometry.atlas`: its direction and
a point on it from a revolving-chair pose sequence (the chair's rotation axis), or a point from the surface
alone.

Frames and units (``docs/geometry.md``): positions in mm in the **model frame** = the rig world at the
reference frame (x right, y down, z away from the cameras), so the head's default up axis is
``(0, -1, 0)``; poses ``(F, 4, 4)`` float64 model -> world rigid transforms; directions ``(3,)`` unit
vectors.
"""

from __future__ import annotations

import math

import numpy as np

from polarface.geometry.poses import check_rigid

__all__ = [
    "DEFAULT_UP_AXIS",
    "default_axis_point",
    "head_axis_from_poses",
    "head_axis_point_from_poses",
    "unit_vector",
]

DEFAULT_UP_AXIS = (0.0, -1.0, 0.0)
"""The head's up axis in the rig/model frame (rig y points down)."""


def unit_vector(value, name: str) -> np.ndarray:
    """``value`` normalised to a ``(3,)`` float64 unit vector.

    Raises:
        ValueError: naming the argument ``name``, unless ``value`` is a finite non-zero 3-vector.
    """
    vector = np.asarray(value, dtype=np.float64)
    if vector.shape != (3,) or not np.isfinite(vector).all():
        raise ValueError(f"argument '{name}' must be a finite 3-vector; got {value!r}")
    norm = float(np.linalg.norm(vector))
    if norm < 1e-12:
        raise ValueError(f"argument '{name}' must be non-zero; got {value!r}")
    return vector / norm


def _check_poses(poses) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or poses.shape[0] == 0:
        raise ValueError(f"argument 'poses' must be a non-empty (F, 4, 4) array; got {poses.shape}")
    if not np.isfinite(poses).all():
        raise ValueError("argument 'poses' contains NaN/inf values")
    for index, pose in enumerate(poses):
        check_rigid(pose, f"poses[{index}]")
    return poses


def _reference_index(poses: np.ndarray, reference: int | None) -> int:
    if reference is None:  # the frame closest to the identity: the model frame is its rig world
        traces = np.trace(poses[:, :3, :3], axis1=1, axis2=2)
        return int(np.argmax(traces))
    if not -len(poses) <= int(reference) < len(poses):
        raise ValueError(f"argument 'reference' must index the {len(poses)} poses; got {reference}")
    return int(reference) % len(poses)


def _relative_motions(poses: np.ndarray, reference: int) -> np.ndarray:
    """``(F, 4, 4)`` motions ``T_ref^-1 T_i`` in the model frame (identity for the reference)."""
    ref = poses[reference]
    inverse = np.eye(4)
    inverse[:3, :3] = ref[:3, :3].T
    inverse[:3, 3] = -ref[:3, :3].T @ ref[:3, 3]
    return inverse[None] @ poses


def _rotation_vectors(rotations: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(rotations).as_rotvec()


def head_axis_from_poses(
    poses: np.ndarray,
    *,
    default_axis: np.ndarray | tuple[float, float, float] = DEFAULT_UP_AXIS,
    min_rotation_deg: float = 5.0,
    reference: int | None = None,
) -> np.ndarray:
    """The head's vertical axis ``(3,)`` (unit, model frame) from a revolving-chair pose sequence.

    Each frame's motion relative to the reference frame, ``R_ref^T R_i`` (a rotation in the model
    frame), has a rotation axis ``a_i`` and angle ``w_i``. The chair turns the head about one vertical
    axis, plus small nods and sways; the estimate is the principal eigenvector of
    ``sum_i w_i a_i a_i^T`` (the angle-weighted mean axis, independent of the turning direction, so
    left and right turns add up instead of cancelling; frames with a large turn dominate the nods).
    Its sign is chosen to point "up": ``a . default_axis >= 0`` (``default_axis`` = rig -y).

    Args:
        poses: ``(F, 4, 4)`` float64 model -> world rigid transforms (mm).
        default_axis: returned (normalised) when no frame turns by ``min_rotation_deg`` relative to
            the reference, and the "up" half-space for the sign.
        min_rotation_deg: the largest relative rotation must reach this to estimate an axis.
        reference: index of the reference frame; None = the frame whose rotation is closest to the
            identity (the model frame is the rig world at the reference frame).

    Raises:
        ValueError: naming the argument, on bad shapes, non-finite or non-rigid poses, a zero or
            non-finite ``default_axis`` or a non-positive / non-finite ``min_rotation_deg``.
    """
    up = unit_vector(default_axis, "default_axis")
    if not (math.isfinite(float(min_rotation_deg)) and float(min_rotation_deg) > 0):
        raise ValueError(f"argument 'min_rotation_deg' must be finite and > 0; got {min_rotation_deg}")
    poses = _check_poses(poses)
    motions = _relative_motions(poses, _reference_index(poses, reference))
    rotvecs = _rotation_vectors(motions[:, :3, :3])
    angles = np.linalg.norm(rotvecs, axis=1)
    if angles.max() < math.radians(float(min_rotation_deg)):
        return up
    moving = angles > 1e-9
    axes = rotvecs[moving] / angles[moving, None]
    scatter = np.einsum("f,fi,fj->ij", angles[moving], axes, axes)
    _, vectors = np.linalg.eigh(scatter)
    axis = vectors[:, -1]
    return axis if float(axis @ up) >= 0 else -axis


def head_axis_point_from_poses(
    poses: np.ndarray,
    axis_direction: np.ndarray | tuple[float, float, float],
    *,
    min_rotation_deg: float = 5.0,
    reference: int | None = None,
) -> np.ndarray:
    """A point ``(3,)`` (mm, model frame) on the chair's rotation axis, the closest one to the origin.

    For a rotation about an axis through ``c`` the relative motion ``(R_i, t_i)`` fixes ``c`` up to a
    slide along the axis: ``(I - R_i) c = t_i - (t_i . a) a``. The equations of all frames are solved
    in the least-squares sense (frames weighted by their rotation angle); the minimum-norm solution is
    the point of the axis closest to the model origin.

    Raises:
        ValueError: naming the argument, on bad poses or axis, or when no frame turns by at least
            ``min_rotation_deg`` relative to the reference (the axis position is then undefined).
    """
    axis = unit_vector(axis_direction, "axis_direction")
    poses = _check_poses(poses)
    motions = _relative_motions(poses, _reference_index(poses, reference))
    angles = np.linalg.norm(_rotation_vectors(motions[:, :3, :3]), axis=1)
    if angles.max() < math.radians(float(min_rotation_deg)):
        raise ValueError(
            f"argument 'poses' turns by at most {math.degrees(angles.max()):.2f} deg "
            f"(< {min_rotation_deg} deg): the rotation axis position is undefined"
        )
    translations = motions[:, :3, 3]
    rhs = translations - (translations @ axis)[:, None] * axis
    lhs = np.eye(3)[None] - motions[:, :3, :3]
    weights = np.sqrt(angles)[:, None]
    point, *_ = np.linalg.lstsq(
        (lhs * weights[:, :, None]).reshape(-1, 3), (rhs * weights).reshape(-1), rcond=None
    )
    return point - (point @ axis) * axis


def default_axis_point(vertices: np.ndarray, axis_direction: np.ndarray) -> np.ndarray:
    """A point ``(3,)`` mm on the head axis from the surface alone: the centre of the circle fitted to
    the vertices projected onto the plane orthogonal to the axis (algebraic least-squares fit), at
    the vertices' mean height. The fit uses the arc of an open (front-only) surface, unlike the
    centroid, which lies in front of the axis for such a surface. Prefer
    :func:`head_axis_point_from_poses` when a rotation sequence is available.
    """
    axis = unit_vector(axis_direction, "axis_direction")
    vertices = np.asarray(vertices, dtype=np.float64)
    mean = vertices.mean(axis=0)
    e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    x, y = (vertices - mean) @ e1, (vertices - mean) @ e2
    # x^2 + y^2 = 2 a x + 2 b y + c
    design = np.stack([2 * x, 2 * y, np.ones_like(x)], axis=1)
    (a, b, _), *_ = np.linalg.lstsq(design, x * x + y * y, rcond=None)
    return mean + a * e1 + b * e2
