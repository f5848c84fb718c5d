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

``radiometric/``: a white diffuse sphere (:class:`DiffuseSphereTarget`) where the face will be:
``ambient/<camera>.png`` (room light, every camera: its silhouette) and ``leds/<module>/<camera>.png``
(one LED module on, the polarization cameras; a Lambertian sphere,
:func:`polarface.capture.radiometric_calibration.lambertian_sphere`, recorded with each camera's true
gains), and ``session.json`` with its radius, albedo and the exposures (:func:`write_radiometric_frames`).

``spectral/``: the spectrometer's readings (``filters.csv``: the Dolby filters' transmittance, ``led.csv``:
the LED spectrum, ``sweep.csv``: each band of a tunable filter in front of the LEDs; 1 nm, with 0.2 %
noise) and the first polarization camera's raw frames of a white target under each band, its Dolby filter
removed (``sweep/<band>/<camera>.png``), and ``session.json`` (:func:`write_spectral_frames`).

The chrome sphere's images (:func:`render_mirror_sphere`): under the room light every ray that hits the sphere
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
from polarface.capture.radiometric_calibration import lambertian_sphere
from polarface.capture.rig import Camera, Rig
from polarface.capture.sensor import SensorNoise, mosaic, simulate_raw
from polarface.geometry.camera import PinholeCamera
from polarface.geometry.mesh import TriangleMesh
from polarface.io import write_png
from polarface.io.atomic import write_json_atomic

__all__ = [
    "CALIBRATION",
    "DiffuseSphereTarget",
    "MirrorSphereTarget",
    "SpectralSweep",
    "mirror_sphere_positions",
    "render_mirror_sphere",
    "sphere_coverage",
    "write_calibration_session",
    "write_light_frames",
    "write_radiometric_frames",
    "write_spectral_frames",
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


@dataclasses.dataclass(frozen=True)
class DiffuseSphereTarget:
    """The white diffuse sphere of the ``radiometric`` frames, at the face's place.

    Attributes:
        radius_mm: its radius; albedo: its (spectrally flat) albedo, a Spectralon's 0.99.
        room: radiance of the room-lit sphere in the ``ambient`` frames; background: the room behind it,
            relative to :attr:`room`.
        fill: the exposures put the brightest pixel at this fraction of the full well.
    """

    radius_mm: float = 75.0
    albedo: float = 0.99
    room: float = 1.0
    background: float = 0.05
    fill: float = 0.8


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
    centre = np.asarray(centre_mm, dtype=np.float64)
    room = target.room * target.background
    if light_mm is None:
        coverage = sphere_coverage(camera, centre, target.radius_mm)
        return room + coverage * (target.reflectance * target.room - room)
    height, width = camera.height, camera.width
    image = np.zeros((height, width))
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


def sphere_coverage(camera: PinholeCamera, centre_mm: np.ndarray, radius_mm: float,
                    samples: int = 4) -> np.ndarray:
    """``(H, W)`` float64 share of each pixel that sees the sphere (``samples`` x ``samples`` rays per
    pixel, only around the sphere's projection)."""
    centre = np.asarray(centre_mm, dtype=np.float64)
    covered = np.zeros((camera.height, camera.width))
    rows, cols = _window(camera, centre, radius_mm, margin=3)
    if rows.stop <= rows.start or cols.stop <= cols.start:
        return covered
    offsets = (np.arange(samples) + 0.5) / samples - 0.5
    grid = camera.pixel_grid()[rows, cols]
    for dv in offsets:
        for du in offsets:
            origins, directions = camera.pixel_rays(grid + np.array([du, dv]))
            offset = origins - centre
            b = np.einsum("hwc,hwc->hw", directions, offset)
            covered[rows, cols] += (b**2 - np.einsum("hwc,hwc->hw", offset, offset) + radius_mm**2) > 0
    return covered / samples**2


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
               noise: bool, white: bool = True) -> np.ndarray:
    """The raw counts of ``camera`` recording the unpolarized ``radiance`` at ``exposure``, with its
    channel gains: ``(H, W)`` the same in every colour (``white``), or ``(H, W, 3)`` per colour."""
    gains = np.asarray(camera.channel_gains, dtype=np.float64)
    colour = (radiance[..., None] if white else radiance) * gains
    sensor = SensorNoise(exposure=float(exposure), bit_depth=camera.bit_depth, black_level=camera.black_level,
                         white_level=camera.white_level)
    if camera.sensor == "rgb":
        channels = [simulate_raw(colour[..., c], sensor, seed=rng, noiseless=not noise) for c in range(3)]
        return np.stack(channels, axis=-1)
    if camera.sensor != "color-polarization":
        colour = colour[..., 0]
    half = torch.from_numpy(np.ascontiguousarray(0.5 * colour))
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


def write_calibration_session(out: Path, rig: Rig, head: TriangleMesh,
                              spectral_parts: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None, *,
                              seed: int = 0, noise: bool = True) -> None:
    """Write the calibration session of the true ``rig`` into ``out`` (``SIM/calibration``): each step's
    folder (module docstring), the targets placed where the ``head`` (world mm) is; the ``spectral`` step
    from the rig's fine curves ``spectral_parts`` (camera ``(3, F)``, filters ``(2, F)``, LED ``(F,)``;
    None: not written). A step whose ``session.json`` exists is kept (a resumed simulation)."""
    out = Path(out)
    centre = head.vertices.mean(axis=0)
    if not (out / "lights" / "session.json").exists():
        write_light_frames(out / "lights", rig, centre, seed=seed, noise=noise)
    if not (out / "radiometric" / "session.json").exists():
        write_radiometric_frames(out / "radiometric", rig, centre, seed=seed, noise=noise)
    if spectral_parts is not None and not (out / "spectral" / "session.json").exists():
        write_spectral_frames(out / "spectral", rig, *spectral_parts, seed=seed, noise=noise)


def write_radiometric_frames(out: Path, rig: Rig, centre_mm: np.ndarray,
                             target: DiffuseSphereTarget = DiffuseSphereTarget(), *, seed: int = 0,
                             noise: bool = True) -> Path:
    """Write the ``radiometric`` frames of the true ``rig`` into ``out``: the white sphere at ``centre_mm``
    under the room light (``ambient/<camera>.png``, every camera) and lit by each LED module alone
    (``leds/<module>/<camera>.png``, the polarization cameras), Lambertian
    (:func:`polarface.capture.radiometric_calibration.lambertian_sphere`), recorded through each camera's
    sensor with its gains; ``session.json`` (radius, albedo, exposures) last."""
    out = Path(out)
    centre = np.asarray(centre_mm, dtype=np.float64)
    exposures: dict[str, dict[str, float]] = {"ambient": {}, "leds": {}}
    for number, camera in enumerate(rig.cameras):
        pinhole = camera.pinhole()
        room = target.room * target.background
        frames = {-1: room + sphere_coverage(pinhole, centre, target.radius_mm) * (target.room - room)}
        if camera.sensor != "rgb":
            for k, light in enumerate(rig.lights):
                position = np.asarray(light.position_mm)
                unit, _, _ = lambertian_sphere(pinhole, centre, target.radius_mm, position)
                frames[k] = target.albedo * float(np.mean(light.radiant_intensity)) * unit
        gain = max(camera.channel_gains)
        exposures["ambient"][camera.id] = target.fill / (float(frames[-1].max()) * gain)
        if camera.sensor != "rgb":
            brightest = max(float(frame.max()) for k, frame in frames.items() if k >= 0)
            exposures["leds"][camera.id] = target.fill / (brightest * gain)
        for k, frame in frames.items():
            kind = "ambient" if k < 0 else "leds"
            rng = np.random.default_rng((seed, 53, number, k + 1))
            raw = _raw_frame(camera, frame, exposures[kind][camera.id], rng, noise)
            folder = out / (kind if k < 0 else f"leds/{rig.lights[k].id}")
            write_png(folder / f"{camera.id}.png", raw, bit_depth=8 if camera.bit_depth <= 8 else 16)
    session = {"format": "polarface-calibration-radiometric", "version": 1, "target": "diffuse-sphere",
               "radius_mm": target.radius_mm, "albedo": target.albedo, "exposures": exposures}
    return write_json_atomic(out / "session.json", session)


@dataclasses.dataclass(frozen=True)
class SpectralSweep:
    """The ``spectral`` step's measurements: the narrow-band sweep and the spectrometer.

    Attributes:
        bands_nm: centres of the sweep's bands (the paper's tunable filter stepped every 10 nm; here over
            400-720 nm, which the rig's grid bins span, where the paper's covered 420-670).
        fwhm_nm: the bands' full width at half maximum (Gaussian).
        spectrometer_noise: sigma of the spectrometer's readings, relative to each curve's maximum.
        albedo: the white target's albedo; fill: the brightest band's brightest colour at this fraction of
            the full well.
    """

    bands_nm: tuple[float, ...] = tuple(float(w) for w in range(400, 721, 10))
    fwhm_nm: float = 10.0
    spectrometer_noise: float = 0.002
    albedo: float = 0.99
    fill: float = 0.8


def write_spectral_frames(out: Path, rig: Rig, camera_curves: np.ndarray, filters: np.ndarray,
                          led: np.ndarray, sweep: SpectralSweep = SpectralSweep(), *, seed: int = 0,
                          noise: bool = True) -> Path:
    """Write the ``spectral`` step's files of a rig whose camera's R, G, B sensitivity is ``camera_curves``
    ``(3, F)``, Dolby filters ``filters`` ``(2, F)`` and LED spectrum ``led`` ``(F,)`` on
    :data:`polarface.skin.spectral.FINE_WAVELENGTHS_NM`: the spectrometer's ``filters.csv`` (upper, lower),
    ``led.csv`` and ``sweep.csv`` (each band's power: the LEDs through the tunable filter), and the first
    polarization camera's raw frames of a white target under each band, its Dolby filter removed,
    ``sweep/<band>/<camera>.png``; ``session.json`` (the camera, the bands, their exposures) last."""
    from polarface.skin.spectral import FINE_WAVELENGTHS_NM

    out = Path(out)
    fine = FINE_WAVELENGTHS_NM
    rng = np.random.default_rng((seed, 54))

    def measured(curve: np.ndarray) -> np.ndarray:
        reading = curve + rng.normal(0.0, sweep.spectrometer_noise * curve.max(), curve.shape)
        return np.clip(reading, 0.0, None)

    sigma = sweep.fwhm_nm / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    bands = np.stack([led * np.exp(-0.5 * ((fine - centre) / sigma) ** 2) for centre in sweep.bands_nm])
    names = [f"band_{centre:g}" for centre in sweep.bands_nm]
    _write_csv(out / "filters.csv", fine, {"upper": measured(filters[0]), "lower": measured(filters[1])})
    _write_csv(out / "led.csv", fine, {"led": measured(led)})
    _write_csv(out / "sweep.csv", fine, {name: measured(b) for name, b in zip(names, bands, strict=True)})
    camera = rig.polarimetric_cameras()[0]
    values = sweep.albedo * np.trapezoid(camera_curves[None] * bands[:, None], fine, axis=-1)  # (B, 3)
    # each band exposed for itself: its brightest colour at the fill (the LEDs are dim in the deep blue)
    exposures = sweep.fill / (values * np.asarray(camera.channel_gains)).max(axis=1)
    for number, (name, colours) in enumerate(zip(names, values, strict=True)):
        radiance = np.broadcast_to(colours, (camera.height, camera.width, 3))
        frame_rng = np.random.default_rng((seed, 54, number))
        raw = _raw_frame(camera, radiance, float(exposures[number]), frame_rng, noise, white=False)
        depth = 8 if camera.bit_depth <= 8 else 16
        write_png(out / "sweep" / name / f"{camera.id}.png", raw, bit_depth=depth)
    session = {"format": "polarface-calibration-spectral", "version": 1, "camera": camera.id,
               "bands": names, "exposures": {"sweep": dict(zip(names, exposures.tolist(), strict=True))}}
    return write_json_atomic(out / "session.json", session)


def _write_csv(path: Path, wavelengths: np.ndarray, columns: dict[str, np.ndarray]) -> None:
    """A spectrometer's CSV (``wavelength_nm`` and ``columns``)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = [",".join(["wavelength_nm", *columns])]
    rows += [",".join([f"{w:g}", *(f"{values[i]:.6g}" for values in columns.values())])
             for i, w in enumerate(wavelengths)]
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")
