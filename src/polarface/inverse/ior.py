"""Refractive index of a sphere from one near-coaxial polarization capture (paper Table
"Validation on refractive index measurements", Sec. 6).

The sphere's geometry gives every pixel's normal, hence its exit zenith ``theta_o`` and the azimuth
double angles ``(xi, zeta) = (cos 2phi, sin 2phi)`` of the normal in the camera's Stokes frame. Under
lights polarized along the camera x axis, the subsurface term leaves the surface with the Stokes
vector ``E/pi [T+, -T- xi, -T- zeta]`` (supplement Eq. p_sss; the entry polarization only scales
``E``), while the near-coaxial specular and single-scattering lobes stay in the ``[k, k, 0, 0]`` state.
Hence, with no specular in ``I90`` or ``I135 - I45``::

    r = (I135 - I45) / (2 I90) = psi zeta / (1 + psi xi),     psi = T-/T+ (eta, theta_o) (signed, <= 0)

a ratio of *signed* components (no upward noise bias of a DoP magnitude) that is independent
of albedo and illumination. :func:`estimate_ior` fits one eta to all usable pixels by robust
(Huber-weighted) least squares on ``r``: a dense scan over ``eta_range`` then golden-section refinement.
Pixels are used where ``theta_o`` lies in ``zenith_range`` (the DoP is informative and the sphere edge
is avoided), ``|zeta|`` is not small, and the co-polarized excess ``I0 - I90`` is small relative to
``2 I90`` (highlights removed). The exact forward model of :mod:`polarface.optics` is used for the
prediction (:func:`polarface.optics.subsurface_exit_stokes`), so the real camera and light positions
enter (the paper's "near-coaxial" geometry is not approximated).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from polarface.optics.image_formation import subsurface_exit_stokes

__all__ = ["IorResult", "SphereScene", "estimate_ior", "sphere_pixels"]


@dataclasses.dataclass(frozen=True)
class SphereScene:
    """Single-view sphere capture geometry (mm, OpenCV camera).

    Attributes:
        K: ``(3, 3)`` intrinsics; world_to_camera: ``(4, 4)``; width, height: image size in pixels;
        centre: ``(3,)`` sphere centre; radius: sphere radius (mm); lights: ``(L, 3)`` positions (unused by
        the ratio but kept for reports).
    """

    K: np.ndarray
    world_to_camera: np.ndarray
    width: int
    height: int
    centre: np.ndarray
    radius: float
    lights: np.ndarray

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
        scene = cls(K, pose, width, height, centre, radius, lights)
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


@dataclasses.dataclass(frozen=True)
class IorResult:
    """Estimated refractive index and diagnostics.

    Attributes:
        eta: estimate; rms_residual: RMS of the ratio residual at the estimate; pixels: pixels used;
        channels: per-channel estimates (when the input has several channels); at_bound: True when
        ``eta`` lies on a bound of the search interval (within 1e-5 of its width): the cost's minimum is
        at or beyond the bound, so ``eta`` is not a measurement.
    """

    eta: float
    rms_residual: float
    pixels: int
    channels: tuple[float, ...] = ()
    at_bound: bool = False


def _ratio_prediction(
    eta: torch.Tensor, normal: torch.Tensor, position: torch.Tensor, centre: torch.Tensor, up: torch.Tensor
) -> torch.Tensor:
    """``(E, N)`` predicted ``(I135 - I45) / (2 I90) = -s2 / (s0 - s1)`` for etas ``(E,)`` and N pixels."""
    exit_stokes = subsurface_exit_stokes(normal, position, centre, up, eta[None, :])  # (N, E, 4)
    s0, s1, s2 = exit_stokes[..., 0], exit_stokes[..., 1], exit_stokes[..., 2]
    return (-s2 / (s0 - s1)).T


def _check_inputs(
    intensities: dict[str, np.ndarray], scene: SphereScene, eta_range: tuple[float, float]
) -> list[np.ndarray]:
    """The four analyzer images ``I0, I45, I90, I135`` as float64 ``(H, W, C)`` arrays (ValueError on
    missing/mismatched/non-finite images or a bad ``eta_range``)."""
    names = ("I0", "I45", "I90", "I135")
    missing = [n for n in names if n not in intensities]
    if missing:
        raise ValueError(f"argument 'intensities' lacks {missing}")
    images = [np.asarray(intensities[n], dtype=np.float64) for n in names]
    images = [im[..., None] if im.ndim == 2 else im for im in images]
    shape = images[0].shape
    for name, image in zip(names, images, strict=True):
        if image.shape != shape or image.ndim != 3:
            raise ValueError(f"argument '{name}' must have shape {shape} (H, W[, C]); got {image.shape}")
        if not np.isfinite(image).all():
            raise ValueError(f"argument '{name}' contains NaN/inf values")
    if shape[:2] != (scene.height, scene.width):
        raise ValueError(
            f"images are {shape[1]}x{shape[0]} but the scene camera is {scene.width}x{scene.height}"
        )
    lo, hi = eta_range
    if not 1.0 < lo < hi:
        raise ValueError(f"argument 'eta_range' must satisfy 1 < lo < hi; got {eta_range}")
    return images


def _sphere_geometry(
    scene: SphereScene, zenith_range_deg: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``usable (H, W)`` bool (on the sphere, exit zenith in ``zenith_range_deg``), world ``position`` and
    ``normal`` ``(H, W, 3)``, camera centre ``(3,)`` and camera up ``(3,)`` (world frame, mm)."""
    mask, position, normal, centre = sphere_pixels(scene)
    to_camera = centre - position
    to_camera /= np.linalg.norm(to_camera, axis=-1, keepdims=True)
    cos_o = np.clip((normal * to_camera).sum(-1), -1, 1)
    zenith = np.degrees(np.arccos(cos_o))
    usable = mask & (zenith >= zenith_range_deg[0]) & (zenith <= zenith_range_deg[1])
    up = -scene.world_to_camera[1, :3]  # camera up = -y axis of the camera, in world coordinates
    return usable, position, normal, centre, up


def _channel_pixels(
    images: list[np.ndarray], channel: int, usable: np.ndarray, max_pixels: int, specular_threshold: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows and columns ``(N,)`` of the pixels used in ``channel`` (lit, no highlight, at most
    ``max_pixels`` evenly subsampled) and the channel's subsurface image ``2 I90`` ``(H, W)``."""
    i0, _, i90, _ = images
    i_sss = 2.0 * i90[..., channel]
    good = usable & (i_sss > 1e-6 * max(float(i_sss.max()), 1e-30))
    good &= (i0[..., channel] - i90[..., channel]) <= specular_threshold * i_sss
    rows, cols = np.nonzero(good)
    if rows.size > max_pixels:
        keep = np.linspace(0, rows.size - 1, max_pixels).astype(np.int64)
        rows, cols = rows[keep], cols[keep]
    return rows, cols, i_sss


def _huber_cost(
    etas: torch.Tensor,
    n: torch.Tensor,
    p: torch.Tensor,
    c: torch.Tensor,
    u: torch.Tensor,
    ratio: torch.Tensor,
) -> torch.Tensor:
    """``(E,)`` mean Huber loss (threshold 2 robust sigmas, per eta) of the ratio residuals of float64
    etas ``(E,)``; pixels weigh by |zeta| (where the ratio carries eta) through the prediction's
    sensitivity. ``n, p``: ``(N, 3)`` world normals and positions (mm); ``c``: ``(3,)`` camera centre;
    ``u``: ``(3,)`` unit camera up; ``ratio``: ``(N,)`` observed ``(I135 - I45) / (2 I90)``."""
    residual = _ratio_prediction(etas, n, p, c, u) - ratio[None]
    scale = 1.4826 * residual.abs().median(dim=1, keepdim=True).values.clamp_min(1e-6)
    huber = torch.where(
        residual.abs() <= 2 * scale, 0.5 * residual**2, 2 * scale * residual.abs() - 2 * scale**2
    )
    return huber.mean(dim=1)


def _minimise_eta(cost: Callable[[torch.Tensor], torch.Tensor], lo: float, hi: float) -> float:
    """Minimiser of ``cost`` (float64 etas ``(E,)`` -> ``(E,)``) on ``[lo, hi]``: a 141-point scan, then
    40 golden-section steps between the best point's neighbours."""
    grid = torch.linspace(lo, hi, 141, dtype=torch.float64)
    values = torch.cat([cost(chunk) for chunk in grid.split(20)])
    best = int(torch.argmin(values))
    a = float(grid[max(best - 1, 0)])
    b = float(grid[min(best + 1, len(grid) - 1)])
    golden = (math.sqrt(5) - 1) / 2
    x1, x2 = b - golden * (b - a), a + golden * (b - a)
    f1, f2 = (
        float(cost(torch.tensor([x1], dtype=torch.float64))),
        float(cost(torch.tensor([x2], dtype=torch.float64))),
    )
    for _ in range(40):
        if f1 < f2:
            b, x2, f2 = x2, x1, f1
            x1 = b - golden * (b - a)
            f1 = float(cost(torch.tensor([x1], dtype=torch.float64)))
        else:
            a, x1, f1 = x1, x2, f2
            x2 = a + golden * (b - a)
            f2 = float(cost(torch.tensor([x2], dtype=torch.float64)))
    return 0.5 * (a + b)


def _channel_estimate(
    images: list[np.ndarray],
    channel: int,
    geometry: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    eta_range: tuple[float, float],
    max_pixels: int,
    specular_threshold: float,
) -> tuple[float, float, int] | None:
    """``(eta, RMS ratio residual, pixels used)`` of one channel (``geometry`` of
    :func:`_sphere_geometry`); ``None`` with fewer than 10 usable pixels."""
    usable, position, normal, centre, up = geometry
    rows, cols, i_sss = _channel_pixels(images, channel, usable, max_pixels, specular_threshold)
    if rows.size < 10:
        return None
    _, i45, _, i135 = images
    ratio = torch.from_numpy((i135[rows, cols, channel] - i45[rows, cols, channel]) / i_sss[rows, cols])
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a))  # noqa: E731
    n, p = t(normal[rows, cols]), t(position[rows, cols])
    c, u = t(centre), t(up / np.linalg.norm(up))
    eta = _minimise_eta(functools.partial(_huber_cost, n=n, p=p, c=c, u=u, ratio=ratio), *eta_range)
    residual = _ratio_prediction(torch.tensor([eta], dtype=torch.float64), n, p, c, u)[0] - ratio
    return eta, float(torch.sqrt((residual**2).mean())), int(rows.size)


def estimate_ior(
    intensities: dict[str, np.ndarray],
    scene: SphereScene,
    *,
    eta_range: tuple[float, float] = (1.05, 3.0),
    zenith_range_deg: tuple[float, float] = (25.0, 80.0),
    max_pixels: int = 20000,
    specular_threshold: float = 0.25,
) -> IorResult:
    """Estimate one refractive index from a sphere's four analyzer images (module docstring).

    Args:
        intensities: ``{"I0", "I45", "I90", "I135"}`` -> ``(H, W)`` or ``(H, W, C)`` linear float images.
        scene: :class:`SphereScene`.
        eta_range: search interval (> 1). zenith_range_deg: usable exit zenith angles.
        max_pixels: pixels used at most (evenly subsampled, deterministic).
        specular_threshold: pixels with ``(I0 - I90) > threshold * 2 I90`` are dropped (highlights).

    Returns:
        :class:`IorResult`: the median of the per-channel estimates with more than two channels, else
        their pixel-count-weighted mean; ``at_bound`` flags an estimate on a bound of ``eta_range``.

    Raises:
        ValueError: missing/mismatched images, NaN/inf, no usable pixel.
    """
    images = _check_inputs(intensities, scene, eta_range)
    geometry = _sphere_geometry(scene, zenith_range_deg)
    fits = [
        _channel_estimate(images, channel, geometry, eta_range, max_pixels, specular_threshold)
        for channel in range(images[0].shape[2])
    ]
    fits = [fit for fit in fits if fit is not None]
    if not fits:
        raise ValueError(
            "no usable sphere pixel: check the scene (sphere centre/radius, camera) and the images"
        )
    estimates = [fit[0] for fit in fits]
    weights = np.asarray([fit[2] for fit in fits], dtype=np.float64)
    eta = float(np.median(estimates)) if len(estimates) > 2 else float(np.average(estimates, weights=weights))
    lo, hi = eta_range
    return IorResult(
        eta=eta,
        rms_residual=float(np.average([fit[1] for fit in fits], weights=weights)),
        pixels=int(sum(fit[2] for fit in fits)),
        channels=tuple(float(e) for e in estimates),
        at_bound=min(eta - lo, hi - eta) <= 1e-5 * (hi - lo),
    )


#: The ten objects of the paper's validation table: (name, measured eta_gt) (Ha et al. 2024, Sec. 6).
PAPER_OBJECTS: tuple[tuple[str, float], ...] = (
    ("red billiard", 1.485),
    ("green billiard", 1.469),
    ("blue billiard", 1.504),
    ("white billiard", 1.463),
    ("POM", 1.462),
    ("fake pearl", 2.295),
    ("yellow silicone", 1.303),
    ("pink silicone", 1.177),
    ("white silicone", 1.248),
    ("light green silicone", 1.343),
)


def default_sphere_scene(size: int = 256, radius: float = 40.0) -> SphereScene:
    """The paper rig's upper polarimetric camera and 8 LED modules looking at a sphere at 1 m."""
    from polarface.capture.rig import paper_rig

    rig = paper_rig(width=size, height=size)
    camera = rig.polarimetric_cameras()[0]
    return SphereScene(
        np.asarray(camera.K),
        np.asarray(camera.world_to_camera),
        size,
        size,
        np.array([0.0, 0.0, 1000.0]),
        radius,
        np.array([light.position_mm for light in rig.lights], dtype=np.float64),
    )


def render_sphere(
    scene: SphereScene,
    eta: float,
    *,
    rho_sss_bar: float = 0.5,
    rho_s: float = 0.3,
    alpha_s: float = 0.2,
    noise: bool = False,
    seed: int = 0,
) -> dict[str, np.ndarray]:
    """Analyzer images ``{"I0", "I45", "I90", "I135"}`` ``(H, W)`` float32 of a dielectric sphere under the
    scene's lights (radiant intensity 1e6, the rig's), with the full forward model
    (:func:`polarface.optics.render_polarimetric`); ``noise`` adds the rig's sensor shot/read noise
    and 12-bit quantisation at an exposure putting the brightest pixel at 80 % of full well."""
    from polarface.capture.sensor import SensorNoise, simulate_raw
    from polarface.optics.image_formation import render_polarimetric

    mask, position, normal, centre = sphere_pixels(scene)
    up = -scene.world_to_camera[1, :3]
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64))  # noqa: E731
    images = render_polarimetric(
        t(normal[mask]),
        t(position[mask]),
        t(centre),
        t(up),
        t(scene.lights),
        torch.full((len(scene.lights), 1), 1.0e6, dtype=torch.float64),
        eta,
        alpha_s,
        0.6,
        rho_s,
        0.1,
        rho_sss_bar,
    )
    out = {}
    for name, values in (("I0", images.i0), ("I45", images.i45), ("I90", images.i90), ("I135", images.i135)):
        image = np.zeros((scene.height, scene.width), np.float64)
        image[mask] = values[:, 0].numpy()
        out[name] = image
    if noise:
        exposure = 0.8 / max(float(out["I0"].max()), 1e-12)
        sensor = SensorNoise(exposure=exposure)
        rng = np.random.default_rng(seed)
        for name in out:
            raw = simulate_raw(out[name], sensor, seed=rng).astype(np.float64)
            white = (2**sensor.bit_depth - 1) if sensor.white_level is None else sensor.white_level
            out[name] = (raw - sensor.black_level) / (white - sensor.black_level) / exposure
    return {k: v.astype(np.float32) for k, v in out.items()}


def validate_paper_objects(
    noise: bool = False, size: int = 256, seed: int = 0
) -> list[dict[str, float | str]]:
    """Render a sphere for each of :data:`PAPER_OBJECTS` and estimate its eta: list of table rows."""
    scene = default_sphere_scene(size)
    rows = []
    for index, (name, eta_gt) in enumerate(PAPER_OBJECTS):
        images = render_sphere(scene, eta_gt, noise=noise, seed=seed + index)
        result = estimate_ior(images, scene)
        rows.append(
            {"object": name, "eta_gt": eta_gt, "eta": result.eta, "abs_error": abs(result.eta - eta_gt)}
        )
    return rows
