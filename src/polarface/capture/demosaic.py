"""Demosaicing of polarization raw frames to full-resolution I0, I45, I90, I135.

Two methods, both vectorised (OpenCV filters and warps on the sub-lattices of the mosaic):

``"bilinear"``
    Each rectangular sub-lattice (see :func:`polarface.capture.sensor.lattices`) is interpolated
    bilinearly to full resolution; the colour sensor's green channel averages its two lattices.
    Affine intensity fields are reproduced exactly away from the border.

``"residual"`` (default)
    Residual interpolation (RI; Kiku et al., "Residual interpolation for color image demosaicking",
    ICIP 2013), the family that Morimatsu et al., "Monochrome and color polarization demosaicking
    using edge-aware residual interpolation", ICIP 2020, adapt to polarization sensors and that the
    paper uses (supplement, "Additional discussion"). A full-resolution intensity guide is the
    symmetric tent average of all lattices (mono: (I0 + I45 + I90 + I135) / 4; colour: the same with
    R + 2G + B weights). For every lattice a guided filter (He et al., TPAMI 2013) fitted on the
    lattice samples gives a local linear model ``I ~ a G + b`` (edge-aware: it follows the guide's
    edges); the residual ``I - (a G + b)`` at the samples is interpolated bilinearly and added back.
    For affine fields the fitted ``a`` is constant and ``b`` affine, so affine fields are again
    reproduced exactly away from the border. Pixels whose guided-filter window touches saturated
    samples fall back to the bilinear estimate. Measured errors: ``docs/capture_store.md``.

Output radiometry: ``(raw - black_level) / (white_level - black_level) / exposure`` in float32,
i.e. 1.0 = the saturation level at unit exposure (the signal unit of
:func:`polarface.capture.sensor.simulate_raw`).

Non-ideal analyzers (``docs/sensors.md``): :func:`demosaic_camera` maps the demosaiced intensities of
a camera whose ``rig.json`` carries an ``analyzer`` calibration to those ideal 0/45/90/135 deg
analyzers would have measured (:func:`polarface.capture.analyzers.ideal_analyzer_intensities`: the
least-squares analysis matrix of :class:`polarface.optics.analyzer.AnalyzerModel`), per colour for a
colour camera, so every stage downstream keeps its ideal-analyzer formulas. Ideal cameras are passed
through bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Literal

import cv2
import numpy as np

from polarface.capture.analyzers import camera_analyzer_models, ideal_analyzer_intensities
from polarface.capture.sensor import Lattice, lattices, pattern_period

if TYPE_CHECKING:
    from polarface.capture.rig import Camera

__all__ = [
    "DEMOSAIC_METHODS", "PolarizationStack", "applied_gains", "check_phase", "demosaic", "demosaic_camera",
]

DemosaicMethod = Literal["bilinear", "residual"]
#: Available demosaicing methods.
DEMOSAIC_METHODS: tuple[str, ...] = ("bilinear", "residual")
_GUIDED_RADIUS = 2  # guided-filter window radius, in lattice samples
_GUIDED_EPS = 1e-4  # guided-filter regulariser, squared normalised intensity
_DEFECT_FLOOR = 0.02  # smallest defect excursion, normalised units (~80 counts at 12 bit)


@dataclass(frozen=True)
class PolarizationStack:
    """Demosaiced analyzer images of one frame of one camera.

    Attributes:
        intensities: float32 ``(4, H, W)`` (mono) or ``(4, H, W, 3)`` (colour, R G B), ordered
            I0, I45, I90, I135; linear, black level removed, exposure normalised (1.0 = white level
            at unit exposure), camera image frame (pixel rows down, columns right).
        saturated: bool ``(H, W)``: some raw sample used for the pixel (any angle, any colour) was
            at the white level.
        defects: bool ``(H, W)``: raw pixels found dead/hot (or given as defective) and repaired.
    """

    intensities: np.ndarray
    saturated: np.ndarray
    defects: np.ndarray

    @property
    def i0(self) -> np.ndarray:
        """Co-polarized image (analyzer 0 deg)."""
        return self.intensities[0]

    @property
    def i45(self) -> np.ndarray:
        """Analyzer 45 deg image."""
        return self.intensities[1]

    @property
    def i90(self) -> np.ndarray:
        """Cross-polarized image (analyzer 90 deg)."""
        return self.intensities[2]

    @property
    def i135(self) -> np.ndarray:
        """Analyzer 135 deg image."""
        return self.intensities[3]

    @property
    def valid(self) -> np.ndarray:
        """bool ``(H, W)``: not saturated."""
        return ~self.saturated


def _validate_raw(raw: np.ndarray, sensor: str, bit_depth: int | None, white_level: float) -> np.ndarray:
    raw = np.asarray(raw)
    if raw.ndim != 2:
        raise ValueError(f"argument 'raw' must be a (H, W) mosaic; got shape {raw.shape}")
    if raw.dtype == np.bool_ or not np.issubdtype(raw.dtype, np.number):
        raise ValueError(f"argument 'raw' must be numeric; got dtype {raw.dtype}")
    period = pattern_period(sensor)
    height, width = raw.shape
    if height % period or width % period or height < 2 * period or width < 2 * period:
        raise ValueError(
            f"argument 'raw' has shape {raw.shape}; a {sensor} mosaic needs both dimensions to be "
            f"multiples of {period} and at least {2 * period}"
        )
    if np.issubdtype(raw.dtype, np.floating):
        if not np.isfinite(raw).all():
            raise ValueError(
                f"argument 'raw' contains {int((~np.isfinite(raw)).sum())} NaN or infinite value(s)"
            )
    elif bit_depth is not None and bit_depth > 8 and raw.dtype == np.uint8:
        raise ValueError(f"argument 'raw' is 8-bit but the camera declares bit_depth {bit_depth}")
    if raw.size and (raw.min() < 0 or raw.max() > white_level):
        raise ValueError(
            f"argument 'raw' values must lie in [0, white_level={white_level:g}]; "
            f"got {raw.min()}..{raw.max()} (wrong bit depth?)"
        )
    return raw


def _upsample(sub: np.ndarray, lattice: Lattice, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear interpolation of a lattice image ``sub`` to the full ``(H, W)`` pixel grid."""
    p = lattice.period
    matrix = np.array([[1.0 / p, 0.0, -lattice.col0 / p], [0.0, 1.0 / p, -lattice.row0 / p]])
    return cv2.warpAffine(
        sub,
        matrix,
        (shape[1], shape[0]),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )


def _tent(period: int) -> np.ndarray:
    """1-D tent of half-width ``period`` normalised so that every lattice gets weight 1 / period."""
    taps = 1.0 - np.abs(np.arange(-period + 1, period)) / period
    return (taps / period).astype(np.float32)


def _box(image: np.ndarray, radius: int) -> np.ndarray:
    return cv2.boxFilter(image, -1, (2 * radius + 1, 2 * radius + 1), borderType=cv2.BORDER_REFLECT)


def _guided_residual(sub: np.ndarray, guide: np.ndarray, lat: Lattice) -> tuple[np.ndarray, np.ndarray]:
    """Guided-filter slope ``a`` and offset-plus-residual ``b + r`` of one lattice (RI step)."""
    period = lat.period
    guide_sub = guide[lat.row0 :: period, lat.col0 :: period].astype(np.float64)
    sub = sub.astype(np.float64)  # window moments in float64: no cancellation in var = E[g^2] - E[g]^2
    mean_g = _box(guide_sub, _GUIDED_RADIUS)
    mean_i = _box(sub, _GUIDED_RADIUS)
    var_g = _box(guide_sub * guide_sub, _GUIDED_RADIUS) - mean_g * mean_g
    cov = _box(guide_sub * sub, _GUIDED_RADIUS) - mean_g * mean_i
    slope = cov / (np.maximum(var_g, 0.0) + _GUIDED_EPS)
    offset = mean_i - slope * mean_g
    slope = _box(slope, _GUIDED_RADIUS)
    offset = _box(offset, _GUIDED_RADIUS)
    residual = sub - (slope * guide_sub + offset)
    return slope.astype(np.float32), (offset + residual).astype(np.float32)


def _repair_defects(sub: np.ndarray, sat: np.ndarray, threshold: float) -> np.ndarray:
    """Flag lattice samples beyond their 8 lattice neighbours' range by more than
    ``max(_DEFECT_FLOOR, threshold * local median)`` (normalised units)."""
    ring = np.ones((3, 3), np.uint8)
    ring[1, 1] = 0
    high = cv2.dilate(sub, ring, borderType=cv2.BORDER_REFLECT)
    low = cv2.erode(sub, ring, borderType=cv2.BORDER_REFLECT)
    margin = np.maximum(np.float32(_DEFECT_FLOOR), np.float32(threshold) * cv2.medianBlur(sub, 3))
    return ((sub > high + margin) | (sub < low - margin)) & ~sat


def demosaic(
    raw: np.ndarray,
    sensor: str = "mono-polarization",
    *,
    method: DemosaicMethod = "residual",
    phase: tuple[int, int] = (0, 0),
    black_level: float = 0.0,
    white_level: float | None = None,
    bit_depth: int | None = None,
    exposure: float = 1.0,
    defect_threshold: float | None = 0.5,
    defect_mask: np.ndarray | None = None,
) -> PolarizationStack:
    """Demosaic one raw polarization frame (see the module docstring for the methods).

    Args:
        raw: ``(H, W)`` raw counts (uint8/uint16/int) or float counts; H and W multiples of the
            pattern period (2 mono, 4 colour).
        sensor: ``"mono-polarization"`` (IMX250MZR) or ``"color-polarization"`` (IMX250MYR).
        method: ``"residual"`` (default) or ``"bilinear"``.
        phase: pattern phase ``(row, col)`` of the readout.
        black_level: ADC offset in counts, subtracted.
        white_level: saturation count; default ``2**bit_depth - 1``, or the integer dtype's maximum
            when ``bit_depth`` is None (float frames need ``white_level`` or ``bit_depth``).
        bit_depth: declared ADC bit depth; an 8-bit array for a deeper camera is an error.
        exposure: relative exposure to divide by (> 0).
        defect_threshold: a sample further than ``max(0.02, defect_threshold * m)`` above the
            maximum or below the minimum of its 8 same-filter neighbours (``m`` their median;
            normalised units, 1 = full scale) is flagged dead/hot and replaced by the median of its
            3x3 same-filter neighbourhood; None disables detection.
        defect_mask: optional bool ``(H, W)`` of known defective raw pixels (repaired the same way).

    Returns:
        :class:`PolarizationStack`.

    Raises:
        ValueError: on a bad shape, odd dimensions, NaN/inf, values beyond the white level, an 8-bit
            frame for a deeper declared bit depth, or bad levels/exposure.
    """
    if method not in DEMOSAIC_METHODS:
        raise ValueError(f"argument 'method' must be one of {DEMOSAIC_METHODS}; got {method!r}")
    white_level = _white_level(raw, white_level, bit_depth)
    if not np.isfinite(black_level) or not black_level < white_level:
        raise ValueError(f"argument 'black_level' ({black_level}) must be below white_level ({white_level})")
    if not (np.isfinite(exposure) and exposure > 0):
        raise ValueError(f"argument 'exposure' must be > 0; got {exposure}")
    raw = _validate_raw(raw, sensor, bit_depth, white_level)
    scale = 1.0 / ((white_level - black_level) * exposure)
    saturated_raw = raw >= white_level
    values = ((raw.astype(np.float32) - np.float32(black_level)) * np.float32(scale)).astype(np.float32)
    lats = lattices(sensor, phase)
    defects = _repair_defects_in_place(values, saturated_raw, lats, defect_mask, defect_threshold)
    period = lats[0].period
    support = 2 * period - 1
    saturated = cv2.dilate(saturated_raw.astype(np.uint8), np.ones((support, support), np.uint8)) > 0
    out = _interpolate_lattices(values, saturated_raw, saturated, lats, method)
    return PolarizationStack(intensities=out, saturated=saturated, defects=defects)


def check_phase(sensor: str, phase: tuple[int, int]) -> tuple[int, int]:
    """``phase`` as ``(row, col)`` ints with ``0 <= row, col < period`` of the sensor's mosaic (2 mono,
    4 colour); ValueError naming argument 'phase' otherwise. (:func:`demosaic` itself takes any integer
    phase modulo the period; user-facing jobs use this to reject a phase that is surely a typo.)"""
    period = pattern_period(sensor)
    try:
        row, col = (int(v) for v in phase)
    except (TypeError, ValueError):
        raise ValueError(f"argument 'phase' must be two integers (row, col); got {phase!r}") from None
    if not (0 <= row < period and 0 <= col < period):
        raise ValueError(
            f"argument 'phase' must lie in 0..{period - 1} per axis (the {sensor} mosaic period is "
            f"{period}); got ({row}, {col})"
        )
    return row, col


def _white_level(raw: np.ndarray, white_level: float | None, bit_depth: int | None) -> float:
    """``white_level``, else ``2**bit_depth - 1``, else the integer dtype's maximum (float frames raise)."""
    if white_level is None:
        if bit_depth is not None:
            white_level = float(2**bit_depth - 1)
        elif np.issubdtype(np.asarray(raw).dtype, np.integer):
            white_level = float(np.iinfo(np.asarray(raw).dtype).max)
        else:
            raise ValueError("argument 'white_level' (or 'bit_depth') is required for a float raw frame")
    return white_level


def _repair_defects_in_place(
    values: np.ndarray,
    saturated_raw: np.ndarray,
    lats: list[Lattice],
    defect_mask: np.ndarray | None,
    defect_threshold: float | None,
) -> np.ndarray:
    """Find dead/hot samples (given and detected) and replace them in ``values`` (float32 ``(H, W)``,
    modified in place) by the median of their 3x3 same-filter neighbourhood; returns bool ``(H, W)``."""
    shape = values.shape
    period = lats[0].period
    defects = np.zeros(shape, dtype=bool)
    if defect_mask is not None:
        defect_mask = np.asarray(defect_mask, dtype=bool)
        if defect_mask.shape != shape:
            raise ValueError(f"argument 'defect_mask' must have shape {shape}; got {defect_mask.shape}")
        defects |= defect_mask & ~saturated_raw
    if defect_threshold is not None:
        for lat in lats:
            sl = (slice(lat.row0, None, period), slice(lat.col0, None, period))
            defects[sl] |= _repair_defects(values[sl], saturated_raw[sl], float(defect_threshold))
    if defects.any():
        for lat in lats:
            sl = (slice(lat.row0, None, period), slice(lat.col0, None, period))
            bad = defects[sl]
            if bad.any():
                values[sl] = np.where(bad, cv2.medianBlur(np.ascontiguousarray(values[sl]), 3), values[sl])
    return defects


def _interpolate_lattices(
    values: np.ndarray,
    saturated_raw: np.ndarray,
    saturated: np.ndarray,
    lats: list[Lattice],
    method: DemosaicMethod,
) -> np.ndarray:
    """Full-resolution float32 ``(4, H, W[, 3])`` analyzer images from the normalised mosaic ``values``
    (module docstring: bilinear, or residual interpolation with a bilinear fallback near saturation)."""
    shape = values.shape
    period = lats[0].period
    colour = lats[0].colour is not None
    out = np.empty((4, *shape, 3) if colour else (4, *shape), dtype=np.float32)
    guide = fallback = None
    if method == "residual":
        tent = _tent(period)
        guide = cv2.sepFilter2D(values, -1, tent, tent, borderType=cv2.BORDER_REFLECT_101)
        wide = 2 * period * (2 * _GUIDED_RADIUS + 1) + 1
        fallback = (
            cv2.dilate(saturated_raw.astype(np.uint8), np.ones((wide, wide), np.uint8)) > 0
        ) & ~saturated
        if not fallback.any():
            fallback = None
    groups: dict[tuple[int, int], list[Lattice]] = {}
    for lat in lats:
        groups.setdefault((lat.angle, lat.colour or 0), []).append(lat)
    for (angle, channel), members in groups.items():
        slope_sum = offset_sum = None
        for lat in members:
            sub = np.ascontiguousarray(values[lat.row0 :: period, lat.col0 :: period])
            if method == "bilinear":
                slope_up, offset_up = None, _upsample(sub, lat, shape)
            else:
                slope, offset = _guided_residual(sub, guide, lat)
                slope_up = _upsample(slope, lat, shape)
                offset_up = _upsample(offset, lat, shape)
                if fallback is not None:
                    np.copyto(offset_up, _upsample(sub, lat, shape), where=fallback)
                    slope_up[fallback] = 0.0
            if offset_sum is None:
                offset_sum, slope_sum = offset_up, slope_up
            else:
                offset_sum += offset_up
                if slope_up is not None:
                    slope_sum += slope_up
        if slope_sum is not None:
            slope_sum *= guide
            offset_sum += slope_sum
        if len(members) > 1:
            offset_sum *= np.float32(1.0 / len(members))
        if colour:
            out[angle, ..., channel] = offset_sum
        else:
            out[angle] = offset_sum
    return out


def demosaic_camera(
    raw: np.ndarray,
    camera: Camera,
    *,
    method: DemosaicMethod = "residual",
    exposure: float | None = None,
    **kwargs,
) -> PolarizationStack:
    """Demosaic a raw frame with the sensor, phase, levels and bit depth of a rig camera.

    Args:
        raw: ``(H, W)`` raw counts of ``camera`` (its width and height are checked).
        camera: a :class:`polarface.capture.rig_components.Camera` with a polarization sensor.
        method: demosaicing method.
        exposure: overrides ``camera.exposure``.
        **kwargs: passed to :func:`demosaic` (``defect_threshold``, ``defect_mask``).

    Returns:
        :class:`PolarizationStack` whose intensities are those of ideal analyzers: a camera with an
        ``analyzer`` calibration is corrected by
        :func:`polarface.capture.analyzers.ideal_analyzer_intensities` (module docstring); divided by
        the camera's ``channel_gains`` (R, G, B; a mono sensor: the first) when they are not 1.

    Raises:
        ValueError: for an ``rgb`` camera, or a frame whose size differs from the camera's.
    """
    if camera.sensor not in ("mono-polarization", "color-polarization"):
        raise ValueError(f"camera '{camera.id}' has sensor {camera.sensor!r}, not a polarization sensor")
    raw = np.asarray(raw)
    if raw.shape != (camera.height, camera.width):
        raise ValueError(
            f"raw frame of camera '{camera.id}' has shape {raw.shape}; the rig declares "
            f"(height, width) = ({camera.height}, {camera.width})"
        )
    stack = demosaic(
        raw,
        camera.sensor,
        method=method,
        phase=tuple(camera.pattern_phase),
        black_level=camera.black_level,
        white_level=camera.white_level,
        bit_depth=camera.bit_depth,
        exposure=camera.exposure if exposure is None else exposure,
        **kwargs,
    )
    corrected = ideal_analyzer_intensities(stack.intensities, camera_analyzer_models(camera))
    gains = np.asarray(camera.channel_gains, dtype=np.float32)
    if (gains != 1.0).any():
        corrected = corrected / (gains if camera.sensor == "color-polarization" else gains[0])
    return stack if corrected is stack.intensities else replace(stack, intensities=corrected)


def applied_gains(rig) -> dict[str, list[float]] | None:
    """Camera id -> ``channel_gains`` of the polarization cameras of ``rig`` whose gains are not 1 (what
    :func:`demosaic_camera` divides by; recorded in the capture store's manifest and frame markers);
    None when every gain is 1."""
    gains = {camera.id: list(camera.channel_gains) for camera in rig.cameras
             if camera.sensor != "rgb" and tuple(camera.channel_gains) != (1.0, 1.0, 1.0)}
    return gains or None
