"""What the images of a ``polarface ior`` capture determine themselves (docs/ior.md, "Refinement").

* :func:`refine_sphere`: the sphere's image is bounded by the cone of rays tangent to it, so its
  silhouette gives the direction of the centre and the angular radius ``alpha`` (``sin alpha = r / D``)
  in the camera's frame (the supplied angular radius is kept unless the silhouette's differs by more
  than :data:`RADIUS_TOLERANCE_PX`). The supplied radius ``r`` fixes the distance ``D``; the normals
  at every pixel (hence the exit zenith and the ratio the estimator fits) do not depend on that scale.
  A sphere centre off by half a millimetre, or a principal point off by a pixel, is thus corrected from
  the image; a focal-length error of 0.2 % changes the image radius by far less than a pixel and is
  left (docs/ior.md, table).
* :func:`check_lights`: the subsurface shading ``2 I90`` of the sphere is predicted from the supplied
  light positions (one albedo per channel, equal LED intensities); each light's gain is refitted alone
  against the others', and a light whose gain departs from 1 beyond a tolerance is flagged as
  miscalibrated (moved, missing or of different intensity). The ratio that gives eta does not depend on
  the lights (module :mod:`polarface.inverse.ior`), so a flagged light warns about the rig, not about eta.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from scipy import ndimage, optimize

from polarface.inverse.ior_scene import SphereScene
from polarface.optics.image_formation import subsurface_entry_flux, subsurface_exit_stokes

__all__ = [
    "LightCheck",
    "SphereRefinement",
    "check_lights",
    "refine_sphere",
    "scene_warnings",
    "silhouette_edges",
]

#: The silhouette's angular radius replaces the supplied one when they differ by more than this many
#: pixels. 0: always, since eta is very sensitive to it (a 0.2 % focal-length error, 0.08 px at a 41 px
#: sphere, gives up to 0.018 at eta 2.3). On small spheres (radius < ~30 px) the edge points'
#: discretisation biases the fitted radius by up to 0.6 % (docs/ior.md, "Limits").
RADIUS_TOLERANCE_PX = 0.0


@dataclasses.dataclass(frozen=True)
class SphereRefinement:
    """The sphere fitted to its silhouette.

    Attributes:
        scene: the input scene with the refined ``centre`` (radius kept; mm, world frame).
        shift_px: distance (pixels) between the supplied and the refined sphere's projected centres.
        angular_radius_change: the silhouette's over the supplied ``sin alpha`` minus 1 (a depth, radius
            or focal-length disagreement; 0.002 is a 0.2 % focal-length error).
        edge_rms_px: RMS distance (pixels) of the silhouette edge points from the fitted cone.
        edge_points: edge points used. centre_std_px: one-sigma uncertainty of the projected centre.
    """

    scene: SphereScene
    shift_px: float
    angular_radius_change: float
    edge_rms_px: float
    edge_points: int
    centre_std_px: float


def silhouette_edges(brightness: np.ndarray, relative_threshold: float = 1e-3) -> np.ndarray:
    """``(M, 2)`` float64 pixel coordinates ``(x, y)`` (pixel centres at integers) of the sphere's
    silhouette edge: midpoints between 4-neighbours on either side of the largest connected region
    brighter than ``relative_threshold`` times the 99th percentile of the lit pixels (holes filled).
    ``brightness``: ``(H, W)`` float image (e.g. s0)."""
    lit = brightness[brightness > 0]
    if lit.size < 10:
        return np.zeros((0, 2))
    mask = brightness > relative_threshold * float(np.percentile(lit, 99))
    labels, count = ndimage.label(mask)
    if count == 0:
        return np.zeros((0, 2))
    sizes = ndimage.sum_labels(mask, labels, index=np.arange(1, count + 1))
    mask = ndimage.binary_fill_holes(labels == 1 + int(np.argmax(sizes)))
    rows, cols = np.nonzero(mask[:, :-1] != mask[:, 1:])
    horizontal = np.stack([cols + 0.5, rows], axis=1)
    rows, cols = np.nonzero(mask[:-1, :] != mask[1:, :])
    vertical = np.stack([cols, rows + 0.5], axis=1)
    return np.concatenate([horizontal, vertical]).astype(np.float64)


def _tangent_basis(direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.array([1.0, 0.0, 0.0]) if abs(direction[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    first = np.cross(direction, helper)
    first /= np.linalg.norm(first)
    return first, np.cross(direction, first)


def refine_sphere(scene: SphereScene, brightness: np.ndarray) -> SphereRefinement | None:
    """Fit the silhouette cone (robust least squares on the angle between each edge point's ray and
    the centre direction, minus ``alpha``) and move the sphere's centre to it; None with fewer than 20
    edge points. ``brightness``: ``(H, W)`` float image of the sphere (e.g. s0)."""
    edges = silhouette_edges(brightness)
    if len(edges) < 20:
        return None
    rotation, translation = scene.world_to_camera[:3, :3], scene.world_to_camera[:3, 3]
    rays = np.concatenate([edges, np.ones((len(edges), 1))], axis=1) @ np.linalg.inv(scene.K).T
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    centre_cam = rotation @ scene.centre + translation
    distance = float(np.linalg.norm(centre_cam))
    direction0 = centre_cam / distance
    first, second = _tangent_basis(direction0)
    focal = float(np.sqrt(scene.K[0, 0] * scene.K[1, 1]))

    def direction_of(params: np.ndarray) -> np.ndarray:
        direction = direction0 + params[0] * first + params[1] * second
        return direction / np.linalg.norm(direction)

    def residual(params: np.ndarray) -> np.ndarray:
        direction = direction_of(params)
        angle = np.arctan2(np.linalg.norm(np.cross(rays, direction), axis=1), rays @ direction)
        return angle - params[2]

    start = np.array([0.0, 0.0, np.arcsin(min(scene.radius / distance, 1.0))])
    fit = optimize.least_squares(residual, start, loss="soft_l1", f_scale=0.5 / focal, x_scale=1.0 / focal)
    direction, alpha = direction_of(fit.x), float(fit.x[2])
    if abs(alpha - start[2]) * focal < RADIUS_TOLERANCE_PX:
        alpha = float(start[2])  # within the silhouette's discretisation: keep the supplied size
    refined_cam = direction * scene.radius / np.sin(alpha)
    refined = dataclasses.replace(scene, centre=rotation.T @ (refined_cam - translation))
    project = lambda p: (scene.K @ p)[:2] / p[2]  # noqa: E731
    angles = residual(fit.x) * focal
    jacobian = fit.jac
    scale2 = float(np.median(angles**2)) / focal**2 * 2.2  # robust residual variance (angle units)
    try:
        covariance = np.linalg.inv(jacobian.T @ jacobian) * scale2
        centre_std = float(np.sqrt(max(covariance[0, 0] + covariance[1, 1], 0.0)) * focal)
    except np.linalg.LinAlgError:
        centre_std = float("inf")
    return SphereRefinement(
        scene=refined,
        shift_px=float(np.linalg.norm(project(refined_cam) - project(centre_cam))),
        angular_radius_change=float(np.sin(fit.x[2]) * distance / scene.radius - 1.0),
        edge_rms_px=float(np.sqrt(np.mean(angles**2))),
        edge_points=len(edges),
        centre_std_px=centre_std,
    )


@dataclasses.dataclass(frozen=True)
class LightCheck:
    """Consistency of the sphere's shading with the supplied lights.

    Attributes:
        gains: ``(L,)`` each light's refitted gain relative to the others' (1 = consistent).
        shading_rms: RMS of the shading residual (all gains 1) relative to the mean shading.
        flagged: indices (into ``scene.lights``) of the lights whose gain departs from 1 by more than
            the tolerance.
    """

    gains: tuple[float, ...]
    shading_rms: float
    flagged: tuple[int, ...]


def check_lights(
    scene: SphereScene,
    shading: np.ndarray,
    normal: np.ndarray,
    position: np.ndarray,
    eta: float,
    tolerance: float = 0.15,
) -> LightCheck | None:
    """Refit each light's gain against the shading (module docstring); None without two lights.

    Args:
        scene: the (refined) scene. shading: ``(N,)`` observed subsurface ``2 I90`` at N sphere pixels.
        normal, position: ``(N, 3)`` world normals and positions (mm) of those pixels.
        eta: the estimated refractive index (exit and entry Fresnel transmission).
        tolerance: a light is flagged when ``|gain - 1| > tolerance``.
    """
    lights = np.asarray(scene.lights, dtype=np.float64)
    if len(lights) < 2 or len(shading) < 10:
        return None
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64))  # noqa: E731
    rotation, translation = scene.world_to_camera[:3, :3], scene.world_to_camera[:3, 3]
    up, centre = t(-scene.world_to_camera[1, :3]), t(-rotation.T @ translation)
    n, p, e = t(normal), t(position), torch.tensor([eta], dtype=torch.float64)
    exit_stokes = subsurface_exit_stokes(n, p, centre, up, e)[..., 0, :]  # (N, 4)
    exit_factor = (exit_stokes[:, 0] - exit_stokes[:, 1]).numpy()
    ones = torch.ones(1, 1, dtype=torch.float64)
    basis = np.stack(
        [
            subsurface_entry_flux(n, p, up, t(light[None]), ones, e)[:, 0].numpy() * exit_factor
            for light in lights
        ],
        axis=1,
    )  # (N, L)
    total = basis.sum(axis=1)
    albedo = float(total @ shading) / max(float(total @ total), 1e-300)
    shading_rms = float(np.sqrt(np.mean((shading - albedo * total) ** 2)) / max(np.mean(shading), 1e-300))
    gains = []
    for index in range(len(lights)):
        design = np.stack([total - basis[:, index], basis[:, index]], axis=1)
        (others, alone), *_ = np.linalg.lstsq(design, shading, rcond=None)
        gains.append(float(alone / others) if others > 0 else float("inf"))
    flagged = tuple(i for i, gain in enumerate(gains) if not abs(gain - 1.0) <= tolerance)
    return LightCheck(tuple(gains), shading_rms, flagged)


def scene_warnings(
    refinement: SphereRefinement | None, refine: bool, lights: LightCheck | None
) -> list[str]:
    """One line per disagreement between scene.json and the images (docs/ior.md, "Checks")."""
    warnings = []
    if refine and refinement is None:
        warnings.append("no sphere silhouette found: the supplied sphere centre is used unrefined")
    if refinement is not None:
        if refinement.shift_px > max(1.0, 3.0 * refinement.centre_std_px):
            warnings.append(
                f"the sphere's silhouette lies {refinement.shift_px:.2f} px from where scene.json's camera "
                "and sphere.center put it (camera pose/principal point or sphere centre miscalibrated; "
                "the centre was refined from the image)"
            )
        if abs(refinement.angular_radius_change) > 0.01:
            warnings.append(
                f"the silhouette's angular size differs by {100 * refinement.angular_radius_change:+.1f} % "
                "from sphere.radius at its distance (focal length, radius or depth miscalibrated; the "
                "normals follow the silhouette)"
            )
        if refinement.edge_rms_px > 1.0:
            warnings.append(
                f"the silhouette is not a sphere's under camera.K (edge rms "
                f"{refinement.edge_rms_px:.2f} px): check the intrinsics, distortion and the background"
            )
    if lights is not None and lights.flagged:
        listed = ", ".join(f"lights[{i}] (gain {lights.gains[i]:.2f})" for i in lights.flagged)
        warnings.append(
            f"the shading disagrees with {listed}: position or intensity miscalibrated "
            "(eta does not depend on the lights)"
        )
    return warnings
