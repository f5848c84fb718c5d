"""The parts of ``rig.json``: cameras (with their measured analyzers) and polarized light modules.

Pydantic v2 models on one base (:class:`StrictModel`: unknown keys, NaN and infinity refused);
:func:`one_line_errors` puts a ``ValidationError`` on one line naming the fields
(``lights[3].position_mm: ...``), as :meth:`polarface.capture.rig.Rig.load` reports a bad file. Both are
shared with :mod:`polarface.capture.rig` and :mod:`polarface.capture.rig_spectral`. Units: positions in
mm, light polarizer angles in radians, analyzer angles in degrees, ``K`` in pixels. Camera poses are 4x4
``world_to_camera`` matrices in the OpenCV convention (camera x right, y down, z forward). The whole
rig and the channel order of ``colour_channels``: :mod:`polarface.capture.rig`.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from polarface.geometry.camera import PinholeCamera
from polarface.optics.analyzer import IDEAL_ANALYZER_ANGLES_DEG, AnalyzerModel

__all__ = ["AnalyzerCalibration", "Camera", "LightModule"]


def _finite_matrix(value: Any, rows: int, cols: int, name: str) -> list[list[float]]:
    array = np.asarray(value, dtype=np.float64)
    if array.shape != (rows, cols):
        raise ValueError(f"{name} must be a {rows}x{cols} matrix; got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    return array.tolist()


class StrictModel(BaseModel):
    """The base of the rig's models: unknown keys and NaN/infinity refused, assignments validated."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


def _field_path(loc: tuple[Any, ...]) -> str:
    """``("lights", 3, "position_mm", 0)`` -> ``lights[3].position_mm[0]``."""
    path = ""
    for part in loc:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else str(part))
    return path or "rig"


def one_line_errors(exc: ValidationError) -> str:
    """Every error of a pydantic ``ValidationError`` on one line: ``field.path: message; ...``."""
    parts = (f"{_field_path(tuple(e['loc']))}: {' '.join(str(e['msg']).split())}" for e in exc.errors())
    return "; ".join(parts)


class AnalyzerCalibration(StrictModel):
    """The measured analyzers of a polarization camera (or of one colour channel of it).

    Absent from ``rig.json`` means ideal (infinite extinction ratio, 0/45/90/135 deg). Written by
    ``polarface calibrate-polarization`` with its one-sigma uncertainties.

    Attributes:
        extinction_ratio: ``k1 / k2`` of the micro-polarizers (> 1); None = infinite (ideal).
        analyzer_angles_deg: orientations of the analyzers polarface calls 0, 45, 90, 135 deg, degrees
            from image +x, counter-clockwise as seen by the camera (``docs/conventions.md``).
        extinction_ratio_std, analyzer_angles_std_deg: one-sigma uncertainties of the calibration.
    """

    extinction_ratio: float | None = Field(default=None, gt=1)
    analyzer_angles_deg: tuple[float, float, float, float] = IDEAL_ANALYZER_ANGLES_DEG
    extinction_ratio_std: float | None = Field(default=None, ge=0)
    analyzer_angles_std_deg: tuple[float, float, float, float] | None = None

    @model_validator(mode="after")
    def _check_model(self) -> AnalyzerCalibration:
        self.model()  # raises ValueError for angles out of order
        return self

    def model(self) -> AnalyzerModel:
        """This calibration as an :class:`polarface.optics.analyzer.AnalyzerModel`."""
        ratio = math.inf if self.extinction_ratio is None else self.extinction_ratio
        return AnalyzerModel(ratio, self.analyzer_angles_deg)


class Camera(StrictModel):
    """One camera of the rig.

    Attributes:
        id: unique name (used for raw folders and store arrays).
        role: ``polarimetric`` (appearance) or ``stereo`` (geometry).
        sensor: ``color-polarization`` (IMX250MYR), ``mono-polarization`` (IMX250MZR) or ``rgb``.
        width, height: image size in pixels.
        K: 3x3 intrinsic matrix (pixels).
        distortion: OpenCV distortion coefficients (k1, k2, p1, p2[, k3, ...]); empty = none.
        world_to_camera: 4x4 rigid transform, OpenCV camera convention, translation in mm.
        black_level, white_level: raw counts of black and of saturation.
        bit_depth: ADC bits (raw values lie in [0, 2**bit_depth - 1]).
        exposure: relative exposure (time x gain) divided out by demosaicing.
        pattern_phase: (row, col) phase of the mosaic (cropped/flipped readouts).
        colour_channels: for colour cameras, the spectral channel index (0..5) of R, G, B, e.g.
            ``{"R": 0, "G": 1, "B": 2}``; empty for mono cameras or when unused.
        channel_gains: the relative gain of the sensor's R, G, B (a mono sensor: the first) on top of
            ``exposure``, divided out with it by demosaicing; measured by ``polarface calibrate-rig``'s
            radiometric step, which puts the two polarization cameras on one scale (docs/calibration.md).
        analyzer: the measured micro-polarizers (polarization sensors only): one
            :class:`AnalyzerCalibration` for every colour, or one per colour ``{"R": ..., "G": ...,
            "B": ...}`` (colour cameras; a colour left out is ideal); None = ideal analyzers.
    """

    id: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")
    role: Literal["polarimetric", "stereo"]
    sensor: Literal["color-polarization", "mono-polarization", "rgb"]
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    K: list[list[float]]
    distortion: list[float] = Field(default_factory=list, max_length=14)
    world_to_camera: list[list[float]] = Field(default_factory=lambda: np.eye(4).tolist())
    black_level: float = Field(default=0.0, ge=0)
    white_level: float | None = None
    bit_depth: int = Field(default=12, ge=1, le=16)
    exposure: float = Field(default=1.0, gt=0)
    pattern_phase: tuple[int, int] = (0, 0)
    colour_channels: dict[Literal["R", "G", "B"], int] = Field(default_factory=dict)
    channel_gains: tuple[float, float, float] = (1.0, 1.0, 1.0)
    analyzer: AnalyzerCalibration | dict[Literal["R", "G", "B"], AnalyzerCalibration] | None = None

    @field_validator("channel_gains")
    @classmethod
    def _check_gains(cls, value: tuple[float, float, float]) -> tuple[float, float, float]:
        if not all(v > 0 for v in value):  # NaN and infinity are refused by the model
            raise ValueError(f"channel_gains must be three values > 0; got {value}")
        return value

    @field_validator("K")
    @classmethod
    def _check_k(cls, value: Any) -> list[list[float]]:
        matrix = _finite_matrix(value, 3, 3, "K")
        if matrix[0][0] <= 0 or matrix[1][1] <= 0 or matrix[2] != [0.0, 0.0, 1.0]:
            raise ValueError("K must have positive focal lengths and last row [0, 0, 1]")
        return matrix

    @field_validator("world_to_camera")
    @classmethod
    def _check_pose(cls, value: Any) -> list[list[float]]:
        matrix = np.asarray(_finite_matrix(value, 4, 4, "world_to_camera"))
        rotation = matrix[:3, :3]
        if not np.allclose(matrix[3], [0, 0, 0, 1]) or not np.allclose(
            rotation @ rotation.T, np.eye(3), atol=1e-6
        ):
            raise ValueError("world_to_camera must be rigid: orthonormal rotation, last row [0, 0, 0, 1]")
        if np.linalg.det(rotation) < 0:
            raise ValueError("world_to_camera rotation must be proper (det +1)")
        return matrix.tolist()

    @field_validator("distortion")
    @classmethod
    def _check_distortion(cls, value: list[float]) -> list[float]:
        if len(value) not in (0, 4, 5, 8, 12, 14) or not all(math.isfinite(v) for v in value):
            raise ValueError("distortion must hold 0, 4, 5, 8, 12 or 14 finite OpenCV coefficients")
        return value

    @field_validator("analyzer", mode="before")
    @classmethod
    def _check_analyzer(cls, value: Any) -> Any:
        """One calibration, or one per colour when every key is R, G or B (clear one-line errors)."""
        if value is None or isinstance(value, AnalyzerCalibration):
            return value
        if not isinstance(value, dict):
            raise ValueError("must be an object {extinction_ratio, analyzer_angles_deg} or {R, G, B: ...}")
        if value and set(value) <= {"R", "G", "B"}:
            per_colour = {}
            for colour, entry in value.items():
                try:
                    per_colour[colour] = AnalyzerCalibration.model_validate(entry)
                except ValidationError as exc:
                    raise ValueError(f"{colour}: {one_line_errors(exc)}") from None
            return per_colour
        try:
            return AnalyzerCalibration.model_validate(value)
        except ValidationError as exc:
            raise ValueError(one_line_errors(exc)) from None

    @field_validator("colour_channels")
    @classmethod
    def _check_channels(cls, value: dict[str, int]) -> dict[str, int]:
        if any(not 0 <= v < 6 for v in value.values()):
            raise ValueError(f"colour_channels indices must lie in 0..5; got {value}")
        return value

    @model_validator(mode="after")
    def _check_levels(self) -> Camera:
        white = self.saturation_level
        if not self.black_level < white <= 2**self.bit_depth - 1:
            raise ValueError(
                f"levels must satisfy black_level ({self.black_level}) < white_level ({white}) <= "
                f"2**bit_depth - 1 ({2**self.bit_depth - 1})"
            )
        if self.sensor == "mono-polarization" and self.colour_channels:
            raise ValueError("colour_channels must be empty for a mono-polarization camera")
        if self.analyzer is not None and self.sensor == "rgb":
            raise ValueError("analyzer is only allowed for a polarization sensor; this camera is 'rgb'")
        if isinstance(self.analyzer, dict) and self.sensor != "color-polarization":
            raise ValueError("a per-colour analyzer {R, G, B} needs a color-polarization sensor")
        period = {"mono-polarization": 2, "color-polarization": 4}.get(self.sensor)
        if period is not None and not all(0 <= p < period for p in self.pattern_phase):
            raise ValueError(
                f"pattern_phase must lie in 0..{period - 1} for a {self.sensor} camera; "
                f"got {self.pattern_phase}"
            )
        return self

    @property
    def saturation_level(self) -> float:
        """White level in counts (``2**bit_depth - 1`` when not given)."""
        return float(self.white_level if self.white_level is not None else 2**self.bit_depth - 1)

    @property
    def intrinsics(self) -> np.ndarray:
        """K as a float64 ``(3, 3)`` array."""
        return np.asarray(self.K, dtype=np.float64)

    @property
    def pose(self) -> np.ndarray:
        """world_to_camera as a float64 ``(4, 4)`` array."""
        return np.asarray(self.world_to_camera, dtype=np.float64)

    @property
    def centre_mm(self) -> np.ndarray:
        """Camera centre in world coordinates, mm, ``(3,)``."""
        pose = self.pose
        return -pose[:3, :3].T @ pose[:3, 3]

    def analyzer_model(self, colour: str | None = None) -> AnalyzerModel:
        """The analyzers of colour ``colour`` (``"R"``, ``"G"``, ``"B"``; None for a mono sensor or a
        camera-wide calibration) as an :class:`polarface.optics.analyzer.AnalyzerModel`; ideal when
        ``rig.json`` gives none."""
        if self.analyzer is None:
            return AnalyzerModel()
        if isinstance(self.analyzer, AnalyzerCalibration):
            return self.analyzer.model()
        if colour not in ("R", "G", "B"):
            raise ValueError(
                f"camera {self.id!r} has per-colour analyzers; colour must be R, G or B; got {colour!r}"
            )
        calibration = self.analyzer.get(colour)
        return AnalyzerModel() if calibration is None else calibration.model()

    def pinhole(self) -> PinholeCamera:
        """This camera as a :class:`polarface.geometry.camera.PinholeCamera` (K, pose, size, distortion)."""
        return PinholeCamera.from_dict(self.model_dump())


class LightModule(StrictModel):
    """One polarized LED module, treated as a point light.

    Attributes:
        id: unique name.
        position_mm: ``[x, y, z]`` in world coordinates, mm.
        polarizer_angle: transmission axis of the linear polarizer, radians, measured in the
            reference camera's image plane from image +x (so 0 gives Stokes [1, 1, 0, 0]).
        stokes: normalised incident Stokes vector ``[1, s1, s2, s3]`` in the camera frame.
        radiant_intensity: radiant intensity ``I_L`` per spectral channel (6 values) or one value
            for all, arbitrary radiometric unit per steradian.
    """

    id: str = Field(min_length=1)
    position_mm: tuple[float, float, float]
    polarizer_angle: float = 0.0
    stokes: tuple[float, float, float, float] = (1.0, 1.0, 0.0, 0.0)
    radiant_intensity: float | list[float] = 1.0e6

    @field_validator("stokes")
    @classmethod
    def _check_stokes(cls, value: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
        if value[0] <= 0 or math.hypot(value[1], value[2], value[3]) > value[0] * (1 + 1e-9):
            raise ValueError(f"stokes must be physical (s0 > 0, |s1,s2,s3| <= s0); got {value}")
        return value

    @field_validator("radiant_intensity")
    @classmethod
    def _check_intensity(cls, value: float | list[float]) -> float | list[float]:
        values = [value] if isinstance(value, float | int) else value
        if (not isinstance(value, float | int) and len(values) != 6) or any(
            not math.isfinite(v) or v < 0 for v in values
        ):
            raise ValueError("radiant_intensity must be one or six finite non-negative values")
        return value
