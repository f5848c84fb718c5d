"""Analytic demo scene: the rig's ring of polarized LEDs and a ray-traced sphere, seen by a
:class:`polarface.geometry.camera.PinholeCamera`.

Frames (``docs/conventions.md``): world coordinates in mm; the camera follows OpenCV (x right, y down,
z forward); :meth:`PinholeCamera.centred` puts it at the world origin looking along +z, so its up
vector is world -y. The LED modules sit on a circle of radius ``ring_radius_mm`` around the lens in the image
plane; at the default 100 mm radius and 1000 mm subject distance they are atan(0.1) = 5.71 deg off axis
(the paper's "5.72 deg").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from polarface._validation import check_finite
from polarface.geometry.camera import PinholeCamera

__all__ = ["SphereGeometry", "ring_light_positions", "trace_sphere"]


def ring_light_positions(
    camera: PinholeCamera,
    ring_radius_mm: float = 100.0,
    count: int = 8,
    phase_rad: float = math.pi / 8,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """``(count, 3)`` positions (mm) of LED modules on a circle around the lens, in the image plane.

    Module ``k`` sits at angle ``phase_rad + 2 pi k / count`` from the camera x axis towards camera up.
    """
    if count < 1:
        raise ValueError(f"argument 'count' must be >= 1; got {count}")
    if not ring_radius_mm >= 0:
        raise ValueError(f"argument 'ring_radius_mm' must be >= 0; got {ring_radius_mm}")
    angles = phase_rad + 2 * math.pi * torch.arange(count, dtype=dtype) / count
    rotation = camera.rotation_tensor(dtype)
    right, up = rotation[:, 0], -rotation[:, 1]
    offsets = ring_radius_mm * (torch.cos(angles)[:, None] * right + torch.sin(angles)[:, None] * up)
    return camera.center_tensor(dtype) + offsets


@dataclass(frozen=True)
class SphereGeometry:
    """Per-pixel surface geometry of a ray-traced sphere.

    Attributes:
        mask: ``(H, W)`` bool, True where the ray hits the sphere.
        position: ``(H, W, 3)`` hit points in world mm (the sphere centre where masked out).
        normal: ``(H, W, 3)`` unit outward normals (camera-facing ``-ray`` where masked out).
    """

    mask: torch.Tensor
    position: torch.Tensor
    normal: torch.Tensor


def trace_sphere(
    camera: PinholeCamera,
    center_mm: tuple[float, float, float] = (0.0, 0.0, 1000.0),
    radius_mm: float = 80.0,
    dtype: torch.dtype = torch.float32,
) -> SphereGeometry:
    """Analytic ray-sphere intersection for every pixel (nearest hit in front of the camera).

    Solves ``|o + t d - c|^2 = r^2`` for the smallest positive ``t`` (vectorised over pixels).
    """
    if not radius_mm > 0:
        raise ValueError(f"argument 'radius_mm' must be > 0; got {radius_mm}")
    center = torch.tensor(center_mm, dtype=dtype)
    check_finite(center, "center_mm")
    origin = camera.center_tensor(dtype)
    directions = camera.ray_directions_tensor(dtype)
    offset = origin - center
    b = (directions * offset).sum(-1)
    c = (offset * offset).sum() - radius_mm**2
    discriminant = b * b - c
    hit = discriminant > 0
    root = torch.sqrt(discriminant.clamp_min(0.0))
    t_near = -b - root
    t_far = -b + root
    t = torch.where(t_near > 0, t_near, t_far)
    mask = hit & (t > 0)
    t = torch.where(mask, t, torch.zeros_like(t))
    position = origin + t[..., None] * directions
    normal = (position - center) / radius_mm
    normal = normal / torch.linalg.vector_norm(normal, dim=-1, keepdim=True).clamp_min(1e-12)
    position = torch.where(mask[..., None], position, center.expand_as(position))
    normal = torch.where(mask[..., None], normal, -directions)
    return SphereGeometry(mask=mask, position=position, normal=normal)
