"""The dynamic metrics' computations on arrays, without files (definitions in
:mod:`polarface.evaluate.dynamic.metrics`): the pressed-patch weight, which the simulator does not store
(:func:`pressed_patch_weight`), the time constant of the blood-flow recovery
(:func:`fit_recovery_time_constant`) and the material-point tracking errors
(:func:`material_point_errors`). Positions in mm, haemoglobin as volume fractions, times in s.
"""

from __future__ import annotations

import numpy as np

from polarface.geometry.raycast import closest_surface_points

__all__ = [
    "fit_recovery_time_constant", "material_point_errors", "material_point_tracking", "pressed_patch_weight",
]


def pressed_patch_weight(static_c_h_out: np.ndarray, first_c_h_out: np.ndarray, pressed_fraction: float = 0.8
                         ) -> np.ndarray:
    """``(H, W)`` float64 pressed-patch weight ``w = (1 - c0 / cs) / pressed_fraction`` in [0, 1] from
    the static outer haemoglobin ``cs`` and the first dynamic frame's ``c0`` (both ``(H, W)``, volume
    fractions); 0 where ``cs <= 0``."""
    static = np.asarray(static_c_h_out, np.float64)
    first = np.asarray(first_c_h_out, np.float64)
    if static.shape != first.shape:
        raise ValueError(f"argument 'first_c_h_out' is {first.shape}; expected the static map's "
                         f"{static.shape}")
    ratio = np.divide(first, static, out=np.ones_like(static), where=static > 0)
    return np.clip((1.0 - ratio) / pressed_fraction, 0.0, 1.0)


def fit_recovery_time_constant(times_s: np.ndarray, values: np.ndarray, min_frames: int = 3) -> float | None:
    """The time constant ``tau`` (s) of ``c(t) = a - b exp(-t / tau)`` fitted to ``values`` ``(F,)`` at
    ``times_s`` ``(F,)`` (scipy ``curve_fit``, ``tau`` bounded to [1e-3, 1e3] s); None with fewer than
    ``min_frames`` finite points or when the fit does not converge."""
    from scipy.optimize import curve_fit

    times, values = np.asarray(times_s, np.float64), np.asarray(values, np.float64)
    if times.shape != values.shape:
        raise ValueError(f"argument 'values' is {values.shape}; expected the shape of 'times_s' "
                         f"{times.shape}")
    finite = np.isfinite(times) & np.isfinite(values)
    times, values = times[finite], values[finite]
    if times.size < max(min_frames, 3):
        return None
    start = times - times.min()
    span = max(float(start.max()), 1e-3)

    def model(t: np.ndarray, a: float, b: float, tau: float) -> np.ndarray:
        return a - b * np.exp(-t / tau)

    guess = (float(values[np.argmax(start)]), float(values[np.argmax(start)] - values[np.argmin(start)]),
             span / 3.0)
    try:
        fitted, _ = curve_fit(model, start, values, p0=guess,
                              bounds=([-np.inf, -np.inf, 1e-3], [np.inf, np.inf, 1e3]), maxfev=20000)
    except (RuntimeError, ValueError):
        return None
    return float(fitted[2])


def material_point_errors(tracked_mm: np.ndarray, confidence: np.ndarray, truth_vertices_mm: np.ndarray,
                          truth_faces: np.ndarray, max_distance_mm: float = 5.0) -> list[np.ndarray]:
    """Per tracked frame, the distances (mm) of the scored material points (module docstring).

    Args:
        tracked_mm: ``(T, N, 3)`` tracked vertex positions, rig world, mm (frame 0 defines the points).
        confidence: ``(T, N)`` tracking confidence (a vertex counts at ``t`` when it is > 0).
        truth_vertices_mm: ``(T, M, 3)`` ground-truth vertices of the same frames, rig world, mm.
        truth_faces: ``(F, 3)`` their triangles.
        max_distance_mm: vertices farther than this from the frame-0 ground truth are not scored.

    Returns:
        T arrays of errors (mm), one per frame, of the counted vertices.
    """
    return [errors for errors, _ in material_point_tracking(
        tracked_mm, confidence, truth_vertices_mm, truth_faces, max_distance_mm)]


def material_point_tracking(tracked_mm: np.ndarray, confidence: np.ndarray, truth_vertices_mm: np.ndarray,
                            truth_faces: np.ndarray, max_distance_mm: float = 5.0
                            ) -> list[tuple[np.ndarray, np.ndarray]]:
    """:func:`material_point_errors` (same arguments) with each counted point's true motion: per tracked
    frame ``(errors (M_t,) mm, motion (M_t,) mm)``, ``motion`` the distance the material point truly
    moved from frame 0 (rig world)."""
    tracked = np.asarray(tracked_mm, np.float64)
    truth = np.asarray(truth_vertices_mm, np.float64)
    if tracked.ndim != 3 or truth.ndim != 3 or len(tracked) != len(truth):
        raise ValueError(f"arguments 'tracked_mm' {tracked.shape} and 'truth_vertices_mm' {truth.shape} "
                         "must be (T, N, 3) and (T, M, 3) with the same T")
    if np.shape(confidence) != tracked.shape[:2]:
        raise ValueError(f"argument 'confidence' is {np.shape(confidence)}; expected {tracked.shape[:2]}")
    faces = np.asarray(truth_faces, np.int64)
    closest = closest_surface_points(truth[0], faces, tracked[0])
    on_surface = closest.distance <= max_distance_mm
    start = np.einsum("nk,nkc->nc", closest.barycentric, truth[0][faces[closest.face]])
    results = []
    for t in range(len(tracked)):
        where = np.einsum("nk,nkc->nc", closest.barycentric, truth[t][faces[closest.face]])
        counted = on_surface & (np.asarray(confidence[t]) > 0)
        results.append((np.linalg.norm(tracked[t][counted] - where[counted], axis=1),
                        np.linalg.norm(where[counted] - start[counted], axis=1)))
    return results

