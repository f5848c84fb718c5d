"""The ``polarface calibrate-rig`` job: a calibration SESSION folder and the rig's nominal ``rig.json`` ->
the calibrated ``rig.json`` (what to capture and how: docs/calibration.md).

SESSION holds one folder per step, run in the order of :data:`CALIBRATION_STEPS`; a step whose folder is
absent is skipped (its part of the rig stays nominal, and the report says so):

* ``lights/``: a chrome sphere at several positions (:mod:`polarface.capture.light_calibration`):
  ``session.json`` (``radius_mm``, ``positions``, ``exposures`` {``ambient``, ``leds``} per camera) and,
  per position ``NN``, ``NN/ambient/<camera>.png`` (room light, LEDs off) and
  ``NN/leds/<module id>/<camera>.png`` (that LED module alone, room dark), raw frames of every camera of
  the rig. Gives the LED modules' positions.
* ``radiometric/``: a white diffuse sphere where the face will be
  (:mod:`polarface.capture.radiometric_calibration`): ``session.json`` (``radius_mm``, ``albedo``,
  ``exposures`` {``ambient``: every camera, ``leds``: the polarization cameras}), ``ambient/<camera>.png``
  (room light) and ``leds/<module id>/<camera>.png`` (that module alone, the polarization cameras). Gives
  each polarization camera's R, G, B gains and each module's six radiant intensities (only their products
  are measurable: the modules' mean intensity per channel stays the nominal rig's).
* ``spectral/``: the spectrometer's ``filters.csv`` (``wavelength_nm``, ``upper``, ``lower``: the Dolby
  filters' transmittance), ``led.csv`` (``wavelength_nm``, ``led``) and ``sweep.csv`` (``wavelength_nm``
  and one column per band of a narrow-band sweep: its spectral power), each covering the bins of the
  rig's wavelength grid; one polarization camera's raw frames of a white target under each band, its
  Dolby filter removed, ``sweep/<band>/<camera>.png``; ``session.json`` (``camera``, ``bands``,
  ``exposures`` {``sweep``: per band}). Gives the six channel responses and the LED spectrum
  (:mod:`polarface.capture.spectral_calibration`).

Raw frames are read as the capture store reads them (a polarization camera demosaiced with its settings
and analyzers, an RGB camera black-level corrected), divided by their exposure and by the camera's
channel gains; the calibration uses their total intensity (the mean over colours of ``I0 + I90``).
Nothing is written unless every step succeeds; the rig is written atomically.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from polarface.capture.demosaic import demosaic_camera
from polarface.capture.light_calibration import (
    HighlightObservation,
    LightCalibration,
    SilhouetteObservation,
    adjust_lights,
    highlight_spots,
    silhouette_cone,
    silhouette_edge,
    specular_points,
    sphere_centre,
)
from polarface.capture.manifest import raw_bit_depth_ok
from polarface.capture.radiometric_calibration import channel_products, lambertian_sphere, split_products
from polarface.capture.rig import Camera, Rig, SpectralModel
from polarface.capture.spectral_calibration import (
    read_spectra_csv,
    rig_spectral_model,
    sensitivity_from_sweep,
)
from polarface.io import read_json_object
from polarface.io.images import read_png
from polarface.io.output_folder import output_file
from polarface.skin.spectral import bin_edges

__all__ = [
    "CALIBRATION_STEPS",
    "LightsReport",
    "RadiometricReport",
    "SpectralReport",
    "calibrate_from_session",
    "calibrate_lights",
    "calibrate_radiometric",
    "calibrate_spectral",
    "format_calibration_report",
    "read_calibration_frame",
    "read_total_intensity",
    "response_peaks_nm",
]

#: The steps of a calibration session, in the order they run (each a folder of SESSION).
CALIBRATION_STEPS = ("lights", "radiometric", "spectral")
#: A detected highlight is the module's when it lies within this many pixels of the predicted one.
HIGHLIGHT_GATE_PX = 3.0
_COMMAND = "calibrate-rig"


def read_calibration_frame(path: Path, camera: Camera, exposure: float) -> tuple[np.ndarray, np.ndarray]:
    """The intensity per colour ``(H, W, C)`` float64 (``I0 + I90`` of a polarization camera; ``C`` = 3,
    or 1 for a mono sensor) of the raw frame ``path`` of ``camera`` at ``exposure``, divided by the
    camera's channel gains, and its ``(H, W)`` bool saturated pixels (module docstring).

    Raises:
        ValueError: an unreadable file, or one of another size or bit depth than the camera's (naming it).
    """
    try:
        raw = read_png(path)
        raw_bit_depth_ok(np.asarray(raw), camera)
        if camera.sensor == "rgb":
            if raw.shape != (camera.height, camera.width, 3):
                raise ValueError(f"shape {raw.shape}; the rig declares ({camera.height}, {camera.width}, 3)")
            gains = np.asarray(camera.channel_gains)
            scale = (camera.saturation_level - camera.black_level) * exposure * gains
            image = (raw.astype(np.float64) - camera.black_level) / scale
            return image, (raw >= camera.saturation_level).any(axis=-1)
        stack = demosaic_camera(raw, camera, exposure=exposure)
    except (OSError, ValueError) as exc:
        raise ValueError(f"raw frame '{path}': {exc}") from None
    total = (stack.intensities[0] + stack.intensities[2]).astype(np.float64)
    return (total if total.ndim == 3 else total[..., None]), stack.saturated


def read_total_intensity(path: Path, camera: Camera, exposure: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`read_calibration_frame`'s image averaged over the colours: ``(H, W)`` float64, and the
    saturated pixels."""
    image, saturated = read_calibration_frame(path, camera, exposure)
    return image.mean(axis=-1), saturated


@dataclasses.dataclass(frozen=True)
class LightsReport:
    """The ``lights`` step: the calibration, the modules' moves from the nominal rig and what was skipped."""

    calibration: LightCalibration
    moved_mm: np.ndarray
    skipped: list[str]

    def to_dict(self, rig: Rig) -> dict[str, Any]:
        """JSON-ready: per module its position, uncertainty and move (mm); the fit's residuals."""
        cal = self.calibration
        return {
            "modules": {light.id: {"position_mm": cal.positions_mm[k].tolist(),
                                   "std_mm": cal.positions_std_mm[k].tolist(),
                                   "moved_mm": float(self.moved_mm[k]), "highlights": int(cal.highlights[k])}
                        for k, light in enumerate(rig.lights)},
            "sphere_centres_mm": cal.sphere_centres_mm.tolist(),
            "highlight_rms_px": cal.highlight_rms_px,
            "silhouette_rms_px": cal.silhouette_rms_px,
            "skipped": self.skipped,
        }


def _silhouettes(folder: Path, rig: Rig, exposures: dict[str, float], radius: float, skipped: list[str],
                 index: int = 0) -> tuple[list[SilhouetteObservation], np.ndarray]:
    """The sphere's silhouette cones in the room-lit frames ``folder/<camera>.png`` of every camera that
    sees all of it (position ``index``), and the centre they give."""
    observations = []
    for camera in rig.cameras:
        path = folder / f"{camera.id}.png"
        image, _ = read_total_intensity(path, camera, exposures[camera.id])
        try:
            edge = silhouette_edge(image)
        except ValueError as exc:
            skipped.append(f"{path}: {exc}")
            continue
        axis, angle, rms = silhouette_cone(camera.pinhole(), edge)
        observations.append(SilhouetteObservation(index, camera.pinhole(), axis, angle, rms))
    if len(observations) < 2:
        raise ValueError(f"sphere not found in '{folder}': fewer than two cameras see all of it "
                         f"({'; '.join(skipped[-3:])})")
    return observations, sphere_centre(observations, radius)


def _highlights(folder: Path, index: int, rig: Rig, exposures: dict[str, float], radius: float,
                centre: np.ndarray, pinholes: dict[str, Any]) -> list[HighlightObservation]:
    """Every module's highlight at position ``index`` in every RGB camera: in the module's frame, the
    brightest spot within :data:`HIGHLIGHT_GATE_PX` of where the nominal module's would be. Not in the
    polarization cameras: a highlight a few pixels wide is undersampled by their 4 x 4-periodic colour
    and analyzer mosaic, and its demosaiced centroid moves by up to 2 pixels (docs/calibration.md)."""
    lights = np.array([light.position_mm for light in rig.lights], dtype=np.float64)
    observations = []
    for camera in (camera for camera in rig.cameras if camera.sensor == "rgb"):
        pinhole = pinholes[camera.id]
        points = specular_points(np.repeat(centre[None], len(lights), 0), radius,
                                 np.repeat(pinhole.center[None], len(lights), 0), lights)
        predicted = pinhole.project(points)[0]
        for k, light in enumerate(rig.lights):
            path = folder / f"{index:02d}" / "leds" / light.id / f"{camera.id}.png"
            image, saturated = read_total_intensity(path, camera, exposures[camera.id])
            spots = [spot for spot in highlight_spots(image, saturated)
                     if np.linalg.norm(spot.pixel - predicted[k]) <= HIGHLIGHT_GATE_PX]
            if not spots:
                continue
            spot = max(spots, key=lambda s: s.peak)
            if spot.saturated:
                where = np.round(spot.pixel, 1).tolist()
                raise ValueError(f"raw frame '{path}': the highlight at pixel {where} is saturated; "
                                 "capture it with a lower exposure")
            observations.append(HighlightObservation(index, k, pinhole, spot.pixel))
    return observations


def _read_session(folder: Path, fields: tuple[str, ...], exposed: dict[str, list[str]]
                  ) -> tuple[dict[str, float], dict[str, dict[str, float]]]:
    """A step's ``session.json``: its numeric ``fields`` (each > 0) and, per kind of frame of ``exposed``,
    each listed camera's exposure (> 0).

    Raises:
        FileNotFoundError: no ``session.json``. ValueError: a missing or bad field (naming the file and
            the field).
    """
    path = folder / "session.json"
    session = read_json_object(path)
    try:
        numbers = {name: float(session[name]) for name in fields}
        exposures = {kind: {camera: float(session["exposures"][kind][camera]) for camera in cameras}
                     for kind, cameras in exposed.items()}
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"'{path}': missing or bad field {exc}") from None
    bad = [name for name, value in numbers.items() if not value > 0]
    bad += [f"exposures.{kind}.{camera}" for kind, values in exposures.items()
            for camera, value in values.items() if not value > 0]
    if bad:
        raise ValueError(f"'{path}': fields {bad} must be > 0")
    return numbers, exposures


def calibrate_lights(folder: str | os.PathLike[str], rig: Rig) -> tuple[Rig, LightsReport]:
    """The ``lights`` step (module docstring): ``(rig with the calibrated module positions, report)``.

    Raises:
        FileNotFoundError: a missing ``session.json`` or frame (naming it).
        ValueError: a bad ``session.json``, a sphere not found, a saturated highlight, a module no
            highlight sees (naming the file or module).
    """
    folder = Path(folder)
    every = [camera.id for camera in rig.cameras]
    numbers, exposures = _read_session(folder, ("radius_mm", "positions"), {"ambient": every, "leds": every})
    radius, positions = numbers["radius_mm"], int(numbers["positions"])
    pinholes = {camera.id: camera.pinhole() for camera in rig.cameras}
    skipped: list[str] = []
    silhouettes, highlights, centres = [], [], []
    for index in range(positions):
        cones, centre = _silhouettes(folder / f"{index:02d}" / "ambient", rig, exposures["ambient"], radius,
                                     skipped, index)
        silhouettes.extend(cones)
        centres.append(centre)
        highlights.extend(_highlights(folder, index, rig, exposures["leds"], radius, centre, pinholes))
    nominal = np.array([light.position_mm for light in rig.lights], dtype=np.float64)
    seen = np.bincount([h.light for h in highlights], minlength=len(nominal))
    if (seen == 0).any():
        missing = [rig.lights[k].id for k in np.nonzero(seen == 0)[0]]
        raise ValueError(f"'{folder}': no highlight of LED module(s) {missing} was found in any frame")
    calibration = adjust_lights(highlights, silhouettes, radius, nominal, np.stack(centres))
    data = rig.model_dump(mode="json")
    for light, position in zip(data["lights"], calibration.positions_mm, strict=True):
        light["position_mm"] = position.tolist()
    moved = np.linalg.norm(calibration.positions_mm - nominal, axis=1)
    return Rig.model_validate(data), LightsReport(calibration, moved, skipped)


@dataclasses.dataclass(frozen=True)
class RadiometricReport:
    """The ``radiometric`` step: per module and channel the measured product of gain and intensity
    ``(K, 6)``, its split into the channels' gains ``(6,)`` and the modules' intensities ``(K, 6)``
    (:func:`~polarface.capture.radiometric_calibration.split_products`), the fits' relative RMS residuals
    ``(K, 6)`` and the sphere's centre (mm)."""

    products: np.ndarray
    gains: np.ndarray
    intensities: np.ndarray
    residuals: np.ndarray
    centre_mm: np.ndarray

    def to_dict(self, rig: Rig) -> dict[str, Any]:
        """JSON-ready, per channel (by the rig's channel names) and per module."""
        names = list(rig.spectral.channel_names) if rig.spectral is not None else [str(c) for c in range(6)]
        return {
            "gains": dict(zip(names, self.gains.tolist(), strict=True)),
            "modules": {light.id: {"radiant_intensity": self.intensities[k].tolist(),
                                   "relative_rms_residual": self.residuals[k].tolist()}
                        for k, light in enumerate(rig.lights)},
            "sphere_centre_mm": self.centre_mm.tolist(),
        }


#: Pixels of the white sphere used: lit at more than this cosine and seen at more than :data:`VIEW_COSINE`
#: (away from the terminator and the silhouette, where a pixel mixes sphere and background).
LIT_COSINE, VIEW_COSINE = 0.2, 0.4


def calibrate_radiometric(folder: str | os.PathLike[str], rig: Rig) -> tuple[Rig, RadiometricReport]:
    """The ``radiometric`` step (:mod:`polarface.capture.radiometric_calibration`): ``(rig with each
    polarization camera's channel gains and each module's six radiant intensities, report)``. Run after
    the ``lights`` step: the modules' positions are the rig's.

    Raises:
        FileNotFoundError: a missing ``session.json`` or frame. ValueError: a bad ``session.json``, the
            sphere not found, a camera without colour channels, no usable pixel (naming the file).
    """
    folder = Path(folder)
    polarimetric = [camera for camera in rig.cameras if camera.sensor != "rgb"]
    numbers, exposures = _read_session(folder, ("radius_mm", "albedo"), {
        "ambient": [camera.id for camera in rig.cameras], "leds": [camera.id for camera in polarimetric]})
    radius, albedo = numbers["radius_mm"], numbers["albedo"]
    _, centre = _silhouettes(folder / "ambient", rig, exposures["ambient"], radius, [])
    products = np.full((len(rig.lights), 6), np.nan)
    residuals = np.full((len(rig.lights), 6), np.nan)
    for camera in polarimetric:
        if len(camera.colour_channels) != 3:
            raise ValueError(f"camera '{camera.id}' has no R, G, B colour_channels: the radiometric step "
                             "needs them to know which channels it measures")
        channels = [camera.colour_channels[colour] for colour in ("R", "G", "B")]
        pinhole = camera.pinhole()
        for k, light in enumerate(rig.lights):
            path = folder / "leds" / light.id / f"{camera.id}.png"
            image, saturated = read_calibration_frame(path, camera, exposures["leds"][camera.id])
            unit, lit, view = lambertian_sphere(pinhole, centre, radius, np.asarray(light.position_mm))
            clipped = ndimage.binary_dilation(saturated, iterations=2)
            valid = (lit > LIT_COSINE) & (view > VIEW_COSINE) & ~clipped
            try:
                products[k, channels], residuals[k, channels] = channel_products(image, albedo * unit, valid)
            except ValueError as exc:
                raise ValueError(f"raw frame '{path}': {exc}") from None
    if np.isnan(products).any():
        missing = sorted({int(c) for c in np.nonzero(np.isnan(products).any(axis=0))[0]})
        raise ValueError(f"'{folder}': no polarization camera records channel(s) {missing}")
    nominal = np.array([np.broadcast_to(np.asarray(light.radiant_intensity, np.float64), (6,))
                        for light in rig.lights])
    gains, intensities = split_products(products, nominal.mean(axis=0))
    data = rig.model_dump(mode="json")
    for camera in data["cameras"]:
        if camera["sensor"] != "rgb":
            camera["channel_gains"] = [g * float(gains[camera["colour_channels"][colour]]) for g, colour
                                       in zip(camera["channel_gains"], ("R", "G", "B"), strict=True)]
    for light, values in zip(data["lights"], intensities, strict=True):
        light["radiant_intensity"] = values.tolist()
    return Rig.model_validate(data), RadiometricReport(products, gains, intensities, residuals, centre)


@dataclasses.dataclass(frozen=True)
class SpectralReport:
    """The ``spectral`` step: the calibrated spectral model and, per channel, its response's peak
    wavelength (nm, a parabola through the grid's three values around the maximum) and its change from
    the nominal rig's (RMS over the grid, relative to the channel's maximum)."""

    model: SpectralModel
    peak_nm: np.ndarray
    change_from_nominal: np.ndarray

    def to_dict(self, rig: Rig) -> dict[str, Any]:
        """JSON-ready, per channel name."""
        return {"channels": {name: {"peak_nm": float(self.peak_nm[c]),
                                    "change_from_nominal": float(self.change_from_nominal[c])}
                             for c, name in enumerate(self.model.channel_names)},
                "led_spd": list(self.model.led_spd)}


def response_peaks_nm(responses: np.ndarray, wavelengths_nm: np.ndarray) -> np.ndarray:
    """``(C,)`` peak wavelength of each ``(C, L)`` response on the grid: the vertex of the parabola through
    the maximum and its two neighbours (the maximum itself at the grid's ends)."""
    grid = np.asarray(wavelengths_nm, dtype=np.float64)
    peaks = []
    for curve in np.asarray(responses, dtype=np.float64):
        i = int(np.argmax(curve))
        if 0 < i < len(curve) - 1:
            left, centre, right = curve[i - 1 : i + 2]
            denominator = left - 2.0 * centre + right
            offset = 0.5 * (left - right) / denominator if denominator != 0 else 0.0
            peaks.append(grid[i] + offset * (grid[i + 1] - grid[i - 1]) / 2.0)
        else:
            peaks.append(grid[i])
    return np.asarray(peaks)


def calibrate_spectral(folder: str | os.PathLike[str], rig: Rig) -> tuple[Rig, SpectralReport]:
    """The ``spectral`` step (:mod:`polarface.capture.spectral_calibration`): ``(rig with the measured
    channel responses and LED spectrum on its wavelength grid, report)``.

    Raises:
        FileNotFoundError: a missing file. ValueError: a bad ``session.json`` or CSV, a spectrometer file
            that misses a wavelength the grid needs, a camera without colour channels (naming the file).
    """
    folder = Path(folder)
    if rig.spectral is None:
        raise ValueError("the rig has no spectral calibration to replace (its wavelength grid is unknown)")
    path = folder / "session.json"
    session = read_json_object(path)
    try:
        camera = rig.camera(str(session["camera"]))
        bands = [str(band) for band in session["bands"]]
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"'{path}': missing or bad field {exc}") from None
    _, exposures = _read_session(folder, (), {"sweep": bands})
    grid = np.asarray(rig.spectral.wavelengths_nm, dtype=np.float64)
    edges = bin_edges(grid)
    cover = (float(edges[0]), float(edges[-1]))
    filters_nm, filters = read_spectra_csv(folder / "filters.csv", ("upper", "lower"), cover)
    led_nm, led = read_spectra_csv(folder / "led.csv", ("led",), cover)
    sweep_nm, sweep = read_spectra_csv(folder / "sweep.csv", bands, cover)
    values = []
    for band in bands:
        image, _ = read_calibration_frame(folder / "sweep" / band / f"{camera.id}.png", camera,
                                          exposures["sweep"][band])
        h, w = image.shape[:2]
        centre = image[h // 4 : 3 * h // 4, w // 4 : 3 * w // 4]  # the white target, away from the edges
        values.append(np.median(centre.reshape(-1, image.shape[-1]), axis=0))
    if len(values[0]) != 3:
        raise ValueError(f"camera '{camera.id}' is not a colour camera: the spectral step needs its R, G, B")
    fine = np.arange(cover[0], cover[1] + 0.5, 1.0)
    power = np.stack([sweep[band] for band in bands])
    sensitivity = sensitivity_from_sweep(np.stack(values), sweep_nm, power, fine)
    parts = np.stack([np.interp(fine, filters_nm, filters[eye]) for eye in ("upper", "lower")])
    model = rig_spectral_model(sensitivity, parts, np.interp(fine, led_nm, led["led"]), fine, grid,
                               rig.spectral.channel_names)
    responses = np.asarray(model.channel_responses)
    nominal = np.asarray(rig.spectral.channel_responses)
    change = np.sqrt(np.mean((responses - nominal) ** 2, axis=1)) / nominal.max(axis=1)
    data = {**rig.model_dump(mode="json"), "spectral": model.model_dump(mode="json")}
    calibrated = Rig.model_validate(data)
    return calibrated, SpectralReport(model, response_peaks_nm(responses, grid), change)


def calibrate_from_session(
    session: str | os.PathLike[str],
    rig_path: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    force: bool = False,
) -> dict[str, Any]:
    """Run the steps of :data:`CALIBRATION_STEPS` found in ``session`` on the rig ``rig_path`` and write
    the calibrated rig to ``out`` (atomically, after every step succeeded); returns the report (per step
    its results, and the steps skipped).

    Raises:
        FileNotFoundError, ValueError: naming the file, field or argument at fault; nothing is written.
    """
    session = Path(session)
    if not session.is_dir():
        raise FileNotFoundError(f"calibration session '{session}' is not a folder")
    rig = Rig.load(rig_path)
    report: dict[str, Any] = {"format": "polarface-rig-calibration", "version": 1, "steps": {}, "skipped": []}
    with output_file(Path(out), _COMMAND, force=force, inputs={"SESSION": session, "--rig": rig_path}):
        for step in CALIBRATION_STEPS:
            if not (session / step).is_dir():
                report["skipped"].append(step)
                continue
            rig, result = STEP_FUNCTIONS[step](session / step, rig)
            report["steps"][step] = result.to_dict(rig)
        rig.save(Path(out))
    return report


#: Each step's function: ``(its folder, the rig so far) -> (the rig with the step's results, report)``.
STEP_FUNCTIONS = {
    "lights": calibrate_lights, "radiometric": calibrate_radiometric, "spectral": calibrate_spectral,
}


def format_calibration_report(report: dict[str, Any]) -> str:
    """The report of :func:`calibrate_from_session` as text: per step its results, one line per module."""
    lines = []
    lights = report["steps"].get("lights")
    if lights is not None:
        lines.append(f"lights: highlight RMS {lights['highlight_rms_px']:.3f} px, silhouette RMS "
                     f"{lights['silhouette_rms_px']:.3f} px, {len(lights['skipped'])} silhouette(s) skipped")
        lines.append(f"{'module':12s} {'x':>9s} {'y':>9s} {'z':>9s} {'std':>6s} {'moved':>6s} "
                     f"{'highlights':>10s}")
        for name, module in lights["modules"].items():
            x, y, z = module["position_mm"]
            std = float(np.linalg.norm(module["std_mm"]))
            lines.append(f"{name:12s} {x:9.2f} {y:9.2f} {z:9.2f} {std:6.2f} {module['moved_mm']:6.2f} "
                         f"{module['highlights']:10d}")
    radiometric = report["steps"].get("radiometric")
    if radiometric is not None:
        gains = ", ".join(f"{name} {value:.4f}" for name, value in radiometric["gains"].items())
        lines.append(f"radiometric: channel gains {gains}")
        for name, module in radiometric["modules"].items():
            values = " ".join(f"{v:.4g}" for v in module["radiant_intensity"])
            lines.append(f"{name:12s} radiant intensity per channel {values}")
    spectral = report["steps"].get("spectral")
    if spectral is not None:
        lines.append("spectral: " + ", ".join(f"{name} peak {channel['peak_nm']:.1f} nm (changed "
                                              f"{100 * channel['change_from_nominal']:.1f} %)"
                                              for name, channel in spectral["channels"].items()))
    for step in report["skipped"]:
        lines.append(f"{step}: no folder in the session; left as the nominal rig has it")
    return "\n".join(lines)
