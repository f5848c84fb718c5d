"""Demosaic one raw polarization frame into analyzer, DoP and AoLP images: the ``polarface stokes`` job.

Outputs in the folder: ``i0.exr i45.exr i90.exr i135.exr dop.exr aolp.exr`` (float32; ``Y`` for a mono
sensor, ``R G B`` for a colour one; AoLP in radians in [0, pi)), ``saturated.png`` (255 where a
sample was at the white level), colour-mapped previews ``*.png`` and ``summary.json``. Every file is
written atomically (:mod:`polarface.io.atomic`). With a rig camera (``StokesOptions.rig`` and
``camera``) whose ``analyzer`` calibration is not ideal, the analyzer images are mapped to ideal
analyzers first (:func:`polarface.capture.analyzers.ideal_analyzer_intensities`, as in the capture
store; ``docs/sensors.md``), so DoP and AoLP are unbiased; ``summary.json`` records the model applied.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import numpy as np

from polarface.capture.analyzers import analyzer_record, camera_analyzer_models, ideal_analyzer_intensities
from polarface.capture.demosaic import DEMOSAIC_METHODS, DemosaicMethod, check_phase, demosaic
from polarface.capture.observations import observations_from_intensities
from polarface.capture.rig import Camera, Rig
from polarface.io import colormap_png, read_png, write_exr, write_json_atomic, write_png

__all__ = ["StokesOptions", "write_stokes_images"]


@dataclasses.dataclass(frozen=True)
class StokesOptions:
    """How :func:`write_stokes_images` reads the raw mosaic (see :func:`polarface.capture.demosaic.demosaic`).

    Attributes:
        method: demosaicing method, ``"residual"`` or ``"bilinear"``.
        bit_depth: ADC bit depth; None: 8 for an 8-bit file, else 16.
        black_level: ADC offset, counts.
        white_level: saturation count; None: ``2**bit_depth - 1``.
        phase: mosaic phase ``(row, col)`` of the readout.
        exposure: relative exposure to divide by (> 0).
        rig, camera: a ``rig.json`` and the id of the camera that took the frame, whose ``analyzer``
            calibration is applied (both or neither; None: ideal analyzers).
    """

    method: DemosaicMethod = "residual"
    bit_depth: int | None = None
    black_level: float = 0.0
    white_level: float | None = None
    phase: tuple[int, int] = (0, 0)
    exposure: float = 1.0
    rig: str | os.PathLike[str] | None = None
    camera: str | None = None

    def __post_init__(self) -> None:
        """Check the options before any work (ValueError naming the argument); the phase is checked
        against the sensor's mosaic period by :func:`write_stokes_images`."""
        if self.method not in DEMOSAIC_METHODS:
            raise ValueError(f"argument 'method' must be one of {DEMOSAIC_METHODS}; got {self.method!r}")
        if self.bit_depth is not None and not 1 <= self.bit_depth <= 16:
            raise ValueError(f"argument 'bit_depth' must lie in 1..16; got {self.bit_depth}")
        if not (math.isfinite(self.black_level) and self.black_level >= 0):
            raise ValueError(f"argument 'black_level' must be finite and >= 0; got {self.black_level}")
        if self.white_level is not None and not (
            math.isfinite(self.white_level) and self.white_level > self.black_level
        ):
            raise ValueError(
                f"argument 'white_level' must be finite and above black_level ({self.black_level}); "
                f"got {self.white_level}"
            )
        if not (math.isfinite(self.exposure) and self.exposure > 0):
            raise ValueError(f"argument 'exposure' must be finite and > 0; got {self.exposure}")
        if (self.rig is None) != (self.camera is None):
            raise ValueError("arguments 'rig' and 'camera' go together: give both (the camera's analyzer "
                             "calibration is applied) or neither (ideal analyzers)")


def _rig_camera(options: StokesOptions, sensor: str) -> Camera | None:
    """The rig camera of ``options`` (checked against ``sensor``), or None without a rig."""
    if options.rig is None:
        return None
    camera = Rig.load(options.rig).camera(str(options.camera))
    if camera.sensor != sensor:
        raise ValueError(
            f"argument 'camera': camera '{camera.id}' of '{options.rig}' has sensor {camera.sensor!r}, "
            f"not {sensor!r}"
        )
    return camera


def _preview_intensity(image: np.ndarray, scale: float) -> np.ndarray:
    """Gamma-2.2 preview in [0, 1] of a linear image divided by ``scale``."""
    return np.clip(image / scale, 0.0, 1.0) ** (1 / 2.2)


def write_stokes_images(
    raw_path: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    sensor: str,
    options: StokesOptions = StokesOptions(),
) -> dict:
    """Demosaic the raw mosaic at ``raw_path`` and write the images listed in the module docstring.

    Args:
        raw_path: single-channel PNG or TIFF mosaic (8- or 16-bit counts).
        out_dir: output folder (created).
        sensor: ``"mono-polarization"`` or ``"color-polarization"``.
        options: :class:`StokesOptions`.

    Returns:
        The ``summary.json`` content: saturated fraction, repaired defects, median DoP and mean s0 over
        the unsaturated pixels (None for both when every pixel is saturated).

    Raises:
        ValueError: an unknown sensor, a phase outside the mosaic period (checked before the file is
            read), a multi-channel file, or a mosaic that :func:`demosaic` rejects; an invalid rig, or a
            camera not in it or of another sensor.
        FileNotFoundError: the raw file or the rig does not exist.
    """
    check_phase(sensor, options.phase)
    camera = _rig_camera(options, sensor)
    raw = read_png(raw_path)
    if raw.ndim != 2:
        raise ValueError(f"raw file '{raw_path}' must be a single-channel mosaic; got shape {raw.shape}")
    bit_depth = options.bit_depth or (8 if raw.dtype == np.uint8 else 16)
    stack = demosaic(
        raw,
        sensor,
        method=options.method,
        phase=tuple(options.phase),
        black_level=options.black_level,
        white_level=options.white_level,
        bit_depth=bit_depth,
        exposure=options.exposure,
    )
    if camera is not None:
        stack = dataclasses.replace(
            stack, intensities=ideal_analyzer_intensities(stack.intensities, camera_analyzer_models(camera))
        )
    obs = observations_from_intensities(*stack.intensities)
    colour = stack.intensities.ndim == 4
    names = ["R", "G", "B"] if colour else ["Y"]
    valid = ~stack.saturated
    finite = stack.intensities[:, valid] if valid.any() else stack.intensities
    scale = float(np.percentile(finite, 99.5)) or 1.0
    s0 = stack.intensities.sum(axis=0) / 2.0
    summary_s0 = s0.mean(axis=-1) if colour else s0
    grey = observations_from_intensities(*(stack.intensities.mean(axis=-1) if colour else stack.intensities))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for label, image in zip(("i0", "i45", "i90", "i135"), stack.intensities, strict=True):
        write_exr(out / f"{label}.exr", image, names)
        write_png(out / f"{label}.png", _preview_intensity(image, scale))
    write_exr(out / "dop.exr", obs["dop"], names)
    write_exr(out / "aolp.exr", obs["aolp"], names)
    colormap_png(out / "dop.png", grey["dop"], vmin=0.0, vmax=1.0, cmap="viridis", mask=valid)
    colormap_png(out / "aolp.png", grey["aolp"], vmin=0.0, vmax=np.pi, cmap="twilight", mask=valid)
    write_png(out / "saturated.png", stack.saturated.astype(np.uint8) * 255)
    summary = {
        "raw": str(raw_path),
        "sensor": sensor,
        "method": options.method,
        "bit_depth": bit_depth,
        "shape": list(raw.shape),
        "analyzer": None if camera is None else analyzer_record(camera),
        "saturated_fraction": float(stack.saturated.mean()),
        "defects_repaired": int(stack.defects.sum()),
        "median_dop": float(np.median(grey["dop"][valid])) if valid.any() else None,
        "mean_s0": float(summary_s0[valid].mean()) if valid.any() else None,
    }
    write_json_atomic(out / "summary.json", summary)
    return summary
