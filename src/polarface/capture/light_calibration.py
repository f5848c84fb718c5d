"""LED module positions from a mirror sphere seen by calibrated cameras (``polarface calibrate-rig``,
its ``lights`` step; docs/calibration.md).

A chrome sphere of known radius is placed at a few positions in front of the rig. At each position every
calibrated camera takes two frames: one under the room light, where the sphere is a bright disc (its
silhouette), and one with the LEDs on and the room dark, where each LED module is a small highlight.

* The silhouette of a sphere is the section of a cone tangent to it from the camera centre: the
  back-projected edge points ``v_i`` (unit rays) satisfy ``a . v_i = cos(alpha)`` for the cone's axis
  ``a`` and half angle ``alpha`` (:func:`silhouette_cone`, linear least squares). The sphere's centre lies
  on the axis at ``r / sin(alpha)``; the cones of all cameras give the first estimate of the centre
  (:func:`sphere_centre`).
* A highlight is where the sphere's normal bisects the directions to the camera and to the LED
  (:func:`specular_points`). Each highlight's reflected ray passes through its LED module; the rays of
  every camera and every sphere position give the first estimate of each module
  (:func:`reflected_rays`, :func:`nearest_point`).
* A bundle adjustment (:func:`adjust_lights`) then moves the sphere centres and the modules together to
  minimise, in pixels, the distance between each detected highlight and the projection of the specular
  point the model predicts, and between each silhouette cone and the cone the centre predicts. The
  highlights constrain the centres far better than the silhouettes do (a centre off by ``d`` turns the
  reflected rays by ``2 d / r``), so neither alone is enough.

Units: mm, world frame of the rig; pixels of the recorded (distorted) images.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import contourpy
import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares

from polarface.geometry.camera import PinholeCamera

__all__ = [
    "HighlightObservation",
    "HighlightSpot",
    "LightCalibration",
    "SilhouetteObservation",
    "adjust_lights",
    "highlight_spots",
    "nearest_point",
    "reflected_rays",
    "silhouette_cone",
    "silhouette_edge",
    "specular_points",
    "sphere_centre",
]


@dataclasses.dataclass(frozen=True)
class SilhouetteObservation:
    """The silhouette cone of the sphere at position ``position`` in one camera.

    Attributes:
        position: index of the sphere position; camera: the camera.
        axis: ``(3,)`` unit world direction of the cone's axis; half_angle: its half angle (radians).
        rms_px: RMS distance of the edge points from the fitted cone, pixels.
    """

    position: int
    camera: PinholeCamera
    axis: np.ndarray
    half_angle: float
    rms_px: float


@dataclasses.dataclass(frozen=True)
class HighlightObservation:
    """One LED module's highlight on the sphere at ``position`` in one camera.

    Attributes:
        position: index of the sphere position; light: index of the LED module; camera: the camera.
        pixel: ``(2,)`` recorded (distorted) pixel of the highlight's centroid.
    """

    position: int
    light: int
    camera: PinholeCamera
    pixel: np.ndarray


@dataclasses.dataclass(frozen=True)
class LightCalibration:
    """Result of :func:`adjust_lights`.

    Attributes:
        positions_mm: ``(K, 3)`` LED module positions, world mm.
        positions_std_mm: ``(K, 3)`` their one-sigma uncertainties (from the adjustment's covariance,
            scaled by the residuals).
        sphere_centres_mm: ``(P, 3)`` the sphere's centre at each position.
        highlight_rms_px: RMS highlight residual, pixels; silhouette_rms_px: RMS silhouette residual.
        highlights: highlights used per module ``(K,)``.
    """

    positions_mm: np.ndarray
    positions_std_mm: np.ndarray
    sphere_centres_mm: np.ndarray
    highlight_rms_px: float
    silhouette_rms_px: float
    highlights: np.ndarray


@dataclasses.dataclass(frozen=True)
class HighlightSpot:
    """A bright spot of an LED frame: ``pixel`` ``(2,)`` its intensity-weighted centroid (u, v), ``peak``
    its brightest value, ``saturated`` whether a pixel of it was at the white level."""

    pixel: np.ndarray
    peak: float
    saturated: bool


def silhouette_edge(image: np.ndarray) -> np.ndarray:
    """``(N, 2)`` sub-pixel points (u, v) of the longest closed iso-line of ``image`` ``(H, W)`` at half
    way between the dark room (its median) and the disc (its 99.5th percentile): the sphere's edge.

    Raises:
        ValueError: no closed edge (no disc in the image, or one cut by the image border).
    """
    image = np.asarray(image, dtype=np.float64)
    dark, bright = float(np.median(image)), float(np.percentile(image, 99.5))
    if not bright > 2.0 * max(dark, 1e-12):
        raise ValueError("no bright disc: the sphere is not in the image")
    lines = contourpy.contour_generator(z=image, line_type="Separate").lines(0.5 * (dark + bright))
    closed = [line for line in lines if len(line) > 8 and np.allclose(line[0], line[-1])]
    if not closed:
        raise ValueError("the sphere's edge is not a closed curve in the image (cut by the border?)")
    return np.asarray(max(closed, key=len)[:-1], dtype=np.float64)


def highlight_spots(image: np.ndarray, saturated: np.ndarray | None = None, threshold: float = 0.05,
                    window: int = 3) -> list[HighlightSpot]:
    """The bright spots of an LED frame ``image`` ``(H, W)``: connected regions above ``threshold`` of its
    maximum, each with its centroid over the ``(2 window + 1)^2`` pixels around its peak (the median of
    the frame subtracted) and whether a pixel of it is ``saturated`` (``(H, W)`` bool)."""
    image = np.asarray(image, dtype=np.float64)
    peak_value = float(image.max())
    if peak_value <= 0:
        return []
    labels, _ = ndimage.label(image > threshold * peak_value)
    background = float(np.median(image))
    spots = []
    for index, region in enumerate(ndimage.find_objects(labels), start=1):
        inside = labels[region] == index
        values = np.where(inside, image[region], -np.inf)
        row, col = np.unravel_index(int(np.argmax(values)), values.shape)
        row, col = row + region[0].start, col + region[1].start
        rows = slice(max(row - window, 0), min(row + window + 1, image.shape[0]))
        cols = slice(max(col - window, 0), min(col + window + 1, image.shape[1]))
        weights = np.clip(image[rows, cols] - background, 0.0, None)
        v, u = np.mgrid[rows, cols]
        total = float(weights.sum())
        pixel = np.array([float((weights * u).sum() / total), float((weights * v).sum() / total)])
        hit = bool(saturated[region][inside].any()) if saturated is not None else False
        spots.append(HighlightSpot(pixel, float(image[row, col]), hit))
    return spots


def silhouette_cone(camera: PinholeCamera, edge_px: np.ndarray) -> tuple[np.ndarray, float, float]:
    """The cone through the back-projected silhouette edge ``edge_px`` ``(N, 2)`` (recorded pixels):
    ``(axis (3,) unit world, half angle (radians), RMS residual (pixels))``.

    Raises:
        ValueError: fewer than 5 edge points, or edge points that no cone fits (collinear).
    """
    edge = np.asarray(edge_px, dtype=np.float64)
    if edge.ndim != 2 or edge.shape[1] != 2 or len(edge) < 5:
        raise ValueError(f"argument 'edge_px' must be (N >= 5, 2) pixels; got {edge.shape}")
    _, rays = camera.pixel_rays(edge)
    w, *_ = np.linalg.lstsq(rays, np.ones(len(rays)), rcond=None)  # w . v_i = 1, w = a / cos(alpha)
    norm = float(np.linalg.norm(w))
    if not np.isfinite(norm) or norm <= 1.0:
        raise ValueError("the silhouette edge fits no cone (points collinear or spread over a hemisphere)")
    axis = w / norm
    half_angle = float(np.arccos(1.0 / norm))
    angles = np.arccos(np.clip(rays @ axis, -1.0, 1.0)) - half_angle
    return axis, half_angle, float(np.sqrt(np.mean(angles**2)) * camera.K[0, 0])


def sphere_centre(observations: Sequence[SilhouetteObservation], radius_mm: float) -> np.ndarray:
    """``(3,)`` least-squares centre of a sphere of ``radius_mm`` from its silhouette cones in several
    cameras: the point nearest to every cone's centre estimate ``C + a r / sin(alpha)`` along its axis
    and to the axes themselves (the axes fix it sideways, the half angles along them)."""
    points = [o.camera.center + o.axis * radius_mm / np.sin(o.half_angle) for o in observations]
    if len(observations) == 1:
        return points[0]
    origins = np.stack([o.camera.center for o in observations])
    directions = np.stack([o.axis for o in observations])
    sideways = nearest_point(origins, directions)
    along = np.mean([o.axis @ (p - sideways) for o, p in zip(observations, points, strict=True)])
    return sideways + along * np.mean(directions, axis=0) / np.linalg.norm(np.mean(directions, axis=0))


def nearest_point(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """``(3,)`` point nearest (least squares) to the lines ``origins + t directions`` (``(N, 3)`` each;
    unit directions)."""
    origins = np.asarray(origins, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    projectors = np.eye(3)[None] - directions[:, :, None] * directions[:, None, :]
    return np.linalg.solve(projectors.sum(axis=0), np.einsum("nij,nj->i", projectors, origins))


def specular_points(centres: np.ndarray, radius_mm: float, eyes: np.ndarray, lights: np.ndarray,
                    iterations: int = 30) -> np.ndarray:
    """``(N, 3)`` points of spheres (``centres`` ``(N, 3)``, radius ``radius_mm``) where the normal bisects
    the directions to ``eyes`` and to ``lights`` (``(N, 3)`` each): the highlight a camera at ``eyes``
    sees of a point light at ``lights`` (fixed-point iteration from the bisector at the centre; both
    farther than a few radii)."""
    centres, eyes, lights = (np.asarray(a, dtype=np.float64) for a in (centres, eyes, lights))

    def unit(v: np.ndarray) -> np.ndarray:
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    normal = unit(unit(eyes - centres) + unit(lights - centres))
    for _ in range(int(iterations)):
        point = centres + radius_mm * normal
        normal = unit(unit(eyes - point) + unit(lights - point))
    return centres + radius_mm * normal


def reflected_rays(camera: PinholeCamera, pixels: np.ndarray, centre: np.ndarray,
                   radius_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rays of recorded ``pixels`` ``(N, 2)`` mirrored by the sphere (``centre``, ``radius_mm``):
    ``(points on the sphere (N, 3), unit reflected directions (N, 3), hit (N,) bool)``."""
    origins, directions = camera.pixel_rays(np.asarray(pixels, dtype=np.float64))
    offset = origins - centre
    b = np.einsum("ij,ij->i", directions, offset)
    disc = b**2 - (np.einsum("ij,ij->i", offset, offset) - radius_mm**2)
    hit = disc > 0
    t = -b - np.sqrt(np.where(hit, disc, 0.0))
    points = origins + t[:, None] * directions
    normals = (points - centre) / radius_mm
    reflected = directions - 2.0 * np.einsum("ij,ij->i", directions, normals)[:, None] * normals
    return points, reflected, hit


def adjust_lights(
    highlights: Sequence[HighlightObservation],
    silhouettes: Sequence[SilhouetteObservation],
    radius_mm: float,
    lights_mm: np.ndarray,
    centres_mm: np.ndarray,
) -> LightCalibration:
    """Bundle adjustment of the LED modules and the sphere centres (module docstring), from starting
    ``lights_mm`` ``(K, 3)`` and ``centres_mm`` ``(P, 3)``; residuals in pixels, Huber-robust at 1 px.

    Raises:
        ValueError: a module or a sphere position that no highlight sees.
    """
    lights0 = np.asarray(lights_mm, dtype=np.float64)
    centres0 = np.asarray(centres_mm, dtype=np.float64)
    count_k, count_p = len(lights0), len(centres0)
    position = np.array([h.position for h in highlights])
    light = np.array([h.light for h in highlights])
    seen = np.bincount(light, minlength=count_k)
    if (seen == 0).any() or (np.bincount(position, minlength=count_p) == 0).any():
        raise ValueError(f"every LED module and sphere position needs a highlight; modules without: "
                         f"{np.nonzero(seen == 0)[0].tolist()}")
    eyes = np.stack([h.camera.center for h in highlights])
    detected = np.stack([h.pixel for h in highlights])
    focal = np.array([h.camera.K[0, 0] for h in silhouettes])
    # the highlights of each camera, projected at once
    cameras: dict[int, tuple[PinholeCamera, list[int]]] = {}
    for index, h in enumerate(highlights):
        cameras.setdefault(id(h.camera), (h.camera, []))[1].append(index)

    def residuals(x: np.ndarray) -> np.ndarray:
        centres = x[: 3 * count_p].reshape(count_p, 3)
        lights = x[3 * count_p:].reshape(count_k, 3)
        points = specular_points(centres[position], radius_mm, eyes, lights[light])
        predicted = np.empty_like(detected)
        for camera, rows in cameras.values():
            predicted[rows] = camera.project(points[rows])[0]
        parts = [(predicted - detected).ravel()]
        for s, f in zip(silhouettes, focal, strict=True):
            offset = centres[s.position] - s.camera.center
            distance = np.linalg.norm(offset)
            axis = offset / distance
            parts.append(f * np.cross(axis, s.axis))  # the axes' angle, pixels
            parts.append([f * (np.arcsin(min(radius_mm / distance, 1.0)) - s.half_angle)])
        return np.concatenate([np.ravel(p) for p in parts])

    start = np.concatenate([centres0.ravel(), lights0.ravel()])
    solution = least_squares(residuals, start, loss="huber", f_scale=1.0, x_scale=1.0)
    final = residuals(solution.x)
    highlight_part = final[: 2 * len(highlights)]
    silhouette_part = final[2 * len(highlights):]
    dof = max(len(final) - len(start), 1)
    sigma2 = float(np.sum(final**2) / dof)
    try:
        covariance = np.linalg.inv(solution.jac.T @ solution.jac) * sigma2
        std = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    except np.linalg.LinAlgError:  # pragma: no cover - a rank-deficient adjustment
        std = np.full(len(start), np.nan)
    return LightCalibration(
        positions_mm=solution.x[3 * count_p:].reshape(count_k, 3),
        positions_std_mm=std[3 * count_p:].reshape(count_k, 3),
        sphere_centres_mm=solution.x[: 3 * count_p].reshape(count_p, 3),
        highlight_rms_px=float(np.sqrt(np.mean(highlight_part**2))),
        silhouette_rms_px=float(np.sqrt(np.mean(silhouette_part**2))) if silhouette_part.size else 0.0,
        highlights=seen,
    )
