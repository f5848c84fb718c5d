"""The simulated sensor's micro-polarizers: a configurable non-ideal analyzer per camera and colour.

:class:`SimulatedAnalyzers` says what the simulated polarization cameras' analyzers really are
(extinction ratio and orientation errors; default: ideal, as the paper's model) and whether the
simulation folder's ``rig.json`` carries them as the rig's ``analyzer`` calibration ("calibration
supplied") or stays ideal ("not supplied"). The true models are recorded in ``simulation.json`` either
way. The simulator renders ideal-analyzer images and passes them through
:func:`polarface.capture.analyzers.measured_analyzer_intensities` before mosaicing. Details and the
measured effect on the reconstruction: ``docs/sensors.md``.

Orientation errors: one value ``sigma`` draws each analyzer's error from ``N(0, sigma^2)`` degrees, per
polarimetric camera (``k``, in rig order), colour (``c`` = 0, 1, 2 for R, G, B) and analyzer, from
``numpy.random.default_rng((seed, k, c))``; four values are the offsets of the 0/45/90/135 deg analyzers
of every camera and colour.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from polarface.capture.rig import AnalyzerCalibration, Camera, Rig
from polarface.optics.analyzer import IDEAL_ANALYZER_ANGLES_DEG, AnalyzerModel

__all__ = ["SimulatedAnalyzers"]

_COLOURS = ("R", "G", "B")


def _ratios(value: Any) -> tuple[float, ...] | None:
    """``extinction_ratio`` as None (ideal) or a tuple of 1 or 3 ratios > 1 (inf allowed)."""
    if value is None:
        return None
    values = (value,) if isinstance(value, int | float) and not isinstance(value, bool) else tuple(value)
    try:
        ratios = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        ratios = ()
    if len(ratios) not in (1, 3) or not all(r > 1.0 for r in ratios):  # NaN fails too
        raise ValueError(
            f"argument 'extinction_ratio' must be one ratio > 1 or three (R, G, B), or None for ideal; "
            f"got {value!r}"
        )
    return ratios


def _angle_errors(value: Any) -> float | tuple[float, float, float, float]:
    """``angle_error_deg`` as a sigma >= 0 or four finite offsets within +-22.5 deg."""
    if isinstance(value, int | float) and not isinstance(value, bool):
        if not (math.isfinite(value) and 0.0 <= value <= 10.0):
            raise ValueError(
                f"argument 'angle_error_deg': one value is the sigma of the orientation errors in degrees, "
                f"within [0, 10]; got {value!r}"
            )
        return float(value)
    try:
        offsets = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        offsets = ()
    if len(offsets) != 4 or not all(math.isfinite(v) and abs(v) < 22.5 for v in offsets):
        raise ValueError(
            "argument 'angle_error_deg' must be one sigma (degrees) or four finite offsets (degrees, "
            f"|offset| < 22.5) of the 0/45/90/135 deg analyzers; got {value!r}"
        )
    return offsets  # type: ignore[return-value]


@dataclasses.dataclass(frozen=True)
class SimulatedAnalyzers:
    """The simulated polarization cameras' analyzers (see the module docstring).

    Attributes:
        extinction_ratio: ``k1 / k2`` of the micro-polarizers: one value for every colour, three for R,
            G, B, or None for ideal (infinite).
        angle_error_deg: orientation errors, degrees: one sigma (random per camera, colour and
            analyzer) or four fixed offsets of the 0/45/90/135 deg analyzers.
        seed: seed of the random orientation errors (independent of the noise seed).
        calibration_supplied: write the true analyzers into the simulation's ``rig.json`` (a user who
            calibrated the sensor); False leaves ``rig.json`` ideal (a user who did not).
    """

    extinction_ratio: float | tuple[float, ...] | None = None
    angle_error_deg: float | tuple[float, float, float, float] = 0.0
    seed: int = 0
    calibration_supplied: bool = True

    def __post_init__(self) -> None:
        """Check every field (ValueError naming the argument) and store sequences as tuples."""
        ratios = _ratios(self.extinction_ratio)
        if ratios is not None and len(ratios) == 1:
            object.__setattr__(self, "extinction_ratio", ratios[0])
        else:
            object.__setattr__(self, "extinction_ratio", ratios)
        object.__setattr__(self, "angle_error_deg", _angle_errors(self.angle_error_deg))
        if isinstance(self.seed, bool) or not isinstance(self.seed, int | np.integer) or self.seed < 0:
            raise ValueError(f"argument 'analyzer_seed' must be an integer >= 0; got {self.seed!r}")
        if not isinstance(self.calibration_supplied, bool):
            raise ValueError(
                f"argument 'calibration_supplied' must be true or false; got {self.calibration_supplied!r}"
            )

    @property
    def is_ideal(self) -> bool:
        """True when every simulated analyzer is ideal (the simulator's bytes are today's)."""
        ratios = _ratios(self.extinction_ratio)
        errors = self.angle_error_deg
        no_error = errors == 0.0 if isinstance(errors, float) else all(e == 0.0 for e in errors)
        return no_error and (ratios is None or all(math.isinf(r) for r in ratios))

    def models(self, camera_number: int, colour_count: int = 3) -> tuple[AnalyzerModel, ...]:
        """The true models of the ``camera_number``-th polarimetric camera: one per colour (R, G, B), or
        one for a mono sensor (``colour_count`` 1)."""
        ratios = _ratios(self.extinction_ratio) or (math.inf,)
        models = []
        for colour in range(colour_count):
            ratio = ratios[colour] if len(ratios) == 3 and colour_count == 3 else ratios[0]
            if isinstance(self.angle_error_deg, float):
                rng = np.random.default_rng((int(self.seed), int(camera_number), colour))
                errors = rng.normal(0.0, self.angle_error_deg, 4) if self.angle_error_deg > 0 else np.zeros(4)
            else:
                errors = np.asarray(self.angle_error_deg, dtype=np.float64)
            angles = tuple(float(a + e) for a, e in zip(IDEAL_ANALYZER_ANGLES_DEG, errors, strict=True))
            models.append(AnalyzerModel(ratio, angles))
        return tuple(models)

    def camera_models(self, rig: Rig) -> dict[str, tuple[AnalyzerModel, ...]]:
        """Camera id -> the true models (:meth:`models`) of every polarization camera of ``rig``."""
        return {
            camera.id: self.models(number, 3 if camera.sensor == "color-polarization" else 1)
            for number, camera in enumerate(_polarization_cameras(rig))
        }

    def rig_for_folder(self, rig: Rig) -> Rig:
        """The rig the simulation folder records: with the true analyzers as each polarization camera's
        ``analyzer`` calibration when supplied and not ideal, else ``rig`` unchanged (ideal)."""
        if self.is_ideal or not self.calibration_supplied:
            return rig
        models = self.camera_models(rig)
        cameras = []
        for camera in rig.cameras:
            if camera.id in models:
                camera = camera.model_copy(update={"analyzer": _calibration(camera, models[camera.id])})
            cameras.append(camera.model_dump(mode="json"))
        return Rig.model_validate({**rig.model_dump(mode="json"), "cameras": cameras})

    def record(self, rig: Rig) -> dict[str, Any]:
        """``simulation.json``'s ``sensor``: the configuration, whether ``rig.json`` carries it, and the
        true models per camera (``{"R": {...}, ...}`` or one for a mono camera)."""
        cameras = {}
        for camera_id, models in self.camera_models(rig).items():
            cameras[camera_id] = (
                models[0].to_dict() if len(models) == 1
                else {colour: model.to_dict() for colour, model in zip(_COLOURS, models, strict=True)}
            )
        return {
            "ideal": self.is_ideal,
            "calibration_supplied": bool(self.calibration_supplied and not self.is_ideal),
            "config": self.to_dict(),
            "analyzers": cameras,
        }

    def to_dict(self) -> dict[str, Any]:
        """JSON form of the fields (tuples as lists)."""
        ratio = self.extinction_ratio
        errors = self.angle_error_deg
        return {
            "extinction_ratio": list(ratio) if isinstance(ratio, tuple) else ratio,
            "angle_error_deg": list(errors) if isinstance(errors, tuple) else errors,
            "seed": int(self.seed),
            "calibration_supplied": self.calibration_supplied,
        }


def _polarization_cameras(rig: Rig) -> list[Camera]:
    return [c for c in rig.polarimetric_cameras() if c.sensor in ("mono-polarization", "color-polarization")]


def _calibration(
    camera: Camera, models: tuple[AnalyzerModel, ...]
) -> AnalyzerCalibration | dict[str, AnalyzerCalibration]:
    def one(model: AnalyzerModel) -> AnalyzerCalibration:
        return AnalyzerCalibration.model_validate(model.to_dict())

    if camera.sensor != "color-polarization":
        return one(models[0])
    return {colour: one(model) for colour, model in zip(_COLOURS, models, strict=True)}
