"""The calibration session of the simulated rig: the frames a user captures to calibrate it
(``SIM/calibration/``, written by ``polarface simulate --perturb-rig SEED``; read by
``polarface calibrate-rig``; docs/calibration.md).

The frames are rendered with the true rig (:mod:`polarface.simulate.rig_perturbation`) and recorded as raw
frames through each camera's sensor (mosaic, shot and read noise, 12-bit), as a real session would be.

``lights/``: a chrome sphere of radius :attr:`MirrorSphereTarget.radius_mm` at several positions in front
of the rig (:func:`mirror_sphere_positions`); per position ``NN/ambient/<camera>.png`` (the room light on,
the LEDs off: the sphere a bright disc on a dark room) and ``NN/leds/<module>/<camera>.png`` (one LED
module on, the room dark: its highlight), and ``session.json`` with the radius and each camera's
exposures. One module at a time: at the demo's resolution the eight modules' highlights lie 5 pixels apart
on the sphere, too close to tell apart once lens blur and demosaicing spread them.

The sphere's images (:func:`render_mirror_sphere`): under the room light every ray that hits the sphere
sees a uniform room (the disc's value, antialiased by 4 x 4 samples per pixel); with the LEDs on, each
module is a point whose mirror image is a point at the specular point
(:func:`polarface.capture.light_calibration.specular_points`), of intensity ``rho I r^2 / (4 D^2)`` (a
convex mirror of radius ``r`` lit from distance ``D``), spread by a Gaussian lens blur. The light is
rendered unpolarized (the analyzers see half of it each): the calibration reads the total intensity.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch

from polarface._validation import trusted_inputs
from polarface.capture.light_calibration import specular_points
from polarface.capture.rig import Camera, Rig
from polarface.capture.sensor import SensorNoise, mosaic, simulate_raw
from polarface.geometry.camera import PinholeCamera
from polarface.geometry.mesh import TriangleMesh
from polarface.io import write_png
from polarface.io.atomic import write_json_atomic

__all__ = [
    "CALIBRATION",
    "MirrorSphereTarget",
    "mirror_sphere_positions",
    "render_mirror_sphere",
    "write_calibration_session",
    "write_light_frames",
]

#: The calibration session's folder in a simulation folder.
CALIBRATION = "calibration"


@dataclasses.dataclass(frozen=True)
class MirrorSphereTarget:
    """The chrome sphere of the ``lights`` frames and where it is put.

    Attributes:
        radius_mm: its radius (a 100 mm ball: large enough that its silhouette and highlights fix the
            modules to a millimetre, docs/calibration.md).
        lateral_mm: ``(x, y)`` half spans of the 3 x 3 grid of positions across the cameras' view.
        depths_mm: offsets along the rig's axis of the grid's rows (one per row of three).
        reflectance: the chrome's reflectance.
        room: radiance of the room reflected in the sphere in the ``ambient`` frames (the disc); the
            background is :attr:`background` of it.
        background: the dark room behind the sphere, relative to :attr:`room`.
        blur_px: sigma of the lens blur of a highlight, pixels.
        fill: the exposures put the brightest highlight (and the disc) at this fraction of the full well.
    """

    radius_mm: float = 50.0
    lateral_mm: tuple[float, float] = (50.0, 35.0)
    depths_mm: tuple[float, float, float] = (-150.0, 0.0, 150.0)
    reflectance: float = 0.6
    room: float = 1.0
    background: float = 0.05
    blur_px: float = 0.8
    fill: float = 0.7


def mirror_sphere_positions(centre_mm: np.ndarray, target: MirrorSphereTarget) -> np.ndarray:
    """``(9, 3)`` sphere centres (world mm): a 3 x 3 grid across the view around ``centre_mm`` (the face's
    place), its rows at the three :attr:`MirrorSphereTarget.depths_mm` in a Latin square, so that every
    column and row spans the depths."""
    x, y = target.lateral_mm
    depth = target.depths_mm
    offsets = [(dx, dy, depth[(i + j) % 3]) for i, dy in enumerate((-y, 0.0, y))
               for j, dx in enumerate((-x, 0.0, x))]
    return np.asarray(centre_mm, dtype=np.float64)[None] + np.asarray(offsets)


def render_mirror_sphere(camera: PinholeCamera, centre_mm: np.ndarray, target: MirrorSphereTarget,
                         light_mm: np.ndarray | None = None, intensity: float = 0.0) -> np.ndarray:
    """``(H, W)`` float64 radiance of the sphere at ``centre_mm`` in ``camera``: the room-lit disc
    (``light_mm`` None) or the highlight of one LED module at ``light_mm`` ``(3,)`` of radiant
    ``intensity`` (module docstring)."""
    height, width = camera.height, camera.width
    centre = np.asarray(centre_mm, dtype=np.float64)
    image = np.full((height, width), target.room * target.background if light_mm is None else 0.0)
    if light_mm is None:
        rows, cols = _window(camera, centre, target.radius_mm, margin=3)
        if rows.stop <= rows.start or cols.stop <= cols.start:
            return image
        samples = 4
        offsets = (np.arange(samples) + 0.5) / samples - 0.5
        grid = camera.pixel_grid()[rows, cols]
        covered = np.zeros(grid.shape[:2])
        for dv in offsets:
            for du in offsets:
                origins, directions = camera.pixel_rays(grid + np.array([du, dv]))
                offset = origins - centre
                b = np.einsum("hwc,hwc->hw", directions, offset)
                covered += (b**2 - np.einsum("hwc,hwc->hw", offset, offset) + target.radius_mm**2) > 0
        covered /= samples**2
        disc = target.reflectance * target.room
        image[rows, cols] += covered * (disc - target.room * target.background)
        return image
    light = np.asarray(light_mm, dtype=np.float64)
    point = specular_points(centre[None], target.radius_mm, camera.center[None], light[None])[0]
    pixel = camera.project(point)[0]
    if not np.isfinite(pixel).all():
        return image
    lit = float(intensity) / float(np.sum((light - point) ** 2))  # the irradiance at the sphere
    virtual = target.reflectance * lit * target.radius_mm**2 / 4.0  # the mirror image's intensity
    energy = virtual * float(camera.K[0, 0]) ** 2 / float(np.sum((camera.center - point) ** 2))  # pixel sum
    reach = int(np.ceil(6 * target.blur_px))
    u, v = pixel
    rows = slice(max(int(v) - reach, 0), min(int(v) + reach + 1, height))
    cols = slice(max(int(u) - reach, 0), min(int(u) + reach + 1, width))
    grid_v, grid_u = np.mgrid[rows, cols]
    spot = np.exp(-((grid_u - u) ** 2 + (grid_v - v) ** 2) / (2.0 * target.blur_px**2))
    image[rows, cols] += energy * spot / (2.0 * np.pi * target.blur_px**2)
    return image


def _window(camera: PinholeCamera, centre: np.ndarray, radius: float, margin: int) -> tuple[slice, slice]:
    """The pixels around the projection of a sphere (its bounding box over 26 points of its
    circumscribed cube, plus ``margin``)."""
    steps = (-1, 0, 1)
    corners = centre + radius * np.array([(x, y, z) for x in steps for y in steps for z in steps])
    pixels = camera.project(corners)[0]
    low = np.floor(np.nanmin(pixels, axis=0)).astype(int) - margin
    high = np.ceil(np.nanmax(pixels, axis=0)).astype(int) + margin
    rows = slice(max(low[1], 0), min(high[1] + 1, camera.height))
    cols = slice(max(low[0], 0), min(high[0] + 1, camera.width))
    return rows, cols


def _raw_frame(camera: Camera, radiance: np.ndarray, exposure: float, rng: np.random.Generator,
               noise: bool) -> np.ndarray:
    """The raw counts of ``camera`` recording the unpolarized, white ``radiance`` ``(H, W)`` at
    ``exposure``, with its channel gains."""
    gains = np.asarray(camera.channel_gains, dtype=np.float64)
    sensor = SensorNoise(exposure=float(exposure), bit_depth=camera.bit_depth, black_level=camera.black_level,
                         white_level=camera.white_level)
    if camera.sensor == "rgb":
        return np.stack([simulate_raw(radiance * g, sensor, seed=rng, noiseless=not noise) for g in gains],
                        axis=-1)
    colour = radiance[..., None] * gains if camera.sensor == "color-polarization" else radiance * gains[0]
    half = torch.from_numpy(0.5 * colour)
    with trusted_inputs():  # finite and >= 0 by construction: the value checks cost more than the mosaic
        signal = np.clip(mosaic(half, half, half, half, sensor=camera.sensor).numpy(), 0.0, None)
    return simulate_raw(signal, sensor, seed=rng, noiseless=not noise)


def write_light_frames(out: Path, rig: Rig, centre_mm: np.ndarray,
                       target: MirrorSphereTarget = MirrorSphereTarget(), *, seed: int = 0,
                       noise: bool = True) -> Path:
    """Write the ``lights`` frames of the true ``rig`` (module docstring) into ``out`` (a folder); returns
    ``out / "session.json"``, written last (a folder without it is incomplete)."""
    out = Path(out)
    positions = mirror_sphere_positions(centre_mm, target)
    lights = np.array([light.position_mm for light in rig.lights], dtype=np.float64)
    intensities = np.array([float(np.mean(light.radiant_intensity)) for light in rig.lights])
    exposures: dict[str, dict[str, float]] = {"ambient": {}, "leds": {}}
    for number, camera in enumerate(rig.cameras):
        pinhole = camera.pinhole()
        # (module index, position) -> radiance; module -1: the room-lit frame
        frames = {(-1, index): render_mirror_sphere(pinhole, centre, target)
                  for index, centre in enumerate(positions)}
        frames |= {(k, index): render_mirror_sphere(pinhole, centre, target, lights[k], intensities[k])
                   for index, centre in enumerate(positions) for k in range(len(lights))}
        for kind in ("ambient", "leds"):
            brightest = max(float(frame.max()) for (k, _), frame in frames.items()
                            if (k < 0) == (kind == "ambient"))
            exposures[kind][camera.id] = target.fill / (brightest * max(camera.channel_gains))
        for (k, index), frame in frames.items():
            kind = "ambient" if k < 0 else "leds"
            rng = np.random.default_rng((seed, 52, number, index, k + 1))
            raw = _raw_frame(camera, frame, exposures[kind][camera.id], rng, noise)
            folder = out / f"{index:02d}" / (kind if k < 0 else f"leds/{rig.lights[k].id}")
            write_png(folder / f"{camera.id}.png", raw, bit_depth=8 if camera.bit_depth <= 8 else 16)
    session = {"format": "polarface-calibration-lights", "version": 1, "target": "mirror-sphere",
               "radius_mm": target.radius_mm, "positions": len(positions), "exposures": exposures}
    return write_json_atomic(out / "session.json", session)


def write_calibration_session(out: Path, rig: Rig, head: TriangleMesh, *, seed: int = 0,
                              noise: bool = True) -> None:
    """Write the calibration session of the true ``rig`` into ``out`` (``SIM/calibration``): each step's
    folder (module docstring), the targets placed where the ``head`` (world mm) is; a step whose
    ``session.json`` exists is kept (a resumed simulation)."""
    out = Path(out)
    if not (out / "lights" / "session.json").exists():
        write_light_frames(out / "lights", rig, head.vertices.mean(axis=0), seed=seed, noise=noise)
