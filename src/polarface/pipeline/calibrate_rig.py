"""The ``polarface calibrate-rig`` job: a calibration SESSION folder and the rig's nominal ``rig.json`` ->
the calibrated ``rig.json`` (what to capture and how: docs/calibration.md).

SESSION holds one folder per step, run in the order of :data:`CALIBRATION_STEPS`; a step whose folder is
absent is skipped (its part of the rig stays nominal, and the report says so):

* ``lights/``: a chrome sphere at several positions (:mod:`polarface.capture.light_calibration`):
  ``session.json`` (``radius_mm``, ``positions``, ``exposures`` {``ambient``, ``leds``} per camera) and,
  per position ``NN``, ``NN/ambient/<camera>.png`` (room light, LEDs off) and
  ``NN/leds/<module id>/<camera>.png`` (that LED module alone, room dark), raw frames of every camera of
  the rig. Gives the LED modules' positions.

Raw frames are read as the capture store reads them (a polarization camera demosaiced with its settings
and analyzers, an RGB camera black-level corrected), divided by their exposure and by the camera's
channel gains; the calibration uses their total intensity (the mean over colours of ``I0 + I90``).
Nothing is written unless every step succeeds; the rig is written atomically.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

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
from polarface.capture.rig import Camera, Rig
from polarface.io import read_json_object
from polarface.io.images import read_png
from polarface.io.output_folder import output_file

__all__ = [
    "CALIBRATION_STEPS",
    "LightsReport",
    "calibrate_from_session",
    "calibrate_lights",
    "format_calibration_report",
    "read_total_intensity",
]

LOGGER = logging.getLogger(__name__)

#: The steps of a calibration session, in the order they run (each a folder of SESSION).
CALIBRATION_STEPS = ("lights",)
#: A detected highlight is the module's when it lies within this many pixels of the predicted one.
HIGHLIGHT_GATE_PX = 3.0
_COMMAND = "calibrate-rig"


def read_total_intensity(path: Path, camera: Camera, exposure: float) -> tuple[np.ndarray, np.ndarray]:
    """The total intensity ``(H, W)`` float64 of the raw frame ``path`` of ``camera`` (module docstring)
    at ``exposure``, and its ``(H, W)`` bool saturated pixels.

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
            image = ((raw.astype(np.float64) - camera.black_level) / scale).mean(axis=-1)
            return image, (raw >= camera.saturation_level).any(axis=-1)
        stack = demosaic_camera(raw, camera, exposure=exposure)
    except (OSError, ValueError) as exc:
        raise ValueError(f"raw frame '{path}': {exc}") from None
    total = stack.intensities[0] + stack.intensities[2]
    image = total.mean(axis=-1) if total.ndim == 3 else total
    return image.astype(np.float64), stack.saturated


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


def _silhouettes(folder: Path, index: int, rig: Rig, exposures: dict[str, float], radius: float,
                 skipped: list[str]) -> tuple[list[SilhouetteObservation], np.ndarray]:
    """The sphere's silhouette cones at position ``index`` in every camera that sees all of it, and the
    centre they give."""
    observations = []
    for camera in rig.cameras:
        path = folder / f"{index:02d}" / "ambient" / f"{camera.id}.png"
        image, _ = read_total_intensity(path, camera, exposures[camera.id])
        try:
            edge = silhouette_edge(image)
        except ValueError as exc:
            skipped.append(f"{path}: {exc}")
            continue
        axis, angle, rms = silhouette_cone(camera.pinhole(), edge)
        observations.append(SilhouetteObservation(index, camera.pinhole(), axis, angle, rms))
    if len(observations) < 2:
        raise ValueError(f"sphere not found at position {index:02d}: fewer than two cameras see all of it "
                         f"('{folder / f'{index:02d}' / 'ambient'}'; {'; '.join(skipped[-3:])})")
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


def calibrate_lights(folder: str | os.PathLike[str], rig: Rig) -> tuple[Rig, LightsReport]:
    """The ``lights`` step (module docstring): ``(rig with the calibrated module positions, report)``.

    Raises:
        FileNotFoundError: a missing ``session.json`` or frame (naming it).
        ValueError: a bad ``session.json``, a sphere not found, a saturated highlight, a module no
            highlight sees (naming the file or module).
    """
    folder = Path(folder)
    session = read_json_object(folder / "session.json")
    try:
        radius = float(session["radius_mm"])
        positions = int(session["positions"])
        exposures = {kind: {camera.id: float(session["exposures"][kind][camera.id]) for camera in rig.cameras}
                     for kind in ("ambient", "leds")}
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"'{folder / 'session.json'}': missing or bad field {exc}") from None
    if not (radius > 0 and positions >= 1):
        raise ValueError(f"'{folder / 'session.json'}': radius_mm must be > 0 and positions >= 1")
    pinholes = {camera.id: camera.pinhole() for camera in rig.cameras}
    skipped: list[str] = []
    silhouettes, highlights, centres = [], [], []
    for index in range(positions):
        cones, centre = _silhouettes(folder, index, rig, exposures["ambient"], radius, skipped)
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
            rig, result = calibrate_lights(session / step, rig)
            report["steps"][step] = result.to_dict(rig)
        rig.save(Path(out))
    return report


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
    for step in report["skipped"]:
        lines.append(f"{step}: no folder in the session; left as the nominal rig has it")
    return "\n".join(lines)
