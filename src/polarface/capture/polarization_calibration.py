"""Polarimetric calibration of a division-of-focal-plane camera: extinction ratio and analyzer angles.

Procedure (Powell and Gruev, "Calibration methods for division-of-focal-plane polarimeters", Optics
Express 21(18), 2013): a uniformly lit, fully linearly polarized target (a diffuse source behind a
rotating linear polarizer) is recorded at several known polarizer angles ``theta``. The signal of a
pixel behind analyzer ``k`` (black level removed, in units of the white level) follows

    ``I_k(theta) = g_k L (1 + d_k cos 2 (theta - a_k)) / 2  =  c0_k + c1_k cos 2 theta + c2_k sin 2 theta``

with ``L`` the source radiance, ``g_k`` the analyzer's gain, ``d_k = (ER_k - 1) / (ER_k + 1)`` its
diattenuation and ``a_k`` its orientation (the model of :class:`polarface.optics.analyzer.AnalyzerModel`
times a gain). It is linear in ``c = (c0, c1, c2)``: ``d = hypot(c1, c2) / c0``, ``a = atan2(c2, c1) / 2``,
``g ~ c0`` (relative; the absolute ``L`` is unknown). Three distinct polarizer angles (modulo 180 deg)
determine ``c``; more give residuals and so an uncertainty.

Estimation. Only pixels of the region of interest whose whole super-pixel (2x2 mono, 4x4 colour mosaic
period) stays below the white level in every frame are used, so every analyzer sees the same pixels.
Each analyzer's (and colour's) signal is averaged over those pixels per frame and fitted by linear
least squares; averaging before fitting avoids the upward bias of ``hypot`` on noisy per-pixel fits.
One-sigma uncertainties: the larger of (a) the least-squares covariance scaled by the residual variance,
propagated to ``d``, ``a``, ``g`` (needs four or more distinct angles) and (b) the spread of the same fit
over ``tiles x tiles`` tiles of the region divided by the square root of their number.

Angle reference. ``"polarizer"`` (default): the polarizer angles are absolute, measured from image +x
(``docs/conventions.md``), so the analyzer angles are too. ``"analyzers"``: the polarizer's zero is
unknown; the mean deviation of the analyzers from 0/45/90/135 deg is removed (reported as
``angle_offset_deg``), which keeps the relative orientations only.

``normalise_frames`` divides each frame by the mean of its analyzers (per colour): for sources whose
intensity differs between frames; it biases ``d`` and ``a`` by terms of the order of the orientation
errors (``docs/calibrate_polarization.md``), so the default is a stable source.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Literal

import numpy as np

from polarface.capture.rig import AnalyzerCalibration, Camera
from polarface.capture.sensor import lattices, pattern_period
from polarface.optics.analyzer import IDEAL_ANALYZER_ANGLES_DEG

__all__ = [
    "AnalyzerFit",
    "PolarizationCalibration",
    "PolarizationCalibrationOptions",
    "calibrate_analyzers",
    "central_roi",
]

COLOUR_NAMES = ("R", "G", "B")
_MIN_DIATTENUATION = 0.1  # extinction ratio 1.22: below it the frames do not see a polarizer
_ONE_SIDED_95 = 1.6448536269514722  # normal quantile of the one-sided 95 % bounds


@dataclasses.dataclass(frozen=True)
class PolarizationCalibrationOptions:
    """Settings of :func:`calibrate_analyzers` (defaults: the documented procedure).

    Attributes:
        roi: ``(x, y, width, height)`` pixels of the region used, shrunk to whole mosaic periods; None:
            the central half of the frame in each direction (:func:`central_roi`).
        colours: colours to calibrate (subset of R, G, B; colour sensors only); None: R, G, B for a
            colour sensor, one camera-wide calibration for a mono sensor.
        angle_reference: ``"polarizer"`` (polarizer angles absolute) or ``"analyzers"`` (mean analyzer
            deviation from nominal removed); see the module docstring.
        normalise_frames: divide each frame by its mean over the analyzers (unstable sources).
        tiles: tiles per side of the region for the spread uncertainty (>= 1).
        min_signal: smallest mean signal of a frame, as a fraction of the white level above black.
        min_pixels: fewest unsaturated super-pixels needed in the region.
    """

    roi: tuple[int, int, int, int] | None = None
    colours: tuple[str, ...] | None = None
    angle_reference: Literal["polarizer", "analyzers"] = "polarizer"
    normalise_frames: bool = False
    tiles: int = 8
    min_signal: float = 0.02
    min_pixels: int = 16

    def __post_init__(self) -> None:
        if self.angle_reference not in ("polarizer", "analyzers"):
            raise ValueError(
                f"argument 'angle_reference' must be 'polarizer' or 'analyzers'; got {self.angle_reference!r}"
            )
        if self.tiles < 1:
            raise ValueError(f"argument 'tiles' must be >= 1; got {self.tiles}")
        if not 0 <= self.min_signal < 1:
            raise ValueError(f"argument 'min_signal' must lie in [0, 1); got {self.min_signal}")
        if self.colours is not None:
            bad = [c for c in self.colours if c not in COLOUR_NAMES]
            if bad or not self.colours or len(set(self.colours)) != len(self.colours):
                raise ValueError(f"argument 'colours' must be distinct values of R, G, B; got {self.colours}")


@dataclasses.dataclass(frozen=True)
class AnalyzerFit:
    """The four analyzers of one colour (``colour`` None: mono sensor), order 0, 45, 90, 135 deg.

    Attributes:
        colour: "R", "G", "B" or None.
        diattenuation, diattenuation_std: ``(4,)`` float64 ``d_k`` and one-sigma.
        angles_deg, angles_std_deg: ``(4,)`` float64 orientations (degrees from image +x) and one-sigma.
        gains, gains_std: ``(4,)`` float64 relative gains (mean 1) and one-sigma; reported, not stored.
        pixels: unsaturated super-pixels used.
        residual_rms: rms least-squares residual relative to the mean signal (0 with three angles).
        angle_offset_deg: offset removed with ``angle_reference="analyzers"`` (else 0).
    """

    colour: str | None
    diattenuation: np.ndarray
    diattenuation_std: np.ndarray
    angles_deg: np.ndarray
    angles_std_deg: np.ndarray
    gains: np.ndarray
    gains_std: np.ndarray
    pixels: int
    residual_rms: float
    angle_offset_deg: float = 0.0

    @property
    def extinction_ratios(self) -> np.ndarray:
        """``(4,)`` per-analyzer extinction ratios (inf where ``d >= 1``)."""
        return _ratio(self.diattenuation)

    @property
    def mean_diattenuation(self) -> tuple[float, float]:
        """Mean ``d`` over the four analyzers and its one-sigma."""
        return float(self.diattenuation.mean()), float(np.sqrt(np.sum(self.diattenuation_std**2)) / 4)

    @property
    def extinction_ratio(self) -> float:
        """The camera's (colour's) extinction ratio ``(1 + d) / (1 - d)`` of the mean ``d``."""
        return float(_ratio(self.mean_diattenuation[0]))

    @property
    def extinction_ratio_std(self) -> float:
        """One-sigma of :attr:`extinction_ratio` (delta method; inf when ``d`` reaches 1)."""
        d, sigma = self.mean_diattenuation
        return math.inf if d >= 1 else 2.0 * sigma / (1.0 - d) ** 2

    @property
    def extinction_ratio_bounds(self) -> tuple[float, float]:
        """One-sided 95 % lower and upper bounds of the extinction ratio (upper inf when unbounded)."""
        d, sigma = self.mean_diattenuation
        return float(_ratio(d - _ONE_SIDED_95 * sigma)), float(_ratio(d + _ONE_SIDED_95 * sigma))

    def calibration(self) -> AnalyzerCalibration:
        """The ``rig.json`` entry (stds None where not determined)."""
        ratio, ratio_std = self.extinction_ratio, self.extinction_ratio_std
        angle_std = self.angles_std_deg
        return AnalyzerCalibration(
            extinction_ratio=None if math.isinf(ratio) else ratio,
            analyzer_angles_deg=tuple(float(a) for a in self.angles_deg),
            extinction_ratio_std=None if not math.isfinite(ratio_std) or math.isinf(ratio) else ratio_std,
            analyzer_angles_std_deg=(
                tuple(float(s) for s in angle_std) if np.isfinite(angle_std).all() else None
            ),
        )


@dataclasses.dataclass(frozen=True)
class PolarizationCalibration:
    """Result of :func:`calibrate_analyzers`: one :class:`AnalyzerFit` per colour (key None: mono).

    Attributes:
        camera_id: the calibrated camera.
        fits: colour (or None) -> fit.
        polarizer_deg: the frames' polarizer angles, degrees.
        roi: ``(x, y, width, height)`` pixels actually used.
    """

    camera_id: str
    fits: dict[str | None, AnalyzerFit]
    polarizer_deg: tuple[float, ...]
    roi: tuple[int, int, int, int]

    def analyzer_field(self) -> AnalyzerCalibration | dict[str, AnalyzerCalibration]:
        """The camera's ``analyzer`` value: one calibration (mono) or ``{colour: calibration}``."""
        if None in self.fits:
            return self.fits[None].calibration()
        return {colour: fit.calibration() for colour, fit in self.fits.items() if colour is not None}


def central_roi(width: int, height: int, period: int) -> tuple[int, int, int, int]:
    """``(x, y, width, height)`` of the central half of a frame in each direction, on whole periods."""
    roi_w, roi_h = max(period, width // 2 // period * period), max(period, height // 2 // period * period)
    x0 = (width - roi_w) // 2 // period * period
    y0 = (height - roi_h) // 2 // period * period
    return x0, y0, roi_w, roi_h


def _snap_roi(roi: tuple[int, int, int, int], camera: Camera, period: int) -> tuple[int, int, int, int]:
    x, y, w, h = (int(v) for v in roi)
    if w <= 0 or h <= 0 or x < 0 or y < 0 or x + w > camera.width or y + h > camera.height:
        raise ValueError(
            f"argument 'roi' {roi} must be x,y,width,height inside the {camera.width}x{camera.height} frame"
        )
    x0, y0 = -(-x // period) * period, -(-y // period) * period
    x1, y1 = (x + w) // period * period, (y + h) // period * period
    if x1 - x0 < period or y1 - y0 < period:
        raise ValueError(f"argument 'roi' {roi} holds no whole {period}x{period} mosaic period")
    return x0, y0, x1 - x0, y1 - y0


def _ratio(d):
    d = np.asarray(d, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return np.where(d >= 1, np.inf, (1 + d) / np.maximum(1 - d, 1e-300))


def _design(polarizer_deg: np.ndarray) -> np.ndarray:
    """``(F, 3)`` design matrix ``[1, cos 2 theta, sin 2 theta]``, checked for three distinct angles."""
    distinct = np.unique(np.round(np.mod(polarizer_deg, 180.0), 6) % 180.0)
    if distinct.size < 3:
        raise ValueError(
            f"polarizer angles must hold at least 3 distinct values modulo 180 deg; got "
            f"{sorted(set(float(a) for a in polarizer_deg))}"
        )
    two = 2.0 * np.deg2rad(polarizer_deg)
    design = np.stack([np.ones_like(two), np.cos(two), np.sin(two)], axis=-1)
    if np.linalg.cond(design) > 1e6:
        raise ValueError(f"polarizer angles {list(polarizer_deg)} are too close together to fit the model")
    return design


def _parameters(coef: np.ndarray, nominal: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``coef (..., 4, 3)`` -> diattenuation, angle (deg, within 90 of ``nominal``), gain (mean 1)."""
    c0, c1, c2 = coef[..., 0], coef[..., 1], coef[..., 2]
    d = np.hypot(c1, c2) / c0
    angle = np.rad2deg(0.5 * np.arctan2(c2, c1))
    angle = nominal + (angle - nominal + 90.0) % 180.0 - 90.0
    gain = c0 / c0.mean(axis=-1, keepdims=True)
    return d, angle, gain


def _lsq_std(coef: np.ndarray, covariance: np.ndarray) -> tuple[np.ndarray, ...]:
    """One-sigma of d, angle (deg), gain from ``coef (4, 3)`` and ``covariance (4, 3, 3)`` (delta method)."""
    c0, c1, c2 = coef[:, 0], coef[:, 1], coef[:, 2]
    rho2 = np.maximum(c1**2 + c2**2, 1e-300)
    rho = np.sqrt(rho2)
    jac_d = np.stack([-rho / c0**2, c1 / (rho * c0), c2 / (rho * c0)], axis=-1)
    jac_a = np.stack([np.zeros_like(c0), -c2 / rho2, c1 / rho2], axis=-1) * (0.5 * 180.0 / math.pi)

    def spread(jac: np.ndarray) -> np.ndarray:
        return np.sqrt(np.maximum(np.einsum("ki,kij,kj->k", jac, covariance, jac), 0.0))

    gain_std = np.sqrt(np.maximum(covariance[:, 0, 0], 0.0)) / c0.mean()
    return spread(jac_d), spread(jac_a), gain_std


def _fit_colour(
    means: np.ndarray, tile_means: np.ndarray, design: np.ndarray, colour: str | None, pixels: int
) -> AnalyzerFit:
    """Fit ``means (F, 4)`` (and ``tile_means (T, F, 4)``) of one colour."""
    nominal = np.asarray(IDEAL_ANALYZER_ANGLES_DEG)
    solve = np.linalg.pinv(design)  # (3, F)
    coef = means.T @ solve.T  # (4, 3)
    if np.any(coef[:, 0] <= 0):
        raise ValueError(f"colour {colour or 'mono'}: no signal above the black level in the region")
    d, angle, gain = _parameters(coef, nominal)
    residual = means.T - coef @ design.T  # (4, F)
    dof = design.shape[0] - 3
    if dof > 0:
        variance = np.sum(residual**2, axis=-1) / dof
        covariance = variance[:, None, None] * np.linalg.inv(design.T @ design)[None]
        lsq = _lsq_std(coef, covariance)
    else:
        lsq = (np.zeros(4),) * 3
    count = tile_means.shape[0]
    if count >= 2:
        tile_d, tile_angle, tile_gain = _parameters(np.einsum("tfk,cf->tkc", tile_means, solve), nominal)
        tile_angle = angle + (tile_angle - angle + 90.0) % 180.0 - 90.0
        tiles = [np.std(v, axis=0, ddof=1) / math.sqrt(count) for v in (tile_d, tile_angle, tile_gain)]
    else:
        tiles = [np.zeros(4)] * 3
    stds = [np.maximum(a, b) for a, b in zip(lsq, tiles, strict=True)]
    if dof == 0 and count < 2:
        stds = [np.full(4, np.nan)] * 3
    rms = float(np.sqrt(np.mean(residual**2)) / means.mean())
    return AnalyzerFit(colour, d, stds[0], angle, stds[1], gain, stds[2], pixels, rms)


def _checked_frames(
    raw_frames: Sequence[np.ndarray], camera: Camera, names: Sequence[str]
) -> list[np.ndarray]:
    expected = (camera.height, camera.width)
    out = []
    for raw, name in zip(raw_frames, names, strict=True):
        raw = np.asarray(raw)
        if raw.ndim != 2 or raw.shape != expected:
            raise ValueError(
                f"frame '{name}' has shape {raw.shape}; camera '{camera.id}' declares {expected}"
            )
        if not np.issubdtype(raw.dtype, np.integer) and not np.issubdtype(raw.dtype, np.floating):
            raise ValueError(f"frame '{name}' must hold numeric raw counts; got dtype {raw.dtype}")
        out.append(raw)
    return out


def calibrate_analyzers(
    raw_frames: Sequence[np.ndarray],
    polarizer_deg: Sequence[float],
    camera: Camera,
    options: PolarizationCalibrationOptions | None = None,
    *,
    names: Sequence[str] | None = None,
    exposures: Sequence[float] | None = None,
) -> PolarizationCalibration:
    """Estimate a camera's analyzers from raw frames of a fully polarized target (module docstring).

    Args:
        raw_frames: ``F`` raw mosaics ``(H, W)`` in counts (the camera's size, bit depth, black and white
            levels and ``pattern_phase`` apply).
        polarizer_deg: ``F`` polarizer angles, degrees from image +x; at least 3 distinct modulo 180.
        camera: a ``mono-polarization`` or ``color-polarization`` camera of the rig.
        options: :class:`PolarizationCalibrationOptions`.
        names: names of the frames for error messages (default ``frame 0``, ...).
        exposures: relative exposure of each frame (default 1), divided out.

    Returns:
        :class:`PolarizationCalibration`.

    Raises:
        ValueError: a non-polarization camera, colours asked of a mono camera, a frame of the wrong
            shape, fewer than three distinct angles, a dark frame or one saturating the region, or
            estimates outside the model (no modulation; angles beyond 22.5 deg of nominal) - each naming
            the frame, argument or camera.
    """
    options = options or PolarizationCalibrationOptions()
    if camera.sensor not in ("mono-polarization", "color-polarization"):
        raise ValueError(f"camera '{camera.id}' has sensor '{camera.sensor}', not a polarization sensor")
    mono = camera.sensor == "mono-polarization"
    if mono and options.colours is not None:
        raise ValueError(f"argument 'colours': camera '{camera.id}' is mono-polarization; it has no colours")
    names = list(names) if names is not None else [f"frame {i}" for i in range(len(raw_frames))]
    angles = np.asarray(polarizer_deg, dtype=np.float64).reshape(-1)
    if len(raw_frames) != angles.size or len(names) != angles.size:
        raise ValueError(f"got {len(raw_frames)} frames but {angles.size} polarizer angles")
    if not np.isfinite(angles).all():
        raise ValueError(f"polarizer angles must be finite; got {list(angles)}")
    design = _design(angles)
    scale = np.ones(angles.size) if exposures is None else np.asarray(exposures, dtype=np.float64)
    if scale.shape != angles.shape or not (np.isfinite(scale).all() and (scale > 0).all()):
        raise ValueError(f"exposures must be {angles.size} finite values > 0; got {exposures}")
    frames = _checked_frames(raw_frames, camera, names)
    period = pattern_period(camera.sensor)
    roi = _snap_roi(options.roi, camera, period) if options.roi else central_roi(
        camera.width, camera.height, period
    )
    x0, y0, w, h = roi
    stack = np.stack([f[y0 : y0 + h, x0 : x0 + w] for f in frames]).astype(np.float64)
    white, black = camera.saturation_level, camera.black_level
    blocks = (len(frames), h // period, period, w // period, period)
    saturated = (stack >= white).reshape(blocks).any(axis=(2, 4))
    valid = ~saturated.any(axis=0)  # (h / p, w / p) super-pixels usable in every frame
    if valid.sum() < options.min_pixels:
        fractions = saturated.mean(axis=(1, 2))
        worst = int(np.argmax(fractions))
        raise ValueError(
            f"frame '{names[worst]}' saturates {fractions[worst]:.0%} of the region's super-pixels at the "
            f"white level {white:g}; {int(valid.sum())} usable (need {options.min_pixels}): lower the "
            "exposure"
        )
    signal = (stack - black) / (white - black) / scale[:, None, None]
    mean_signal = np.array([s[np.repeat(np.repeat(valid, period, 0), period, 1)].mean() for s in signal])
    for name, value in zip(names, mean_signal, strict=True):
        if value < options.min_signal:
            raise ValueError(
                f"frame '{name}' is too dark: mean signal {value:.2%} of the white level above black in the "
                f"region (need {options.min_signal:.0%}); raise the exposure or check black_level"
            )
    colours = [None] if mono else list(options.colours or COLOUR_NAMES)
    means, tile_means = _lattice_means(signal, valid, camera, colours, options.tiles)
    if options.normalise_frames:
        means = means / means.mean(axis=-1, keepdims=True)
        tile_means = tile_means / tile_means.mean(axis=-1, keepdims=True)
    pixels = int(valid.sum())
    fits = {
        colour: _fit_colour(means[:, i], tile_means[:, :, i], design, colour, pixels)
        for i, colour in enumerate(colours)
    }
    fits = _reference_angles(fits, options.angle_reference, camera.id)
    return PolarizationCalibration(camera.id, fits, tuple(float(a) for a in angles), roi)


def _lattice_means(
    signal: np.ndarray, valid: np.ndarray, camera: Camera, colours: list[str | None], tiles: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame means over the valid super-pixels: ``(F, C, 4)`` and per tile ``(T, F, C, 4)``."""
    rows, cols = valid.shape
    row_edges = np.linspace(0, rows, min(tiles, rows) + 1).astype(int)
    col_edges = np.linspace(0, cols, min(tiles, cols) + 1).astype(int)
    tile_index = (np.searchsorted(row_edges, np.arange(rows), side="right") - 1)[:, None] * (
        len(col_edges) - 1
    ) + (np.searchsorted(col_edges, np.arange(cols), side="right") - 1)[None, :]
    n_tiles = (len(row_edges) - 1) * (len(col_edges) - 1)
    counts = np.bincount(tile_index[valid], minlength=n_tiles).astype(np.float64)
    frames = signal.shape[0]
    sums = np.zeros((n_tiles, frames, len(colours), 4))
    weights = np.zeros((len(colours), 4))
    wanted = {colour: i for i, colour in enumerate(colours)}
    for lattice in lattices(camera.sensor, camera.pattern_phase):
        colour = None if lattice.colour is None else COLOUR_NAMES[lattice.colour]
        if colour not in wanted:
            continue
        sub = signal[:, lattice.row0 :: lattice.period, lattice.col0 :: lattice.period]
        for f in range(frames):
            sums[:, f, wanted[colour], lattice.angle] += np.bincount(
                tile_index[valid], weights=sub[f][valid], minlength=n_tiles
            )
        weights[wanted[colour], lattice.angle] += 1.0
    filled = counts > 0
    tile_means = sums[filled] / (counts[filled, None, None, None] * weights[None, None])
    means = sums.sum(axis=0) / (counts.sum() * weights[None])
    return means, tile_means


def _reference_angles(
    fits: dict[str | None, AnalyzerFit], reference: str, camera_id: str
) -> dict[str | None, AnalyzerFit]:
    """Apply the angle reference and check every fit against the model's range."""
    nominal = np.asarray(IDEAL_ANALYZER_ANGLES_DEG)
    if reference == "analyzers":
        offset = float(np.mean([fit.angles_deg - nominal for fit in fits.values()]))
        fits = {
            c: dataclasses.replace(fit, angles_deg=fit.angles_deg - offset, angle_offset_deg=offset)
            for c, fit in fits.items()
        }
    for colour, fit in fits.items():
        label = f"camera '{camera_id}'" + (f" colour {colour}" if colour else "")
        if np.any(fit.diattenuation < _MIN_DIATTENUATION):
            raise ValueError(
                f"{label}: the frames show no polarization modulation (diattenuation "
                f"{np.round(fit.diattenuation, 3).tolist()} < {_MIN_DIATTENUATION}); is the target polarized?"
            )
        deviation = np.abs(fit.angles_deg - nominal)
        if np.any(deviation > 22.5):
            raise ValueError(
                f"{label}: estimated analyzer angles {np.round(fit.angles_deg, 2).tolist()} deg lie more "
                "than 22.5 deg from 0/45/90/135: check the camera's pattern_phase and the polarizer's zero "
                "(or use angle_reference 'analyzers')"
            )
    return fits
