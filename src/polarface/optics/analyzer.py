"""Non-ideal linear analyzers of a division-of-focal-plane polarization camera.

A real micro-polarizer at orientation ``a`` with extinction ratio ``ER`` (principal transmittances
``k1 > k2``, ``ER = k1 / k2``) transmits, for a linear Stokes vector ``(s0, s1, s2)``,

    ``I = (k1 + k2) / 2 * s0 + (k1 - k2) / 2 * (cos 2a * s1 + sin 2a * s2)``

(Collett, *Field Guide to Polarization*, SPIE 2005, ch. 5; Powell and Gruev, "Calibration methods for
division-of-focal-plane polarimeters", Optics Express 21(18), 2013). polarface normalises ``k1 + k2 = 1``
so that an ideal analyzer (``ER`` infinite) gives Malus' ``I = (s0 + s1 cos 2a + s2 sin 2a) / 2`` of
:func:`polarface.optics.stokes.analyzer_intensity`; the diattenuation ``d = (ER - 1) / (ER + 1)`` scales
the polarized part. A per-pixel-type gain (flat field) is outside this model: it is removed by the
camera's flat-field calibration.

The four analyzers of one camera (nominally 0, 45, 90, 135 deg) form the ``(4, 3)`` analysis matrix
``A`` (intensities ``I = A s``). Stokes estimation is the least-squares ``s = pinv(A) I``, which for the
ideal matrix is the textbook ``s0 = (I0 + I45 + I90 + I135) / 2``, ``s1 = I0 - I90``, ``s2 = I45 - I135``.
:meth:`AnalyzerModel.to_ideal` maps measured intensities to those an ideal sensor would have measured
(``A_ideal pinv(A) I``), so every stage downstream of demosaicing keeps its ideal-analyzer formulas;
:meth:`AnalyzerModel.from_ideal` is the forward model the simulator uses.

Angles are in degrees here (as in ``rig.json`` and ``scene.json``), measured from the image +x axis,
counter-clockwise as seen by the camera (``docs/conventions.md``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, TypeVar

import numpy as np
import torch

__all__ = ["IDEAL_ANALYZER_ANGLES_DEG", "AnalyzerModel"]

#: Nominal analyzer orientations of a 2x2 polarization super-pixel, degrees, in polarface's order.
IDEAL_ANALYZER_ANGLES_DEG = (0.0, 45.0, 90.0, 135.0)

Array = TypeVar("Array", np.ndarray, torch.Tensor)


@dataclasses.dataclass(frozen=True)
class AnalyzerModel:
    """The four analyzers of one polarization camera (or one colour channel of it).

    Attributes:
        extinction_ratio: ``k1 / k2`` of the micro-polarizers, > 1; ``math.inf`` is ideal.
        angles_deg: orientations of the analyzers polarface calls 0, 45, 90 and 135 deg, in degrees
            from image +x (counter-clockwise as seen by the camera).
    """

    extinction_ratio: float = math.inf
    angles_deg: tuple[float, float, float, float] = IDEAL_ANALYZER_ANGLES_DEG

    def __post_init__(self) -> None:
        ratio = float(self.extinction_ratio)
        if math.isnan(ratio) or ratio <= 1.0:
            raise ValueError(f"extinction_ratio must be > 1 (inf for ideal); got {self.extinction_ratio}")
        angles = tuple(float(a) for a in np.asarray(self.angles_deg, dtype=np.float64).reshape(-1))
        if len(angles) != 4 or not all(math.isfinite(a) for a in angles):
            raise ValueError(
                f"analyzer_angles_deg must hold 4 finite angles in degrees; got {self.angles_deg}"
            )
        for got, nominal in zip(angles, IDEAL_ANALYZER_ANGLES_DEG, strict=True):
            if abs(got - nominal) > 22.5:
                raise ValueError(
                    f"analyzer_angles_deg must lie within 22.5 deg of {list(IDEAL_ANALYZER_ANGLES_DEG)} "
                    f"(the order 0, 45, 90, 135); got {list(angles)}"
                )
        object.__setattr__(self, "extinction_ratio", ratio)
        object.__setattr__(self, "angles_deg", angles)

    @classmethod
    def from_dict(cls, payload: dict[str, Any] | None, name: str = "polarizer") -> AnalyzerModel:
        """The model of ``{"extinction_ratio": ER, "analyzer_angles_deg": [a0, a45, a90, a135]}``
        (both optional; None or missing gives the ideal analyzer). Errors name ``name``."""
        if payload is None:
            return cls()
        if not isinstance(payload, dict):
            raise ValueError(f"{name} must be an object with extinction_ratio and analyzer_angles_deg")
        unknown = sorted(set(payload) - {"extinction_ratio", "analyzer_angles_deg"})
        if unknown:
            raise ValueError(
                f"{name}: unknown field(s) {unknown}; allowed: extinction_ratio, analyzer_angles_deg"
            )
        ratio = payload.get("extinction_ratio")
        angles = payload.get("analyzer_angles_deg", IDEAL_ANALYZER_ANGLES_DEG)
        try:
            return cls(math.inf if ratio is None else float(ratio), tuple(np.asarray(angles, float).ravel()))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{name}: {exc}") from None

    def to_dict(self) -> dict[str, Any]:
        """JSON form (``extinction_ratio`` None when ideal), inverse of :meth:`from_dict`."""
        ratio = None if math.isinf(self.extinction_ratio) else self.extinction_ratio
        return {"extinction_ratio": ratio, "analyzer_angles_deg": list(self.angles_deg)}

    @property
    def is_ideal(self) -> bool:
        """True for infinite extinction ratio at exactly 0, 45, 90, 135 deg."""
        return math.isinf(self.extinction_ratio) and self.angles_deg == IDEAL_ANALYZER_ANGLES_DEG

    @property
    def diattenuation(self) -> float:
        """``d = (ER - 1) / (ER + 1)`` in (0, 1]; 1 for the ideal analyzer."""
        ratio = self.extinction_ratio
        return 1.0 if math.isinf(ratio) else (ratio - 1.0) / (ratio + 1.0)

    def analysis_matrix(self) -> np.ndarray:
        """``(4, 3)`` float64 matrix ``A`` with ``(I0, I45, I90, I135) = A (s0, s1, s2)``."""
        two_a = 2.0 * np.deg2rad(np.asarray(self.angles_deg, dtype=np.float64))
        d = self.diattenuation
        return 0.5 * np.stack([np.ones(4), d * np.cos(two_a), d * np.sin(two_a)], axis=-1)

    def stokes_matrix(self) -> np.ndarray:
        """``(3, 4)`` float64 least-squares estimator ``pinv(A)``: ``s = pinv(A) I``."""
        return np.linalg.pinv(self.analysis_matrix())

    def to_ideal_matrix(self) -> np.ndarray:
        """``(4, 4)`` float64 map from measured to ideal-analyzer intensities, ``A_ideal pinv(A)``.

        For ideal analyzers this is the projection onto consistent intensities (I0 + I90 = I45 + I135),
        not the identity: callers pass ideal data through untouched (:attr:`is_ideal`)."""
        return AnalyzerModel().analysis_matrix() @ self.stokes_matrix()

    def from_ideal_matrix(self) -> np.ndarray:
        """``(4, 4)`` float64 map from ideal-analyzer to measured intensities, ``A pinv(A_ideal)``."""
        return self.analysis_matrix() @ AnalyzerModel().stokes_matrix()

    def measure(self, stokes: Array) -> Array:
        """Intensities ``(..., 4)`` (I0, I45, I90, I135) behind these analyzers of linear Stokes
        vectors ``(..., 3)`` (or ``(..., 4)``, s3 ignored), same kind/dtype as the input."""
        return _apply(self.analysis_matrix(), stokes[..., :3])

    def stokes(self, intensities: Array) -> Array:
        """Least-squares linear Stokes ``(..., 3)`` of measured intensities ``(..., 4)``."""
        return _apply(self.stokes_matrix(), _check_four(intensities))

    def to_ideal(self, intensities: Array) -> Array:
        """Measured ``(..., 4)`` -> what ideal 0/45/90/135 analyzers would have measured ``(..., 4)``."""
        return _apply(self.to_ideal_matrix(), _check_four(intensities))

    def from_ideal(self, intensities: Array) -> Array:
        """Ideal-analyzer intensities ``(..., 4)`` -> what these analyzers measure ``(..., 4)``."""
        return _apply(self.from_ideal_matrix(), _check_four(intensities))


def _check_four(intensities: Array) -> Array:
    if intensities.shape[-1:] != (4,):
        raise ValueError(
            f"intensities must have a last axis of 4 (I0, I45, I90, I135); got {tuple(intensities.shape)}"
        )
    return intensities


def _apply(matrix: np.ndarray, values: Array) -> Array:
    """``matrix @ values[..., :, None]`` for numpy or torch ``values`` (matrix cast to its dtype)."""
    if isinstance(values, torch.Tensor):
        weights = torch.as_tensor(matrix, dtype=values.dtype, device=values.device)
        return torch.einsum("ij,...j->...i", weights, values)
    values = np.asarray(values)
    dtype = values.dtype if np.issubdtype(values.dtype, np.floating) else np.float64
    return np.einsum("ij,...j->...i", matrix.astype(dtype), values.astype(dtype, copy=False))
