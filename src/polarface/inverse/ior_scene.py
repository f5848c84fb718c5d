"""The geometry of a ``polarface ior`` capture: ``scene.json`` (docs/ior.md, "scene.json").

A single view of a sphere: the camera (intrinsics ``K``, OpenCV ``world_to_camera``, image size), the
sphere (centre and radius, mm), the LED positions (mm; the lights are polarized along the camera x axis)
and, optionally, the camera's measured analyzers (``"polarizer": {"extinction_ratio": ER,
"analyzer_angles_deg": [a0, a45, a90, a135]}``, ideal when absent;
:class:`polarface.optics.analyzer.AnalyzerModel`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from polarface.optics.analyzer import AnalyzerModel

__all__ = ["SphereScene", "sphere_pixels"]


@dataclasses.dataclass(frozen=True)
class SphereScene:
    """Single-view sphere capture geometry (mm, OpenCV camera).

    Attributes:
        K: ``(3, 3)`` intrinsics; world_to_camera: ``(4, 4)``; width, height: image size in pixels;
        centre: ``(3,)`` sphere centre; radius: sphere radius (mm); lights: ``(L, 3)`` positions (not used
        by the ratio; used by the shading check of :func:`polarface.inverse.ior_refine.check_lights`);
        polarizer: the camera's analyzers (ideal by default).
    """

    K: np.ndarray
    world_to_camera: np.ndarray
    width: int
    height: int
    centre: np.ndarray
    radius: float
    lights: np.ndarray
    polarizer: AnalyzerModel = dataclasses.field(default_factory=AnalyzerModel)

    @classmethod
    def from_dict(cls, payload: dict[str, Any]) -> SphereScene:
        """Parse the ``scene.json`` layout of ``polarface ior`` (ValueError naming the field)."""
        if payload.get("units", "mm") != "mm":
            raise ValueError(f"scene: units must be 'mm'; got {payload.get('units')!r}")
        K, pose = _field(payload, "camera.K"), _field(payload, "camera.world_to_camera")
        width, height = _field(payload, "camera.width", int), _field(payload, "camera.height", int)
        centre, radius = _field(payload, "sphere.center"), _field(payload, "sphere.radius", float)
        lights = _field(payload, "lights", _positions) if "lights" in payload else np.zeros((0, 3))
        if K.shape != (3, 3) or pose.shape != (4, 4) or centre.shape != (3,):
            raise ValueError("scene: camera.K must be 3x3, camera.world_to_camera 4x4, sphere.center 3-D")
        if not (np.isfinite(K).all() and np.isfinite(pose).all() and np.isfinite(centre).all()):
            raise ValueError("scene: NaN/inf in the camera or sphere")
        if not (radius > 0 and math.isfinite(radius)) or width < 1 or height < 1:
            raise ValueError(
                f"scene: need sphere.radius > 0 and a positive image size; got {radius}, {width}x{height}"
            )
        if lights.size and not np.isfinite(lights).all():
            raise ValueError("scene: lights[].position contains NaN/inf")
        try:
            polarizer = AnalyzerModel.from_dict(payload.get("polarizer"), name="polarizer")
        except ValueError as exc:
            raise ValueError(f"scene: {exc}") from None
        scene = cls(K, pose, width, height, centre, radius, lights, polarizer)
        scene.check_geometry()
        return scene

    def check_geometry(self) -> None:
        """ValueError naming the field unless K has positive focal lengths, zero skew row ``[0, 0, 1]``
        and the principal point inside the image, ``world_to_camera`` is rigid (orthonormal to 1e-6,
        det +1, last row ``[0, 0, 0, 1]``) and the sphere lies wholly in front of the camera."""
        K, pose = self.K, self.world_to_camera
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise ValueError(f"scene: camera.K focal lengths must be > 0; got {K[0, 0]}, {K[1, 1]}")
        if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0:
            raise ValueError(
                f"scene: camera.K must be upper triangular with last row [0, 0, 1]; got {K.tolist()}"
            )
        if not (0 <= K[0, 2] <= self.width and 0 <= K[1, 2] <= self.height):
            raise ValueError(
                f"scene: camera.K principal point ({K[0, 2]}, {K[1, 2]}) lies outside the "
                f"{self.width}x{self.height} image"
            )
        rotation = pose[:3, :3]
        if not np.allclose(pose[3], [0, 0, 0, 1]) or not np.allclose(
            rotation @ rotation.T, np.eye(3), atol=1e-6
        ):
            raise ValueError(
                "scene: camera.world_to_camera must be rigid "
                "(orthonormal rotation to 1e-6, last row [0, 0, 0, 1])"
            )
        if np.linalg.det(rotation) < 0:
            raise ValueError("scene: camera.world_to_camera rotation must be proper (det +1)")
        depth = float((rotation @ self.centre + pose[:3, 3])[2])
        if depth <= self.radius:
            raise ValueError(
                f"scene: the sphere (sphere.center depth {depth:.6g} mm, radius {self.radius:.6g} mm) "
                "must lie in front of the camera"
            )


def _positions(lights: Any) -> np.ndarray:
    """``(L, 3)`` positions of a ``lights`` list of ``{"position": [x, y, z]}`` objects."""
    if not isinstance(lights, list):
        raise TypeError("must be a list of objects with a 'position'")
    return np.asarray([light["position"] for light in lights], dtype=np.float64).reshape(len(lights), 3)


def _field(payload: dict, name: str, convert: Callable | None = None):
    """The scene field at the dotted ``name``, converted; ValueError naming the field otherwise."""
    try:
        value = functools.reduce(lambda node, key: node[key], name.split("."), payload)
        return np.asarray(value, dtype=np.float64) if convert is None else convert(value)
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise ValueError(f"scene: missing or malformed field '{name}' ({exc})") from None


def sphere_pixels(scene: SphereScene) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel of the sphere: ``mask (H, W)``, world ``position (H, W, 3)``, ``normal (H, W, 3)``,
    camera centre ``(3,)`` (ray-sphere intersection of each pixel centre)."""
    rotation, translation = scene.world_to_camera[:3, :3], scene.world_to_camera[:3, 3]
    centre_cam = -rotation.T @ translation
    y, x = np.mgrid[0 : scene.height, 0 : scene.width].astype(np.float64)
    pixels = np.stack([x, y, np.ones_like(x)], axis=-1)
    rays_cam = pixels @ np.linalg.inv(scene.K).T
    rays = rays_cam @ rotation  # camera -> world: R^T d
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    oc = centre_cam - scene.centre
    b = rays @ oc
    c = float(oc @ oc) - scene.radius**2
    disc = b * b - c
    mask = disc > 0
    t = -b - np.sqrt(np.where(mask, disc, 0.0))
    mask &= t > 0
    position = centre_cam + t[..., None] * rays
    normal = (position - scene.centre) / scene.radius
    return mask, position, normal, centre_cam


