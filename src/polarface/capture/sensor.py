"""Forward model of the division-of-focal-plane polarization sensors: mosaic layout and raw noise.

Sensors (Sony datasheets; FLIR BFS-U3-51S5P / -51SPC technical reference):

* ``mono-polarization`` (IMX250MZR): one wire-grid polarizer per pixel in a 2x2 block::

      row 0:  90 deg   45 deg
      row 1: 135 deg    0 deg

* ``color-polarization`` (IMX250MYR): the same 2x2 polarizer block under each colour filter, the
  colour filters forming an RGGB Bayer pattern at block level, so the full period is 4x4 pixels::

      90R  45R  90G  45G
      135R  0R 135G   0G
      90G  45G  90B  45B
      135G  0G 135B   0B

``phase = (row, col)``: the raw pixel ``(r, c)`` sits at ``(r + row, c + col)`` of the canonical
pattern above. Cropped readouts (an odd ROI offset) or flipped readouts shift the phase; a vertical
flip of an IMX250MZR frame, for instance, corresponds to ``phase = (1, 0)``.

Angle indices are 0, 1, 2, 3 for 0, 45, 90, 135 deg (the order of
:data:`polarface.optics.stokes.ANALYZER_ANGLES`); colour indices 0, 1, 2 for R, G, B.

Radiometry of the simulated raw (:func:`simulate_raw`): the linear signal is in units of the
sensor's full-well capacity at unit exposure, so ``signal = 1`` fills the well; electrons are
``signal * exposure * full_well_e``; the ADC maps ``full_well_e`` electrons to ``white_level -
black_level`` counts (gain ``full_well_e / (white_level - black_level)`` e-/ADU), adds the black
level, rounds and clips to ``[0, white_level]``. :func:`polarface.capture.demosaic.demosaic`
inverts this: ``(raw - black) / (white - black) / exposure`` gives back the signal.
Defaults: IMX250 full well about 10 500 e-, temporal read noise about 2.4 e- (EMVA 1288 figures
published for the FLIR BFS-U3-51S5P), 12-bit ADC.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from polarface._validation import array_api, check_range

__all__ = [
    "BAYER_BLOCK",
    "POLARIZER_BLOCK",
    "SENSOR_KINDS",
    "Lattice",
    "SensorNoise",
    "angle_index_map",
    "colour_index_map",
    "lattices",
    "mosaic",
    "pattern_period",
    "simulate_raw",
]

SensorKind = Literal["mono-polarization", "color-polarization"]
#: The polarization sensor kinds this module models.
SENSOR_KINDS: tuple[str, ...] = ("mono-polarization", "color-polarization")
#: Angle index (0: 0 deg, 1: 45, 2: 90, 3: 135) of the 2x2 polarizer block, [row][col].
POLARIZER_BLOCK = ((2, 1), (3, 0))
#: Colour index (0: R, 1: G, 2: B) of the block-level RGGB Bayer pattern, [row][col].
BAYER_BLOCK = ((0, 1), (1, 2))


def _check_sensor(sensor: str) -> str:
    if sensor not in SENSOR_KINDS:
        raise ValueError(f"argument 'sensor' must be one of {SENSOR_KINDS}; got {sensor!r}")
    return sensor


def pattern_period(sensor: str) -> int:
    """Pixel period of the mosaic: 2 for ``mono-polarization``, 4 for ``color-polarization``."""
    return 2 if _check_sensor(sensor) == "mono-polarization" else 4


def _check_phase(phase: tuple[int, int]) -> tuple[int, int]:
    try:
        row, col = (int(v) for v in phase)
    except Exception as exc:
        raise ValueError(f"argument 'phase' must be two integers (row, col); got {phase!r}") from exc
    return row, col


@dataclass(frozen=True)
class Lattice:
    """One rectangular sub-lattice of the mosaic: pixels ``raw[row0::period, col0::period]``.

    Attributes:
        angle: analyzer angle index (0..3 for 0, 45, 90, 135 deg).
        colour: colour index (0 R, 1 G, 2 B), or None for the monochrome sensor.
        row0, col0: first raw pixel of the lattice, in ``[0, period)``.
        period: lattice spacing in pixels (2 mono, 4 colour). The green channel of the colour
            sensor is the union of two lattices per angle.
    """

    angle: int
    colour: int | None
    row0: int
    col0: int
    period: int


def lattices(sensor: str, phase: tuple[int, int] = (0, 0)) -> list[Lattice]:
    """The sub-lattices of a sensor for a pattern phase (4 for mono, 16 for colour)."""
    period = pattern_period(sensor)
    row_phase, col_phase = _check_phase(phase)
    out = []
    for row0 in range(period):
        for col0 in range(period):
            r, c = row0 + row_phase, col0 + col_phase
            angle = POLARIZER_BLOCK[r % 2][c % 2]
            colour = None if period == 2 else BAYER_BLOCK[(r // 2) % 2][(c // 2) % 2]
            out.append(Lattice(angle, colour, row0, col0, period))
    return out


def angle_index_map(sensor: str, height: int, width: int, phase: tuple[int, int] = (0, 0)) -> np.ndarray:
    """``(height, width)`` int64 map of the analyzer angle index (0..3) of every raw pixel."""
    row_phase, col_phase = _check_phase(phase)
    _check_sensor(sensor)
    rows = (np.arange(height)[:, None] + row_phase) % 2
    cols = (np.arange(width)[None, :] + col_phase) % 2
    return np.asarray(POLARIZER_BLOCK, dtype=np.int64)[rows, cols]


def colour_index_map(sensor: str, height: int, width: int, phase: tuple[int, int] = (0, 0)) -> np.ndarray:
    """``(height, width)`` int64 map of the colour index (0 R, 1 G, 2 B); zeros for the mono sensor."""
    row_phase, col_phase = _check_phase(phase)
    if _check_sensor(sensor) == "mono-polarization":
        return np.zeros((height, width), dtype=np.int64)
    rows = ((np.arange(height)[:, None] + row_phase) // 2) % 2
    cols = ((np.arange(width)[None, :] + col_phase) // 2) % 2
    return np.asarray(BAYER_BLOCK, dtype=np.int64)[rows, cols]


@array_api("i0", "i45", "i90", "i135")
def mosaic(
    i0: torch.Tensor,
    i45: torch.Tensor,
    i90: torch.Tensor,
    i135: torch.Tensor,
    sensor: str = "mono-polarization",
    phase: tuple[int, int] = (0, 0),
) -> torch.Tensor:
    """Sample four full-resolution analyzer images into one raw mosaic (noise-free, float).

    Differentiable with respect to the intensities (a gather).

    Args:
        i0, i45, i90, i135: images behind analyzers at 0/45/90/135 deg: ``(H, W)`` for
            ``mono-polarization``, ``(H, W, 3)`` (R, G, B) for ``color-polarization``; linear units.
        sensor: ``"mono-polarization"`` or ``"color-polarization"``.
        phase: pattern phase ``(row, col)`` (see the module docstring).

    Returns:
        ``(H, W)`` raw mosaic in the intensities' unit and dtype.

    Raises:
        ValueError: on an unknown sensor, mismatched shapes, or a missing colour axis.
    """
    _check_sensor(sensor)
    shapes = {tuple(t.shape) for t in (i0, i45, i90, i135)}
    if len(shapes) != 1:
        raise ValueError(f"arguments 'i0', 'i45', 'i90', 'i135' must share one shape; got {sorted(shapes)}")
    stack = torch.stack((i0, i45, i90, i135), dim=0)
    if sensor == "mono-polarization":
        if stack.ndim != 3:
            raise ValueError(
                f"argument 'i0' must be (H, W) for a mono-polarization sensor; got {tuple(i0.shape)}"
            )
        stack = stack[..., None]
    elif stack.ndim != 4 or stack.shape[-1] != 3:
        raise ValueError(
            f"argument 'i0' must be (H, W, 3) for a color-polarization sensor; got {tuple(i0.shape)}"
        )
    height, width = stack.shape[1], stack.shape[2]
    angle = torch.from_numpy(angle_index_map(sensor, height, width, phase)).to(stack.device)
    colour = torch.from_numpy(colour_index_map(sensor, height, width, phase)).to(stack.device)
    rows = torch.arange(height, device=stack.device)[:, None].expand(height, width)
    cols = torch.arange(width, device=stack.device)[None, :].expand(height, width)
    return stack[angle, rows, cols, colour]


@dataclass(frozen=True)
class SensorNoise:
    """Raw noise and ADC model of a polarization camera (defaults: Sony IMX250 class, 12-bit).

    Attributes:
        full_well_e: full-well capacity in electrons (signal 1.0 at exposure 1 fills it).
        read_noise_e: temporal read noise, electrons rms (Gaussian).
        bit_depth: ADC bits; raw counts lie in ``[0, 2**bit_depth - 1]``.
        black_level: ADC offset in counts added to every pixel.
        white_level: saturation count; None means ``2**bit_depth - 1``.
        exposure: relative exposure (exposure time x gain, 1 = nominal) scaling the signal.
    """

    full_well_e: float = 10_500.0
    read_noise_e: float = 2.4
    bit_depth: int = 12
    black_level: float = 0.0
    white_level: float | None = None

    exposure: float = 1.0

    @property
    def saturation_count(self) -> float:
        """White level in counts."""
        return float(self.white_level if self.white_level is not None else 2**self.bit_depth - 1)

    @property
    def electrons_per_count(self) -> float:
        """Conversion gain in e-/ADU: the full well spans ``white_level - black_level`` counts."""
        return self.full_well_e / (self.saturation_count - self.black_level)

    def validate(self) -> SensorNoise:
        """Raise ``ValueError`` naming the field if a value is out of range; returns self."""
        if not 1 <= self.bit_depth <= 16:
            raise ValueError(f"field 'bit_depth' must be in 1..16; got {self.bit_depth}")
        if self.full_well_e <= 0:
            raise ValueError(f"field 'full_well_e' must be > 0; got {self.full_well_e}")
        if self.read_noise_e < 0:
            raise ValueError(f"field 'read_noise_e' must be >= 0; got {self.read_noise_e}")
        if self.exposure <= 0:
            raise ValueError(f"field 'exposure' must be > 0; got {self.exposure}")
        if not 0 <= self.black_level < self.saturation_count <= 2**self.bit_depth - 1:
            raise ValueError(
                f"fields 'black_level' {self.black_level} and 'white_level' {self.saturation_count} must "
                f"satisfy 0 <= black < white <= {2**self.bit_depth - 1}"
            )
        return self


def simulate_raw(
    signal: np.ndarray | torch.Tensor,
    noise: SensorNoise | None = None,
    *,
    seed: int | np.random.Generator | None = 0,
    noiseless: bool = False,
) -> np.ndarray:
    """Integer raw counts of a sensor from a noise-free float mosaic (see the module docstring).

    Args:
        signal: ``(H, W)`` linear signal, 1.0 = full well at unit exposure (e.g. from :func:`mosaic`);
            must be finite and >= 0.
        noise: sensor model; default :class:`SensorNoise()`.
        seed: seed or ``numpy.random.Generator``; the same seed gives the same frame.
        noiseless: skip shot and read noise (quantisation and clipping remain).

    Returns:
        ``(H, W)`` uint16 counts in ``[0, white_level]``.

    Raises:
        ValueError: if ``signal`` holds NaN/inf or negative values, or the model is invalid.
    """
    noise = (noise or SensorNoise()).validate()
    values = signal.detach().cpu().numpy() if isinstance(signal, torch.Tensor) else np.asarray(signal)
    values = values.astype(np.float64)
    if not np.isfinite(values).all():
        raise ValueError("argument 'signal' contains NaN or infinite value(s)")
    check_range(torch.from_numpy(values), "signal", 0.0)
    if values.ndim != 2:
        raise ValueError(f"argument 'signal' must be a (H, W) mosaic; got shape {values.shape}")
    electrons = values * noise.exposure * noise.full_well_e
    if not noiseless:
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        electrons = rng.poisson(np.minimum(electrons, 1e12)).astype(np.float64)
        electrons += rng.normal(0.0, noise.read_noise_e, size=electrons.shape)
    counts = noise.black_level + electrons / noise.electrons_per_count
    return np.clip(np.rint(counts), 0, noise.saturation_count).astype(np.uint16)
