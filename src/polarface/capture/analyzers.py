"""Non-ideal micro-polarizers of a rig camera applied to its demosaiced analyzer images.

A camera whose ``rig.json`` entry carries an ``analyzer`` calibration (extinction ratio and analyzer
orientations, camera-wide or per colour:
:class:`polarface.capture.rig_components.AnalyzerCalibration`) measures ``I = A s`` with a non-ideal
analysis matrix ``A`` (:class:`polarface.optics.analyzer.AnalyzerModel`).
:func:`ideal_analyzer_intensities` maps its demosaiced ``(I0, I45, I90, I135)`` to ``A_ideal pinv(A) I``,
what ideal analyzers would have measured of the least-squares Stokes vector, so every stage after
demosaicing (observations, DoP, AoLP, the inverse) keeps its ideal-analyzer formulas and is unbiased.
:func:`polarface.capture.demosaic.demosaic_camera` applies it; ideal cameras are passed through bit for
bit. :func:`analyzer_record` is what the capture store records as applied. Details: ``docs/sensors.md``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from polarface.optics.analyzer import AnalyzerModel

if TYPE_CHECKING:
    from polarface.capture.rig import Camera, Rig

__all__ = [
    "analyzer_record", "applied_analyzers", "camera_analyzer_models", "ideal_analyzer_intensities",
    "measured_analyzer_intensities",
]


def camera_analyzer_models(camera: Camera) -> tuple[AnalyzerModel, ...]:
    """The analyzer models of a polarization camera: one ``(model,)`` for a mono sensor, three (R, G, B)
    for a colour sensor; ideal where ``rig.json`` gives no ``analyzer`` (``docs/sensors.md``)."""
    if camera.sensor == "color-polarization":
        return tuple(camera.analyzer_model(colour) for colour in ("R", "G", "B"))
    return (camera.analyzer_model(None),)


def analyzer_record(camera: Camera) -> dict[str, Any] | None:
    """What :func:`demosaic_camera` applies for ``camera``, as JSON for the capture store's manifest and
    frame markers: None for ideal analyzers (nothing applied), else ``{"extinction_ratio",
    "analyzer_angles_deg"}`` (camera-wide) or ``{"R": {...}, "G": {...}, "B": {...}}`` (per colour)."""
    models = camera_analyzer_models(camera)
    if all(model.is_ideal for model in models):
        return None
    if len(set(models)) == 1:
        return models[0].to_dict()
    return {colour: model.to_dict() for colour, model in zip("RGB", models, strict=True)}


def applied_analyzers(rig: Rig) -> dict[str, dict[str, Any]] | None:
    """Camera id -> :func:`analyzer_record` for the polarization cameras of ``rig`` whose analyzers are
    not ideal (what demosaicing applies; recorded in the capture store's manifest and frame markers);
    None when every camera is ideal."""
    records = {
        camera.id: analyzer_record(camera) for camera in rig.cameras if camera.sensor != "rgb"
    }
    records = {camera_id: record for camera_id, record in records.items() if record is not None}
    return records or None


def ideal_analyzer_intensities(
    intensities: np.ndarray, models: AnalyzerModel | Sequence[AnalyzerModel]
) -> np.ndarray:
    """Measured analyzer images -> what ideal 0/45/90/135 deg analyzers would have measured.

    Per pixel ``I_ideal = A_ideal pinv(A) I`` (:meth:`polarface.optics.analyzer.AnalyzerModel.to_ideal`):
    the least-squares Stokes vector of the four measured intensities under the calibrated analysis
    matrix ``A``, re-analysed by ideal analyzers (``docs/sensors.md``).

    Args:
        intensities: float ``(4, H, W)`` (mono) or ``(4, H, W, 3)`` (colour, R G B), ordered I0, I45, I90,
            I135 (a :class:`PolarizationStack`'s ``intensities``).
        models: one model for every colour, or one per colour channel (1 for mono, 3 for R, G, B).

    Returns:
        float32 array of the same shape; ``intensities`` itself (not a copy) when every model is ideal, so
        ideal captures stay bit-identical.

    Raises:
        ValueError: a first axis other than 4, or a model count that does not match the colour channels.
    """
    return _apply_per_colour(intensities, models, "to_ideal_matrix")


def measured_analyzer_intensities(
    intensities: np.ndarray, models: AnalyzerModel | Sequence[AnalyzerModel]
) -> np.ndarray:
    """Ideal-analyzer images -> what the analyzers ``models`` measure (the forward model, inverse of
    :func:`ideal_analyzer_intensities`): per pixel ``A pinv(A_ideal) I``
    (:meth:`polarface.optics.analyzer.AnalyzerModel.from_ideal`). For the simulator.

    Args:
        intensities: float ``(4, H, W)`` or ``(4, H, W, 3)`` ideal-analyzer images (I0, I45, I90, I135).
        models: one model for every colour, or one per colour channel.

    Returns:
        float32 array of the same shape; ``intensities`` itself when every model is ideal.
    """
    return _apply_per_colour(intensities, models, "from_ideal_matrix")


def _apply_per_colour(
    intensities: np.ndarray, models: AnalyzerModel | Sequence[AnalyzerModel], matrix_name: str
) -> np.ndarray:
    """``M intensities`` along axis 0 with ``M = getattr(model, matrix_name)()`` of each colour's model."""
    models = (models,) if isinstance(models, AnalyzerModel) else tuple(models)
    array = np.asarray(intensities)
    if array.ndim not in (3, 4) or array.shape[0] != 4:
        raise ValueError(
            "argument 'intensities' must be (4, H, W) or (4, H, W, 3) (I0, I45, I90, I135); "
            f"got {array.shape}"
        )
    channels = array.shape[-1] if array.ndim == 4 else 1
    if len(models) not in (1, channels):
        raise ValueError(
            f"argument 'models' must hold 1 or {channels} analyzer model(s) for {channels} colour "
            f"channel(s); got {len(models)}"
        )
    if all(model.is_ideal for model in models):
        return intensities
    out = np.empty(array.shape, dtype=np.float32)
    if array.ndim == 3 or len(models) == 1:
        matrix = getattr(models[0], matrix_name)().astype(np.float32)
        np.einsum("ij,j...->i...", matrix, array.astype(np.float32, copy=False), out=out)
        return out
    for channel, model in enumerate(models):
        matrix = getattr(model, matrix_name)().astype(np.float32)
        out[..., channel] = np.einsum("ij,j...->i...", matrix, array[..., channel].astype(np.float32))
    return out
