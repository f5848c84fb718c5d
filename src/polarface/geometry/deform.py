"""Procedural smooth expression deformations of the head for the dynamic sequence.

Each expression is a displacement field ``D_e(p)`` (mm) on the vertices of the rest mesh, built from
smooth compactly supported falloff regions centred on landmarks of the asset (picked by vertex position,
:func:`polarface.geometry.head_asset.pick_landmark`). A frame with weights ``w_e`` (one per expression,
in [0, 1]) has vertices ``p + sum_e w_e D_e(p)`` (linear blend shapes); faces and UVs never change, so
the UV raster's face ids and barycentrics stay valid (:func:`polarface.geometry.uv_raster.reposition`).

Falloff: ``f(d) = (1 - (d / r)^2)^3`` for distance ``d < r``, else 0 (C2-smooth at the border, a
Wendland-style bump). Regions (defaults, :class:`ExpressionConfig`):

* ``brow_raise``: both brows move up by ``brow_lift`` mm (regions of radius ``brow_radius``).
* ``smile``: the mouth corners move outwards, up and slightly back; the cheeks rise.
* ``jaw_open``: the jaw rotates by ``jaw_angle`` about a horizontal (x) axis through the jaw hinge,
  weighted by a smooth step in y below the mouth line and a smooth step in z in front of the hinge
  (the neck and back of the head stay still).

Validity: a blend is accepted only if no triangle flips (its normal turning by more than 90 degrees from
the rest mesh) -- :func:`flipped_faces`; the defaults are tested on the bundled head over [0, 1]^3.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from polarface.geometry.mesh import TriangleMesh, face_normals

__all__ = [
    "EXPRESSIONS",
    "ExpressionConfig",
    "ExpressionRig",
    "dynamic_sequence_weights",
    "flipped_faces",
    "smooth_falloff",
]

#: Expression names, in the order of the weight vectors.
EXPRESSIONS = ("brow_raise", "smile", "jaw_open")


def smooth_falloff(distance: np.ndarray, radius: float) -> np.ndarray:
    """``(1 - (d/r)^2)^3`` inside ``d < r``, 0 outside; ``distance`` in mm, ``radius`` > 0 mm."""
    if not radius > 0:
        raise ValueError(f"argument 'radius' must be > 0 mm; got {radius}")
    s2 = np.clip((np.asarray(distance, dtype=np.float64) / radius) ** 2, 0.0, 1.0)
    return (1.0 - s2) ** 3


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


@dataclasses.dataclass(frozen=True)
class ExpressionConfig:
    """Amplitudes and regions of the procedural expressions (mm, radians).

    The landmarks come from the head asset; ``jaw_hinge`` is a point on the jaw's rotation axis in the
    model frame of :func:`~polarface.geometry.head_asset.load_head_asset` (below and in front of the ears).
    """

    brow_lift: float = 6.0
    brow_radius: float = 32.0
    smile_corner: tuple[float, float, float] = (5.0, 5.0, -3.0)
    smile_radius: float = 26.0
    cheek_lift: tuple[float, float, float] = (0.0, 3.0, 2.0)
    cheek_radius: float = 24.0
    jaw_angle: float = math.radians(10.0)
    jaw_hinge: tuple[float, float, float] = (0.0, -20.0, 5.0)
    jaw_band: float = 14.0
    jaw_depth_band: float = 30.0
    jaw_neck_band: float = 30.0


class ExpressionRig:
    """Displacement fields ``(E, N, 3)`` (mm) of :data:`EXPRESSIONS` on a rest mesh.

    Args:
        mesh: the rest mesh (model frame, mm).
        landmarks: name -> vertex index; needs ``brow_left/right``, ``mouth_left/right``,
            ``mouth_center``, ``cheek_left/right`` (as :attr:`HeadAsset.landmarks`).
        config: amplitudes and radii.
    """

    def __init__(
        self, mesh: TriangleMesh, landmarks: dict[str, int], config: ExpressionConfig | None = None
    ) -> None:
        required = (
            "brow_left",
            "brow_right",
            "mouth_left",
            "mouth_right",
            "mouth_center",
            "cheek_left",
            "cheek_right",
        )
        missing = [name for name in required if name not in landmarks]
        if missing:
            raise ValueError(f"argument 'landmarks' lacks {missing}")
        self.mesh = mesh
        self.config = config or ExpressionConfig()
        points = mesh.vertices
        at = {name: points[index] for name, index in landmarks.items()}
        cfg = self.config

        def bump(centre: np.ndarray, radius: float) -> np.ndarray:
            return smooth_falloff(np.linalg.norm(points - centre, axis=1), radius)[:, None]

        brow = np.zeros_like(points)
        for side in ("brow_left", "brow_right"):
            brow += bump(at[side], cfg.brow_radius) * np.array([0.0, cfg.brow_lift, 0.0])

        smile = np.zeros_like(points)
        for side, sign in (("left", 1.0), ("right", -1.0)):
            corner = np.array(cfg.smile_corner) * np.array([sign, 1.0, 1.0])
            smile += bump(at[f"mouth_{side}"], cfg.smile_radius) * corner
            cheek = np.array(cfg.cheek_lift) * np.array([sign, 1.0, 1.0])
            smile += bump(at[f"cheek_{side}"], cfg.cheek_radius) * cheek

        hinge = np.array(cfg.jaw_hinge, dtype=np.float64)
        mouth_y = at["mouth_center"][1]
        below = _smoothstep((mouth_y + 0.25 * cfg.jaw_band - points[:, 1]) / cfg.jaw_band)
        in_front = _smoothstep((points[:, 2] - (hinge[2] - cfg.jaw_depth_band)) / cfg.jaw_depth_band)
        chin_y = at["chin"][1] if "chin" in at else mouth_y - 45.0
        above_neck = _smoothstep((points[:, 1] - (chin_y - cfg.jaw_neck_band)) / cfg.jaw_neck_band)
        weight = (below * in_front * above_neck)[:, None]
        cos_a, sin_a = math.cos(cfg.jaw_angle), math.sin(cfg.jaw_angle)
        # rotation about +x by +angle moves the chin (in front of and below the hinge) down and back
        rotation = np.array([[1.0, 0.0, 0.0], [0.0, cos_a, -sin_a], [0.0, sin_a, cos_a]])
        rel = points - hinge
        jaw = weight * (rel @ rotation.T - rel)

        self.fields = np.stack([brow, smile, jaw]).astype(np.float64)  # (E, N, 3)
        self._rest_normals = face_normals(mesh.vertices, mesh.faces)

    def vertices(self, weights: np.ndarray) -> np.ndarray:
        """Deformed positions ``(N, 3)`` mm for expression weights ``(E,)`` (each in [0, 1] nominally)."""
        weights = np.asarray(weights, dtype=np.float64).reshape(-1)
        if weights.shape != (len(EXPRESSIONS),) or not np.isfinite(weights).all():
            raise ValueError(f"argument 'weights' must be {len(EXPRESSIONS)} finite values {EXPRESSIONS}")
        return self.mesh.vertices + np.einsum("e,enc->nc", weights, self.fields)

    def deform(self, weights: np.ndarray, *, check: bool = True) -> TriangleMesh:
        """The deformed mesh (same faces and UVs, recomputed normals).

        Raises:
            ValueError: if ``check`` and the blend flips a triangle (see :func:`flipped_faces`).
        """
        vertices = self.vertices(weights)
        if check:
            flipped = flipped_faces(self.mesh.vertices, vertices, self.mesh.faces)
            if flipped.any():
                raise ValueError(
                    f"expression weights {np.asarray(weights).tolist()} flip {int(flipped.sum())} triangles"
                )
        return self.mesh.with_vertices(vertices)


def flipped_faces(rest_vertices: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(F,)`` bool: triangles whose normal turned by more than 90 degrees (or collapsed to zero area)."""
    rest = face_normals(np.asarray(rest_vertices, dtype=np.float64), faces)
    new_corners = np.asarray(vertices, dtype=np.float64)[faces]
    cross = np.cross(new_corners[:, 1] - new_corners[:, 0], new_corners[:, 2] - new_corners[:, 0])
    rest_ok = np.linalg.norm(rest, axis=1) > 0
    return rest_ok & (np.einsum("fc,fc->f", rest, cross) <= 0)


def dynamic_sequence_weights(frame_count: int) -> np.ndarray:
    """Expression weights ``(M, 3)`` for a dynamic sequence of ``frame_count`` frames (order
    :data:`EXPRESSIONS`): a brow raise, then a smile, then a jaw opening, each a smooth ``sin^2`` pulse
    over an overlapping third of the sequence, starting and ending neutral (all weights in [0, 1])."""
    if int(frame_count) < 1:
        raise ValueError(f"argument 'frame_count' must be >= 1; got {frame_count}")
    count = int(frame_count)
    phase = np.arange(count) / max(count - 1, 1)
    weights = np.zeros((count, len(EXPRESSIONS)))
    starts = (0.0, 0.3, 0.6)
    width = 0.4
    for e, start in enumerate(starts):
        local = (phase - start) / width
        inside = (local >= 0) & (local <= 1)
        weights[inside, e] = np.sin(np.pi * local[inside]) ** 2
    return weights
