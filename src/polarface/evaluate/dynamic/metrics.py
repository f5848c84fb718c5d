"""Metrics of a dynamic reconstruction against simulator ground truth (``polarface evaluate``, group
``dynamic``).

Inputs. The RESULT holds the static reconstruction and, per dynamic frame ``t``, ``frames/NNNN/``
(its tracked ``mesh.obj`` in the static model frame and its maps, ``docs/result_folder.md``), the
tracking ``tracking/tracked.npz`` (``frames (T,)``, ``vertices (T, N, 3)`` dynamic rig world, mm,
``confidence (T, N)``, vertex order of ``RESULT/mesh.obj``) and ``result.json``'s ``stages.dynamic``
(``completed`` frames, ``timestamps_s``, ``alignment``: static model frame -> dynamic rig world,
``seconds_per_frame``). The ground truth (``SIM/ground_truth``) holds the static maps and rest mesh
and ``dynamic/meshes/NNNNNN.ply`` (rest-mesh topology, rig world, mm) and
``dynamic/maps/NNNNNN_c_h_out.exr`` / ``NNNNNN_rho_sss_bar.exr`` (every other map is the static one:
the simulated dynamic sequence changes only the geometry and the outer haemoglobin,
``src/polarface/simulate/sequences.py``). Their readers: :mod:`polarface.evaluate.dynamic.inputs`.

Evaluated frames: the frames of ``stages.dynamic.completed`` whose folder holds ``maps/mask.png``,
ascending; every per-frame list below follows that order (``frames`` is their count).

Texel correspondence: :func:`polarface.evaluate.correspondence.texel_correspondence` of the
static RESULT with the ground truth, the same for every frame because the tracked meshes keep the
RESULT's faces and UVs (a texel is one material point in every frame) and the ground truth's dynamic
meshes keep the rest mesh's. Ground-truth maps are looked up with ``TexelCorrespondence.truth_map`` over the
ground-truth mask; a texel of frame ``t`` counts when it is in the frame's mask and in
``truth_mask`` (its ground-truth counterpart is valid).

Definitions (:class:`DynamicEvaluationConfig` holds the constants; the computations on arrays are in
:mod:`polarface.evaluate.dynamic.measures`):

* ``tracking_mm``: material points. Each tracked vertex's position in the first tracked frame ``t0`` is
  projected to the closest point of the ground-truth frame-``t0`` mesh (triangle and barycentric coordinates,
  :func:`polarface.geometry.raycast.closest_surface_points`); vertices farther than
  ``max_material_distance_mm`` (5 mm) are left out (off the ground-truth surface, e.g. outside the simulated
  head). The same barycentric coordinates on the ground-truth frame-``t`` mesh are where that material point
  truly is at ``t``; the error is its distance to the tracked position at ``t``, over the vertices with
  ``confidence > 0`` at ``t``. ``median_per_frame``: the median per evaluated frame; ``max``: the largest
  per-frame ``tracking_tail_percentile`` (90th) percentile (the worst frame's tail). The moving region:
  ``moving_median_per_frame`` and ``moving_max``, the same over the points that truly moved more than
  ``moving_mm`` (2 mm) from the first frame (the brows, the mouth corners, the jaw and lips; None in a
  frame where nothing moved). Targets (issue 50): median <= 0.2 mm every frame, max <= 1.0 mm.
* pressed-patch weight ``w``: not stored by the simulator. Its frame 0 lowers the outer haemoglobin to
  ``c0 = cs (1 - 0.8 w)`` (``cs`` the static map; the pressure is released at ``t = 0``, where
  ``blood_flow_factor`` is 0), so ``w = (1 - c0 / cs) / 0.8`` where ``cs > 0`` (0 elsewhere)
  (:func:`pressed_patch_weight`). Patch texels: ``w > patch_weight_threshold`` (0.5) on the RESULT
  atlas.
* ``c_h_out_patch_abs_error``: per frame, median ``|C_h_out - C_h_out_gt|`` over the patch texels.
* ``recovery_time_constant_s``: ``c(t) = a - b exp(-t / tau)`` fitted (least squares, ``tau > 0``,
  :func:`fit_recovery_time_constant`) to the patch's mean C_h_out per evaluated frame against its
  timestamp (``stages.dynamic.timestamps_s``, else the dynamic capture's ``manifest.json``), over one
  texel set for all frames (the patch texels inside every evaluated frame's mask), for the
  ground truth (``ground_truth``; the simulator's tau is 2 s / 3 = 0.667 s) and the reconstruction
  (``reconstructed``); None with fewer than ``min_fit_frames`` (3) frames or when the fit fails. The
  mean, not the median: every texel recovers as ``cs (1 - 0.8 w exp(-t / tau))`` with the same tau,
  so their mean is the same exponential, while the median switches texels as their order changes
  (on the demo preset's ground truth the median gives 0.72 s, the mean 2/3 s).
* ``c_m_patch_drift_max``: the largest ``|median_patch C_m(t) - median_patch C_m(t_first)|`` (the
  melanin must not move when only blood changes; 0 with one frame).
* ``rho_sss_bar_median_relative_error``: per frame, median over texels and channels of
  ``|rho - rho_gt| / rho_gt`` (``rho_gt`` floored at 1e-6).
* ``normal_median_deg``: per frame, the median angle between the frame's shading normal (its
  ``mesh.obj`` rasterised at the maps' resolution, displaced by its ``displacement_mm``, rotated into
  the dynamic rig world by ``alignment``) and the ground truth's (the rest mesh with the frame's PLY
  vertices, displaced by the static ground-truth displacement, rig world), looked up at the
  corresponding texel (``truth_normals``).
* ``rho_s_flicker_median``: ``|rho_s(t) - rho_s(t')| / rho_s(t')`` for consecutive evaluated frames
  ``t' < t`` over the texels in both frames' masks, median over all texels and pairs; the ground-truth
  rho_s does not change in the dynamic sequence, so every texel counts (None with one frame).
* ``seconds_per_frame``: ``stages.dynamic.seconds_per_frame`` (None when not recorded).
"""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path
from typing import Any

import numpy as np

from polarface.evaluate.correspondence import (
    TexelCorrespondence,
    texel_correspondence,
)
from polarface.evaluate.dynamic.inputs import (
    DynamicInputs,
    load_dynamic_inputs,
    truth_frame_map,
    truth_frame_mesh,
)
from polarface.evaluate.dynamic.measures import (
    fit_recovery_time_constant,
    material_point_tracking,
    pressed_patch_weight,
)
from polarface.geometry import load_mesh, rasterize_uv
from polarface.results import RHO_SSS_BAR, ResultFolder, layout
from polarface.simulate.layout import REST_MESH_OBJ, ground_truth_folder

__all__ = [
    "DYNAMIC_METRIC_KEYS",
    "DynamicEvaluationConfig",
    "dynamic_group",
    "dynamic_metrics",
]

#: The keys of :func:`dynamic_metrics`'s answer (module docstring).
DYNAMIC_METRIC_KEYS = (
    "frames", "tracking_mm", "c_h_out_patch_abs_error", "recovery_time_constant_s", "c_m_patch_drift_max",
    "rho_sss_bar_median_relative_error", "normal_median_deg", "rho_s_flicker_median", "seconds_per_frame",
)


@dataclasses.dataclass(frozen=True)
class DynamicEvaluationConfig:
    """Constants of the dynamic metrics (module docstring).

    Attributes:
        patch_weight_threshold: texels with pressed-patch weight above this form the patch (1).
        pressed_fraction: fraction of the outer haemoglobin removed at full weight in frame 0 (1; the
            simulator's 0.8, ``src/polarface/simulate/sequences.py``).
        max_material_distance_mm: tracked vertices farther than this from the ground-truth surface in
            the first tracked frame are not scored (mm).
        tracking_tail_percentile: percentile of a frame's errors whose largest value is ``max`` (%).
        min_fit_frames: fewest frames to fit the recovery time constant.
        moving_mm: material points that truly moved farther than this from the first frame form the
            moving region of ``tracking_mm`` (mm).
    """

    patch_weight_threshold: float = 0.5
    pressed_fraction: float = 0.8
    max_material_distance_mm: float = 5.0
    tracking_tail_percentile: float = 90.0
    min_fit_frames: int = 3
    moving_mm: float = 2.0


# ---- tracking ------------------------------------------------------------------------------------
def _tracking(inputs: DynamicInputs, rest, config: DynamicEvaluationConfig) -> dict[str, Any]:
    path = inputs.result.tracking_dir / layout.TRACKED_NPZ
    if not path.is_file():
        raise FileNotFoundError(f"tracking file '{path}' does not exist")
    with np.load(path) as data:
        try:
            tracked_frames = [int(t) for t in data["frames"]]
            vertices, confidence = np.asarray(data["vertices"]), np.asarray(data["confidence"])
        except KeyError as exc:
            raise ValueError(f"tracking file '{path}' lacks the array {exc}") from exc
    truth = np.stack([truth_frame_mesh(inputs.truth_root, rest, t).vertices for t in tracked_frames])
    measured = dict(zip(tracked_frames, material_point_tracking(
        vertices, confidence, truth, rest.faces, config.max_material_distance_mm), strict=True))
    empty = (np.zeros(0), np.zeros(0))
    scored = [measured.get(t, empty) for t in inputs.frames]
    tails = [float(np.percentile(e, config.tracking_tail_percentile)) for e, _ in scored if e.size]
    moving = [e[m > config.moving_mm] for e, m in scored]
    moving_tails = [float(np.percentile(e, config.tracking_tail_percentile)) for e in moving if e.size]
    return {"median_per_frame": [_median(e) for e, _ in scored],
            "max": max(tails) if tails else None,
            "moving_median_per_frame": [_median(e) for e in moving],
            "moving_max": max(moving_tails) if moving_tails else None}


# ---- maps ----------------------------------------------------------------------------------------
def _frame_normals(frame: ResultFolder, displacement_mm: np.ndarray, alignment: np.ndarray) -> np.ndarray:
    """The frame's shading normals ``(Ht, Wt, 3)`` in the dynamic rig world (module docstring)."""
    from polarface.render import shading_normals

    raster = rasterize_uv(frame.read_mesh(), displacement_mm.shape)
    normals = np.nan_to_num(shading_normals(raster, displacement_mm))
    return normals @ alignment[:3, :3].T


def _truth_normals(truth_mesh, displacement_mm: np.ndarray) -> np.ndarray:
    from polarface.render import shading_normals

    raster = rasterize_uv(truth_mesh, displacement_mm.shape)
    return np.nan_to_num(shading_normals(raster, displacement_mm))


def _median(values: np.ndarray) -> float | None:
    return float(np.median(values)) if values.size else None


def _mean(values: np.ndarray) -> float | None:
    return float(np.mean(values)) if values.size else None


@dataclasses.dataclass(frozen=True)
class _TruthOnResult:
    """The static ground truth on the RESULT atlas (``(Ht, Wt)`` arrays) and what the lookups need."""

    correspondence: TexelCorrespondence
    gt_mask: np.ndarray
    valid: np.ndarray
    patch: np.ndarray
    displacement_mm: np.ndarray


def _truth_on_result(inputs: DynamicInputs, shape: tuple[int, int], config: DynamicEvaluationConfig
                     ) -> _TruthOnResult:
    truth = ResultFolder(inputs.truth_root)
    gt_mask = truth.read_mask()
    correspondence = texel_correspondence(inputs.result.root, inputs.truth_root, shape)
    first = truth_frame_map(inputs.truth_root, 0, "c_h_out", [])
    weight = pressed_patch_weight(truth.read_scalar_map("c_h_out"), first, config.pressed_fraction)
    valid = correspondence.truth_mask(gt_mask)
    patch = valid & (correspondence.truth_map(weight, gt_mask) > config.patch_weight_threshold)
    displacement = truth.read_scalar_map("displacement_mm").astype(np.float64)
    return _TruthOnResult(correspondence, gt_mask, valid, patch, displacement)


def _frame_values(inputs: DynamicInputs, frame_index: int, truth: _TruthOnResult, rest, names: list[str]
                  ) -> dict[str, Any]:
    """One frame's map errors, patch medians, rho_s and mask."""
    frame = inputs.result.frame(frame_index)
    mask = frame.read_mask() & truth.valid
    patch = mask & truth.patch
    on_result = lambda values: truth.correspondence.truth_map(values, truth.gt_mask)  # noqa: E731
    c_h_out = frame.read_scalar_map("c_h_out").astype(np.float64)
    c_h_out_gt = on_result(truth_frame_map(inputs.truth_root, frame_index, "c_h_out", names))
    rho = frame.read_channel_map(RHO_SSS_BAR, names, strict=False).astype(np.float64)
    rho_gt = on_result(truth_frame_map(inputs.truth_root, frame_index, RHO_SSS_BAR, names))
    relative = np.abs(rho - rho_gt)[mask] / np.maximum(rho_gt[mask], 1e-6)
    displacement = frame.read_scalar_map("displacement_mm").astype(np.float64)
    normals = _frame_normals(frame, displacement, inputs.alignment)
    normals_gt = truth.correspondence.truth_normals(
        _truth_normals(truth_frame_mesh(inputs.truth_root, rest, frame_index), truth.displacement_mm),
        truth.gt_mask)
    unit = (np.linalg.norm(normals, axis=-1) > 0.5) & (np.linalg.norm(normals_gt, axis=-1) > 0.5)
    normal_valid = mask & unit
    cosine = np.clip((normals * normals_gt).sum(-1)[normal_valid], -1.0, 1.0)
    return {
        "mask": frame.read_mask(),
        "rho_s": frame.read_scalar_map("rho_s").astype(np.float64),
        "c_h_out_abs_error": _median(np.abs(c_h_out - c_h_out_gt)[patch]),
        "c_h_out": c_h_out,
        "c_h_out_gt": c_h_out_gt,
        "c_m_patch": _median(frame.read_scalar_map("c_m").astype(np.float64)[patch]),
        "rho_relative_error": _median(relative),
        "normal_deg": _median(np.degrees(np.arccos(cosine))),
    }


def _flicker(frames: list[dict[str, Any]]) -> float | None:
    changes = []
    for before, after in itertools.pairwise(frames):
        both = before["mask"] & after["mask"]
        previous = before["rho_s"][both]
        changes.append(np.abs(after["rho_s"][both] - previous) / np.maximum(np.abs(previous), 1e-6))
    pooled = np.concatenate(changes) if changes else np.zeros(0)
    return _median(pooled)


def _drift(values: list[float | None]) -> float | None:
    finite = [v for v in values if v is not None]
    return max(abs(v - finite[0]) for v in finite) if finite else None


def _fit(times: np.ndarray, values: list[float | None], config: DynamicEvaluationConfig) -> float | None:
    series = np.array([np.nan if v is None else v for v in values], np.float64)
    return fit_recovery_time_constant(times, series, config.min_fit_frames)


# ---- public entry points -------------------------------------------------------------------------
def dynamic_metrics(result_dir: str | Path, gt_dir: str | Path,
                    config: DynamicEvaluationConfig | None = None) -> dict[str, Any]:
    """The dynamic metrics (module docstring) with exactly the keys :data:`DYNAMIC_METRIC_KEYS`.

    Values that cannot be computed (no patch texel, no tracked vertex in a frame, too few frames for a
    fit) are None.

    Raises:
        FileNotFoundError: the RESULT has no ``result.json`` or no per-frame folder, the ground truth no
            ``dynamic/``, or a file the metrics read is missing (naming it).
        ValueError: ``stages.dynamic`` is missing or malformed, no completed frame has maps, a frame has
            no timestamp, or a file is malformed (naming it).
    """
    config = config or DynamicEvaluationConfig()
    inputs = load_dynamic_inputs(result_dir, gt_dir)
    rest_path = inputs.truth_root / REST_MESH_OBJ
    if not rest_path.is_file():
        raise FileNotFoundError(f"ground-truth rest mesh '{rest_path}' does not exist")
    rest = load_mesh(rest_path)
    names = inputs.result.channel_names()
    shape = inputs.result.frame(inputs.frames[0]).read_mask().shape
    truth = _truth_on_result(inputs, shape, config)
    frames = [_frame_values(inputs, t, truth, rest, names) for t in inputs.frames]
    # the recovery curves average one texel set over all frames: the patch texels in every frame's mask
    common = truth.patch & truth.valid & np.logical_and.reduce([f["mask"] for f in frames])
    seconds = inputs.record.get("seconds_per_frame")
    return {
        "frames": len(inputs.frames),
        "tracking_mm": _tracking(inputs, rest, config),
        "c_h_out_patch_abs_error": [f["c_h_out_abs_error"] for f in frames],
        "recovery_time_constant_s": {
            name: _fit(inputs.timestamps_s, [_mean(f[key][common]) for f in frames], config)
            for name, key in (("ground_truth", "c_h_out_gt"), ("reconstructed", "c_h_out"))
        },
        "c_m_patch_drift_max": _drift([f["c_m_patch"] for f in frames]),
        "rho_sss_bar_median_relative_error": [f["rho_relative_error"] for f in frames],
        "normal_median_deg": [f["normal_deg"] for f in frames],
        "rho_s_flicker_median": _flicker(frames),
        "seconds_per_frame": float(seconds) if isinstance(seconds, int | float) else None,
    }


def dynamic_group(result_dir: str | Path, gt_dir: str | Path) -> dict[str, Any]:
    """``polarface evaluate``'s ``dynamic`` group: :func:`dynamic_metrics`, or ``{"skipped": reason}``
    when the RESULT has no per-frame folder or the ground truth no ``dynamic/``."""
    if not ResultFolder(result_dir).frame_indices():
        return {"skipped": "the RESULT has no per-frame folders (the dynamic stage has not run)"}
    try:
        ground_truth_folder(gt_dir, require="dynamic")
    except FileNotFoundError:
        return {"skipped": "the ground truth has no dynamic sequence (ground_truth/dynamic)"}
    return dynamic_metrics(result_dir, gt_dir)
