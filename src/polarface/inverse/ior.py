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

Before the fit (docs/ior.md): measured intensities are mapped to ideal-analyzer intensities with the
scene's polarizer calibration (:meth:`polarface.optics.analyzer.AnalyzerModel.to_ideal`); the sphere's
centre is refitted to its silhouette (:func:`polarface.inverse.ior_refine.refine_sphere`). After it:
the uncertainty of eta is a delete-one-group jackknife over 18 pixel groups (6 azimuth sectors x 3
zenith bands), so geometric errors that bias one side or one zenith band of the sphere show as spread;
the shading is checked against the lights (:func:`polarface.inverse.ior_refine.check_lights`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from scipy import ndimage

from polarface.inverse.ior_refine import (
    LightCheck,
    SphereRefinement,
    check_lights,
    refine_sphere,
    scene_warnings,
)
from polarface.inverse.ior_scene import SphereScene, sphere_pixels
from polarface.optics.analyzer import AnalyzerModel
from polarface.optics.image_formation import subsurface_exit_stokes

__all__ = ["IorResult", "estimate_ior"]

#: An eta one-sigma uncertainty above this is reported as untrustworthy (``IorResult.warnings``).
UNCERTAINTY_WARNING = 0.01
#: Delete-one-group jackknife groups: azimuth sectors x zenith bands.
AZIMUTH_GROUPS, ZENITH_GROUPS = 6, 3


@dataclasses.dataclass(frozen=True)
class IorResult:
    """Estimated refractive index and diagnostics.

    Attributes:
        eta: estimate; rms_residual: RMS of the ratio residual at the estimate; pixels: pixels used;
        channels: per-channel estimates (when the input has several channels); at_bound: True when
        ``eta`` lies on a bound of the search interval (within 1e-5 of its width): the cost's minimum is
        at or beyond the bound, so ``eta`` is not a measurement.
        eta_std: one-sigma uncertainty of ``eta`` (jackknife over pixel groups, channels combined);
        channel_stds: per-channel one-sigma uncertainties. eta_u95: half-width of the 95 % interval,
        ``t(0.975, G - 1) * eta_std`` for the jackknife's G groups (Student's t).
        refinement: the silhouette fit (None when not refined). lights: the shading check (None without
        lights). warnings: one line per reason to distrust the scene or the estimate.
    """

    eta: float
    rms_residual: float
    pixels: int
    channels: tuple[float, ...] = ()
    at_bound: bool = False
    eta_std: float = math.nan
    channel_stds: tuple[float, ...] = ()
    eta_u95: float = math.nan
    refinement: SphereRefinement | None = None
    lights: LightCheck | None = None
    warnings: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (the output of ``polarface ior --json``)."""
        refinement = None
        if self.refinement is not None:
            refinement = {
                "center": self.refinement.scene.centre.tolist(),
                **{f.name: getattr(self.refinement, f.name) for f in dataclasses.fields(self.refinement)[1:]},
            }
        lights = None if self.lights is None else dataclasses.asdict(self.lights)
        return {
            "eta": self.eta,
            "eta_std": self.eta_std,
            "eta_u95": self.eta_u95,
            "rms_residual": self.rms_residual,
            "pixels": self.pixels,
            "channels": list(self.channels),
            "channel_stds": list(self.channel_stds),
            "refinement": refinement,
            "lights": lights,
            "warnings": list(self.warnings),
        }


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


def _observed_ratio(
    difference: np.ndarray, i_sss: np.ndarray, rows: np.ndarray, cols: np.ndarray
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(I135 - I45) / S~`` and ``2 I90 / S~`` ``(N,)`` at the pixels, with ``S~`` the subsurface
    image ``2 I90`` averaged over each pixel's neighbours *without* the pixel itself (5 x 5 Gaussian,
    sigma 1 px, normalised over the lit pixels). The residual ``prediction * 2 I90 / S~ - (I135 - I45)
    / S~`` is then linear in each pixel's own noisy intensities, so zero-mean noise leaves it unbiased;
    the plain ratio ``(I135 - I45) / (2 I90)`` is biased where ``2 I90`` is dim (Jensen)."""
    offsets = np.arange(-2, 3, dtype=np.float64)
    kernel = np.exp(-0.5 * (offsets[:, None] ** 2 + offsets[None, :] ** 2))
    kernel[2, 2] = 0.0
    lit = (i_sss > 0).astype(np.float64)
    smooth = ndimage.convolve(i_sss * lit, kernel, mode="constant") / np.maximum(
        ndimage.convolve(lit, kernel, mode="constant"), 1e-12
    )
    smooth = np.maximum(smooth[rows, cols], 1e-12 * max(float(i_sss.max()), 1e-300))
    smooth = np.sqrt(smooth * float(smooth.mean()))  # shot-noise weights: variance ~ intensity
    return (
        torch.from_numpy(difference[rows, cols] / smooth),
        torch.from_numpy(i_sss[rows, cols] / smooth),
    )


def _huber_cost(
    etas: torch.Tensor,
    n: torch.Tensor,
    p: torch.Tensor,
    c: torch.Tensor,
    u: torch.Tensor,
    ratio: torch.Tensor,
    gain: torch.Tensor,
) -> torch.Tensor:
    """``(E,)`` mean Huber loss (threshold 2 robust sigmas, per eta) of the ratio residuals of float64
    etas ``(E,)``; pixels weigh by |zeta| (where the ratio carries eta) through the prediction's
    sensitivity. ``n, p``: ``(N, 3)`` world normals and positions (mm); ``c``: ``(3,)`` camera centre;
    ``u``: ``(3,)`` unit camera up; ``ratio``, ``gain``: ``(N,)`` observed ``(I135 - I45) / S~`` and
    ``2 I90 / S~`` (:func:`_observed_ratio`)."""
    residual = _ratio_prediction(etas, n, p, c, u) * gain[None] - ratio[None]
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


def _refine_eta(
    eta: float,
    n: torch.Tensor,
    p: torch.Tensor,
    c: torch.Tensor,
    u: torch.Tensor,
    ratio: torch.Tensor,
    gain: torch.Tensor,
) -> float:
    """Huber-weighted Gauss-Newton steps on the ratio residual from ``eta`` (a local refit, used for
    the jackknife's leave-one-group-out estimates; inputs as :func:`_huber_cost`)."""
    step_h = 1e-4
    for _ in range(8):
        prediction = _ratio_prediction(torch.tensor([eta, eta + step_h], dtype=torch.float64), n, p, c, u)
        residual = prediction[0] * gain - ratio
        slope = (prediction[1] - prediction[0]) * gain / step_h
        scale = float(1.4826 * residual.abs().median().clamp_min(1e-6))
        weight = torch.where(residual.abs() <= 2 * scale, 1.0, 2 * scale / residual.abs().clamp_min(1e-300))
        step = -float((weight * slope * residual).sum() / (weight * slope * slope).sum().clamp_min(1e-300))
        eta = min(max(eta + step, 1.0 + 1e-6), 10.0)
        if abs(step) < 1e-7:
            break
    return eta


def _pixel_groups(normal: np.ndarray, to_camera: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """``(N,)`` group index in ``[0, AZIMUTH_GROUPS * ZENITH_GROUPS)`` of each pixel: the sector of
    its normal's azimuth in the camera frame times the band of its exit zenith (equal-count bands)."""
    normal_cam = normal @ rotation.T
    azimuth = np.arctan2(normal_cam[:, 1], normal_cam[:, 0])
    quadrant = np.floor((azimuth + np.pi) / (2 * np.pi) * AZIMUTH_GROUPS).astype(np.int64) % AZIMUTH_GROUPS
    cos_o = (normal * to_camera).sum(-1)
    edges = np.quantile(cos_o, np.linspace(0, 1, ZENITH_GROUPS + 1)[1:-1])
    band = np.searchsorted(edges, cos_o)
    return quadrant * ZENITH_GROUPS + band


@dataclasses.dataclass(frozen=True)
class _ChannelFit:
    eta: float
    rms: float
    pixels: int
    std: float
    groups: int
    rows: np.ndarray
    cols: np.ndarray


def _channel_estimate(
    images: list[np.ndarray],
    channel: int,
    geometry: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    rotation: np.ndarray,
    eta_range: tuple[float, float],
    max_pixels: int,
    specular_threshold: float,
) -> _ChannelFit | None:
    """One channel's fit (``geometry`` of :func:`_sphere_geometry`, ``rotation`` the camera's world ->
    camera rotation) with its jackknife uncertainty; ``None`` with fewer than 10 usable pixels."""
    usable, position, normal, centre, up = geometry
    rows, cols, i_sss = _channel_pixels(images, channel, usable, max_pixels, specular_threshold)
    if rows.size < 10:
        return None
    _, i45, _, i135 = images
    ratio, gain = _observed_ratio(i135[..., channel] - i45[..., channel], i_sss, rows, cols)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a))  # noqa: E731
    n, p = t(normal[rows, cols]), t(position[rows, cols])
    c, u = t(centre), t(up / np.linalg.norm(up))
    cost = functools.partial(_huber_cost, n=n, p=p, c=c, u=u, ratio=ratio, gain=gain)
    eta = _minimise_eta(cost, *eta_range)
    residual = _ratio_prediction(torch.tensor([eta], dtype=torch.float64), n, p, c, u)[0] * gain - ratio
    to_camera = centre - position[rows, cols]
    to_camera /= np.linalg.norm(to_camera, axis=-1, keepdims=True)
    groups = _pixel_groups(normal[rows, cols], to_camera, rotation)
    left_out = []
    for group in np.unique(groups):
        keep = torch.from_numpy(groups != group)
        if int(keep.sum()) >= 10:
            left_out.append(_refine_eta(eta, n[keep], p[keep], c, u, ratio[keep], gain[keep]))
    count = len(left_out)
    std = math.sqrt((count - 1) / count * float(np.sum((np.asarray(left_out) - np.mean(left_out)) ** 2)))
    rms = float(torch.sqrt((residual**2).mean()))
    return _ChannelFit(eta, rms, int(rows.size), std, count, rows, cols)


def _ideal_images(images: list[np.ndarray], polarizer: AnalyzerModel) -> list[np.ndarray]:
    """The four ``(H, W, C)`` images mapped to what ideal 0/45/90/135 deg analyzers would measure."""
    if polarizer.is_ideal:
        return images
    ideal = polarizer.to_ideal(np.stack(images, axis=-1))
    return [np.ascontiguousarray(ideal[..., k]) for k in range(4)]


def estimate_ior(
    intensities: dict[str, np.ndarray],
    scene: SphereScene,
    *,
    eta_range: tuple[float, float] = (1.05, 3.0),
    zenith_range_deg: tuple[float, float] = (25.0, 80.0),
    max_pixels: int = 20000,
    specular_threshold: float = 0.25,
    polarizer: AnalyzerModel | None = None,
    refine: bool = True,
) -> IorResult:
    """Estimate one refractive index from a sphere's four analyzer images (module docstring).

    Args:
        intensities: ``{"I0", "I45", "I90", "I135"}`` -> ``(H, W)`` or ``(H, W, C)`` linear float images
            as measured behind the camera's analyzers.
        scene: :class:`SphereScene`.
        eta_range: search interval (> 1). zenith_range_deg: usable exit zenith angles.
        max_pixels: pixels used at most (evenly subsampled, deterministic).
        specular_threshold: pixels with ``(I0 - I90) > threshold * 2 I90`` are dropped (highlights).
        polarizer: the analyzers' calibration (default ``scene.polarizer``; ideal when absent).
        refine: refit the sphere's centre to its silhouette (``IorResult.refinement``).

    Returns:
        :class:`IorResult`: the median of the per-channel estimates with more than two channels, else
        their pixel-count-weighted mean; ``at_bound`` flags an estimate on a bound of ``eta_range``;
        ``eta_std`` its one-sigma uncertainty; ``warnings`` the reasons to distrust it.

    Raises:
        ValueError: missing/mismatched images, NaN/inf, no usable pixel.
    """
    images = _ideal_images(_check_inputs(intensities, scene, eta_range), polarizer or scene.polarizer)
    refinement = None
    if refine:
        brightness = 0.5 * sum(image.sum(axis=-1) for image in images)
        refinement = refine_sphere(scene, brightness)
    fitted_scene = scene if refinement is None else refinement.scene
    geometry = _sphere_geometry(fitted_scene, zenith_range_deg)
    rotation = scene.world_to_camera[:3, :3]
    fits = [
        _channel_estimate(images, channel, geometry, rotation, eta_range, max_pixels, specular_threshold)
        for channel in range(images[0].shape[2])
    ]
    fits = [fit for fit in fits if fit is not None]
    if not fits:
        raise ValueError(
            "no usable sphere pixel: check the scene (sphere centre/radius, camera) and the images"
        )
    estimates = np.asarray([fit.eta for fit in fits])
    weights = np.asarray([fit.pixels for fit in fits], dtype=np.float64)
    eta = float(np.median(estimates)) if len(estimates) > 2 else float(np.average(estimates, weights=weights))
    stds = np.asarray([fit.std for fit in fits])
    # channels share the geometry, so their errors are not independent: the typical channel's
    # uncertainty, plus the channels' disagreement
    spread = float(np.var(estimates)) / len(estimates) if len(estimates) > 1 else 0.0
    eta_std = math.sqrt(float(np.median(stds)) ** 2 + spread)
    widest = max(fits, key=lambda fit: fit.pixels)
    from scipy import stats  # here, not at the top: ~0.6 s of every process's start

    eta_u95 = float(stats.t.ppf(0.975, max(min(fit.groups for fit in fits) - 1, 1))) * eta_std
    _, position, normal, _, _ = geometry
    shading = 2.0 * images[2].sum(axis=-1)[widest.rows, widest.cols]
    lights = check_lights(
        fitted_scene, shading, normal[widest.rows, widest.cols], position[widest.rows, widest.cols], eta
    )
    warnings = scene_warnings(refinement, refine, lights)
    if eta_std > UNCERTAINTY_WARNING:
        warnings.append(
            f"eta uncertainty {eta_std:.3g} exceeds {UNCERTAINTY_WARNING}: the measurement cannot be trusted"
        )
    lo, hi = eta_range
    return IorResult(
        eta=eta,
        rms_residual=float(np.average([fit.rms for fit in fits], weights=weights)),
        pixels=int(sum(fit.pixels for fit in fits)),
        channels=tuple(float(e) for e in estimates),
        at_bound=min(eta - lo, hi - eta) <= 1e-5 * (hi - lo),
        eta_std=eta_std,
        eta_u95=eta_u95,
        channel_stds=tuple(float(s) for s in stds),
        refinement=refinement,
        lights=lights,
        warnings=tuple(warnings),
    )
