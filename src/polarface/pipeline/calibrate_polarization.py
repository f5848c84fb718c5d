"""The ``polarface calibrate-polarization`` job: a folder of raw frames of a polarized target -> the
camera's analyzer calibration in ``rig.json`` (procedure and folder format:
``docs/calibrate_polarization.md``; estimator: :mod:`polarface.capture.polarization_calibration`).

FRAMES folder, one raw mosaic per file (``.png``, ``.tif``/``.tiff`` integer counts, or ``.npy`` integer
arrays), at the camera's size and bit depth; the polarizer angle of each file comes from, in order:

1. ``FRAMES/frames.json``: ``{"frames": [{"file": "a.png", "polarizer_deg": 0.0, "exposure": 1.0}, ...]}``
   (``exposure`` optional, relative, divided out);
2. ``angles_deg`` (the command's ``--angles-deg``): one angle per raw file, files in name order;
3. the file names ``pol_<deg>[_<anything>].<suffix>``, e.g. ``pol_045.0.png``, ``pol_-10_b.tiff``.

The rig is written only after every frame has been read and the estimate has succeeded, atomically.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from polarface.capture.ingest import RAW_SUFFIXES
from polarface.capture.manifest import raw_bit_depth_ok
from polarface.capture.polarization_calibration import (
    PolarizationCalibration,
    PolarizationCalibrationOptions,
    calibrate_analyzers,
)
from polarface.capture.rig import AnalyzerCalibration, Camera, Rig
from polarface.io import read_json_object
from polarface.io.images import read_png
from polarface.io.output_folder import output_file

__all__ = [
    "FRAMES_JSON",
    "POLARIZATION_FRAME_SUFFIXES",
    "PolarizationFrame",
    "calibrate_polarization",
    "format_polarization_table",
    "polarization_report",
    "read_polarization_frames",
]

#: The optional listing of a FRAMES folder.
FRAMES_JSON = "frames.json"
#: Raw frame suffixes of a FRAMES folder.
POLARIZATION_FRAME_SUFFIXES = (*RAW_SUFFIXES, ".npy")
_NAME_PATTERN = re.compile(r"^pol_([+-]?\d+(?:\.\d+)?)(?:_.*)?$")
_COMMAND = "calibrate-polarization"


@dataclasses.dataclass(frozen=True)
class PolarizationFrame:
    """One raw frame of a FRAMES folder: its file, polarizer angle (degrees) and relative exposure."""

    path: Path
    polarizer_deg: float
    exposure: float = 1.0


def _raw_files(folder: Path) -> list[Path]:
    return sorted(
        p for p in folder.iterdir()
        if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in POLARIZATION_FRAME_SUFFIXES
    )


def _from_listing(folder: Path) -> list[PolarizationFrame]:
    listing = folder / FRAMES_JSON
    entries = read_json_object(listing).get("frames")
    if not isinstance(entries, list) or not entries:
        raise ValueError(f"'{listing}': field 'frames' must be a non-empty list of {{file, polarizer_deg}}")
    frames = []
    for i, entry in enumerate(entries):
        try:
            name, angle = entry["file"], float(entry["polarizer_deg"])
            exposure = float(entry.get("exposure", 1.0))
        except (TypeError, KeyError, ValueError) as exc:
            raise ValueError(
                f"'{listing}': frames[{i}] needs 'file' and a numeric 'polarizer_deg' ({exc})"
            ) from None
        if not isinstance(name, str) or Path(name).name != name:
            raise ValueError(
                f"'{listing}': frames[{i}].file must be a file name inside the folder; got {name!r}"
            )
        if not (math.isfinite(angle) and math.isfinite(exposure) and exposure > 0):
            raise ValueError(f"'{listing}': frames[{i}] needs a finite polarizer_deg and an exposure > 0")
        frames.append(PolarizationFrame(folder / name, angle, exposure))
    return frames


def read_polarization_frames(
    folder: str | os.PathLike[str], angles_deg: Sequence[float] | None = None
) -> list[PolarizationFrame]:
    """The frames of a FRAMES folder with their polarizer angles (module docstring), not yet decoded.

    Raises:
        FileNotFoundError: the folder or a listed file does not exist.
        ValueError: no raw frames, a bad ``frames.json``, ``angles_deg`` not matching the files, or a file
            name without an angle (each naming the file or argument).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"frames folder '{folder}' does not exist")
    if (folder / FRAMES_JSON).exists():
        if angles_deg is not None:
            raise ValueError(f"argument '--angles-deg' conflicts with '{folder / FRAMES_JSON}'; give one")
        frames = _from_listing(folder)
    else:
        files = _raw_files(folder)
        if not files:
            raise ValueError(
                f"frames folder '{folder}' holds no raw frames ({', '.join(POLARIZATION_FRAME_SUFFIXES)})"
            )
        if angles_deg is not None:
            if len(angles_deg) != len(files):
                raise ValueError(
                    f"argument '--angles-deg' gives {len(angles_deg)} angles for {len(files)} raw frames in "
                    f"'{folder}' (one per file, in name order)"
                )
            frames = [PolarizationFrame(p, float(a)) for p, a in zip(files, angles_deg, strict=True)]
        else:
            frames = []
            for path in files:
                match = _NAME_PATTERN.match(path.stem)
                if match is None:
                    raise ValueError(
                        f"raw frame '{path}' carries no polarizer angle: name it pol_<deg>.<suffix> "
                        f"(e.g. pol_045.0.png), list it in {FRAMES_JSON}, or pass --angles-deg"
                    )
                frames.append(PolarizationFrame(path, float(match.group(1))))
    for frame in frames:
        if not frame.path.is_file():
            raise FileNotFoundError(f"raw frame '{frame.path}' does not exist")
    return frames


def _read_raw(path: Path, camera: Camera) -> np.ndarray:
    try:
        if path.suffix.lower() == ".npy":
            raw = np.load(path, allow_pickle=False)
        else:
            raw = read_png(path)
        raw_bit_depth_ok(np.asarray(raw), camera)
    except (OSError, ValueError, EOFError) as exc:
        raise ValueError(f"raw frame '{path}': {exc}") from None
    return raw


def _merged_analyzer(camera: Camera, result: PolarizationCalibration) -> Any:
    """The new ``analyzer`` value; a per-colour subset keeps the camera's other colours."""
    new = result.analyzer_field()
    if isinstance(new, AnalyzerCalibration):
        return new
    old = camera.analyzer
    if isinstance(old, AnalyzerCalibration):
        return {colour: old for colour in ("R", "G", "B")} | new
    return (dict(old) if isinstance(old, dict) else {}) | new


def _updated_rig(rig: Rig, camera: Camera, result: PolarizationCalibration) -> Rig:
    data = rig.model_dump(mode="json")
    index = [c.id for c in rig.cameras].index(camera.id)
    merged = _merged_analyzer(camera, result)
    data["cameras"][index]["analyzer"] = (
        merged.model_dump(mode="json") if isinstance(merged, AnalyzerCalibration)
        else {c: entry.model_dump(mode="json") for c, entry in merged.items()}
    )
    return Rig.model_validate(data)


def calibrate_polarization(
    frames_dir: str | os.PathLike[str],
    rig_path: str | os.PathLike[str],
    camera_id: str,
    *,
    angles_deg: Sequence[float] | None = None,
    options: PolarizationCalibrationOptions | None = None,
    out: str | os.PathLike[str] | None = None,
    force: bool = False,
) -> PolarizationCalibration:
    """Calibrate ``camera_id``'s analyzers from ``frames_dir`` and write them into the rig.

    Args:
        frames_dir: the FRAMES folder (module docstring).
        rig_path: ``rig.json`` holding the camera.
        camera_id: a polarization camera of the rig.
        angles_deg: polarizer angles of the files in name order (when there is no ``frames.json``).
        options: estimator settings.
        out: rig file to write (default: update ``rig_path`` in place). An existing other file is refused
            unless ``force``; a file inside ``frames_dir`` is refused.
        force: replace an existing ``out`` that is not ``rig_path``.

    Returns:
        The estimate (:class:`polarface.capture.polarization_calibration.PolarizationCalibration`).

    Raises:
        FileNotFoundError, ValueError: naming the file, camera or argument at fault; nothing is written.
    """
    rig_path = Path(rig_path)
    rig = Rig.load(rig_path)
    camera = rig.camera(camera_id)
    if camera.sensor == "rgb":
        raise ValueError(f"camera '{camera_id}' has an rgb sensor; --camera must name a polarization camera")
    if camera.sensor == "mono-polarization" and options is not None and options.colours is not None:
        raise ValueError(
            f"argument '--colours': camera '{camera_id}' is mono-polarization; it has no colours"
        )
    frames = read_polarization_frames(frames_dir, angles_deg)
    target = Path(out) if out is not None else rig_path
    same = target.exists() and target.resolve() == rig_path.resolve()
    # the output may be --rig itself (updated in place by design), never a file inside FRAMES
    with output_file(target, _COMMAND, force=force, owned=lambda _: same, inputs={"FRAMES": frames_dir}):
        raws = [_read_raw(frame.path, camera) for frame in frames]
        result = calibrate_analyzers(
            raws,
            [frame.polarizer_deg for frame in frames],
            camera,
            options,
            names=[str(frame.path) for frame in frames],
            exposures=[frame.exposure for frame in frames],
        )
        _updated_rig(rig, camera, result).save(target)
    return result


def polarization_report(result: PolarizationCalibration) -> dict[str, Any]:
    """JSON-ready summary: per colour the stored values and the per-analyzer diagnostics (gains too)."""

    def plain(values: np.ndarray) -> list[float | None]:
        return [float(v) if math.isfinite(v) else None for v in np.asarray(values, dtype=np.float64)]

    colours = {}
    for colour, fit in result.fits.items():
        lower, upper = fit.extinction_ratio_bounds
        colours[colour or "mono"] = {
            **fit.calibration().model_dump(mode="json"),
            "extinction_ratio_95_bounds": plain(np.array([lower, upper])),
            "analyzer_extinction_ratios": plain(fit.extinction_ratios),
            "analyzer_diattenuation": plain(fit.diattenuation),
            "analyzer_diattenuation_std": plain(fit.diattenuation_std),
            "analyzer_gains": plain(fit.gains),
            "analyzer_gains_std": plain(fit.gains_std),
            "angle_offset_deg": fit.angle_offset_deg,
            "residual_rms": fit.residual_rms,
            "super_pixels": fit.pixels,
        }
    return {
        "camera": result.camera_id,
        "polarizer_deg": list(result.polarizer_deg),
        "roi": list(result.roi),
        "colours": colours,
    }


def format_polarization_table(result: PolarizationCalibration) -> str:
    """A fixed-width text table: one row per colour and analyzer (angle, ER, gain with one-sigma)."""

    def pm(value: float, sigma: float, digits: int) -> str:
        if not math.isfinite(value):
            return "inf"
        return f"{value:.{digits}f} +- {sigma:.{digits}f}" if math.isfinite(sigma) else f"{value:.{digits}f}"

    lines = [
        f"camera {result.camera_id}: {len(result.polarizer_deg)} frames, roi x,y,w,h = "
        f"{','.join(str(v) for v in result.roi)}",
        f"{'colour':<7}{'analyzer':>9}{'angle_deg':>22}{'extinction_ratio':>24}{'gain (not stored)':>22}",
    ]
    for colour, fit in result.fits.items():
        for k, nominal in enumerate((0, 45, 90, 135)):
            ratio = float(fit.extinction_ratios[k])
            d, sd = fit.diattenuation[k], fit.diattenuation_std[k]
            ratio_sd = 2 * sd / (1 - d) ** 2 if d < 1 else math.inf
            lines.append(
                f"{colour or 'mono':<7}{nominal:>9}{pm(fit.angles_deg[k], fit.angles_std_deg[k], 3):>22}"
                f"{pm(ratio, ratio_sd, 1):>24}{pm(fit.gains[k], fit.gains_std[k], 4):>22}"
            )
        lower, upper = fit.extinction_ratio_bounds
        lines.append(
            f"{colour or 'mono':<7}{'stored':>9}{'':>22}"
            f"{pm(fit.extinction_ratio, fit.extinction_ratio_std, 1):>24}"
            f"   95% bounds {lower:.1f}..{upper:.1f}"
            + (f", angle offset removed {fit.angle_offset_deg:.3f} deg" if fit.angle_offset_deg else "")
        )
    return "\n".join(lines)
