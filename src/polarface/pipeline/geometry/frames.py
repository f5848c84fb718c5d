"""One frame of the geometry stage: stereo of its pairs, their clouds fused on a voxel grid and, when
asked, meshed (paper Sec. "Geometry Reconstruction and Tracking"), as an executor unit
(:class:`StereoFrameUnit`, :func:`run_stereo_frame_unit`) that the static stage
(:func:`polarface.pipeline.geometry.stage.reconstruct_geometry`) and the dynamic stage's stereo pass
(:mod:`polarface.pipeline.dynamic.tracking`) both run. Units: mm, rig world.
"""

from __future__ import annotations

import dataclasses
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from polarface.capture.store import CaptureStore
from polarface.executors import Executor, UnitOutcome, map_units_with_progress
from polarface.geometry.fusion import confident_points, poisson_mesh
from polarface.geometry.mesh import TriangleMesh, save_ply
from polarface.geometry.point_cloud import PointCloud, save_point_cloud
from polarface.geometry.stereo import StereoConfig, StereoDepth, match_stereo_pair, rectify_pair
from polarface.pipeline.geometry.config import GeometryConfig

__all__ = [
    "FrameGeometry", "StereoFrameUnit", "frame_geometry", "frame_stereo",
    "run_stereo_frame_unit", "run_stereo_units", "write_frame_geometry",
]


def frame_stereo(
    store: CaptureStore, frame_index: int, config: StereoConfig
) -> list[tuple[str, StereoDepth]]:
    """Dense stereo of every stereo pair of one frame: ``[(pair name, StereoDepth), ...]``.

    The raw frames are read from ``store`` and black-level corrected; saturation is tested on the raw
    counts. The pairs run in threads (OpenCV releases the GIL), one per CPU core. Raises ValueError
    when the rig has no stereo pair (pointing to known-geometry mode).
    """

    def one_pair(pair) -> tuple[str, StereoDepth]:
        camera_a, camera_b = pair
        images = [
            store.read_raw(frame_index, camera.id).astype(np.float32) - camera.black_level
            for camera in (camera_a, camera_b)
        ]
        depth = match_stereo_pair(
            images[0], images[1], camera_a.pinhole(), camera_b.pinhole(), config,
            saturation=camera_a.saturation_level - camera_a.black_level,
        )
        return f"{camera_a.id}+{camera_b.id}", depth

    pairs = store.rig.stereo_camera_pairs()
    workers = max(1, min(len(pairs), os.cpu_count() or 1))
    if max(_sgbm_bytes(a.pinhole(), b.pinhole(), config) for a, b in pairs) > _PARALLEL_SGBM_BYTES:
        workers = 1  # full-size images: one 8-path SGBM cost volume (GBs) at a time
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(one_pair, pairs))


#: Pairs are matched in parallel only while one pair's SGBM cost volume stays below this (bytes).
_PARALLEL_SGBM_BYTES = 2.0e9


def _sgbm_bytes(camera_a, camera_b, config: StereoConfig) -> float:
    """Size of OpenCV's 8-path SGBM cost volume of a pair, ``width x height x disparities`` int16 (bytes;
    measured on the full preset: 17.7 GB peak with two 2448 x 2048 pairs of 448 disparities at once)."""
    _, count = rectify_pair(camera_a, camera_b).disparity_range(config.depth_range_mm)
    return 2.0 * camera_a.width * camera_a.height * count


@dataclasses.dataclass(frozen=True)
class FrameGeometry:
    """One frame's stereo result, merged cloud and mesh (None when not asked for); ``error`` says why the
    frame is unusable (too few points, or meshing failed), else None."""

    pairs: list[tuple[str, StereoDepth]]
    cloud: PointCloud
    mesh: TriangleMesh | None
    error: str | None
    seconds: float


def frame_geometry(store: CaptureStore, frame: int, config: GeometryConfig, *,
                   mesh: bool = True) -> FrameGeometry:
    """Stereo, fusion and (``mesh``) meshing of one frame (nothing written)."""
    started = time.perf_counter()
    pairs = frame_stereo(store, frame, config.stereo)
    merged = PointCloud.concatenate([depth.cloud for _, depth in pairs])
    cloud = merged.voxel_downsample(config.frame_voxel_mm)
    surface, error = None, None
    try:
        if mesh:
            surface = poisson_mesh(cloud, config.frame_poisson)
        else:
            confident_points(cloud, config.frame_poisson)
    except ValueError as exc:
        error = f"no mesh: {exc}" if mesh else f"too few points: {exc}"
    return FrameGeometry(pairs, cloud, surface, error, time.perf_counter() - started)


def write_frame_geometry(result: FrameGeometry, mesh_path: Path | None,
                         cloud_path: Path | None) -> dict[str, Any]:
    """Write a frame's mesh to ``mesh_path`` (when it has one) and then its cloud to ``cloud_path``
    (None: not kept; written last, it marks the frame complete), atomically; returns the frame's summary
    entry: ``points``, ``pairs`` (points per stereo pair), ``seconds``, ``mesh_vertices`` (with a mesh)
    and ``error`` (an unusable frame)."""
    entry: dict[str, Any] = {"points": len(result.cloud), "pairs": {n: len(d.cloud) for n, d in result.pairs},
                             "seconds": result.seconds}
    if result.error is not None:
        entry["error"] = result.error
    if result.mesh is not None and mesh_path is not None:
        save_ply(mesh_path, result.mesh)
        entry["mesh_vertices"] = result.mesh.vertex_count
    if cloud_path is not None:
        save_point_cloud(cloud_path, result.cloud)
    return entry


@dataclasses.dataclass(frozen=True)
class StereoFrameUnit:
    """One frame's stereo, fusion and meshing (:func:`frame_geometry`) as an executor unit: where its
    inputs and outputs are, not the data.

    Attributes:
        capture: the capture store (absolute path).
        frame: the frame's index in the capture.
        config: the geometry configuration (its ``stereo``, ``frame_voxel_mm`` and ``frame_poisson``).
        mesh_path: where the frame's mesh goes (PLY, rig world, mm; absolute path); None: the frame is
            not meshed.
        cloud_path: where its fused cloud goes (``.npz``; None: not kept).
    """

    capture: Path
    frame: int
    config: GeometryConfig
    mesh_path: Path | None
    cloud_path: Path | None = None


def run_stereo_frame_unit(unit: StereoFrameUnit) -> dict[str, Any]:
    """Stereo, fusion and meshing of one frame (:class:`StereoFrameUnit`) from the capture, written by
    :func:`write_frame_geometry`; returns the frame's summary entry (``error`` when meshing failed).

    Raises:
        ValueError, FileNotFoundError: the frame's raw images cannot be read or matched (reported by the
            executor as the frame's failure).
    """
    store = CaptureStore.open(unit.capture, validate=False)
    result = frame_geometry(store, unit.frame, unit.config, mesh=unit.mesh_path is not None)
    return write_frame_geometry(result, unit.mesh_path, unit.cloud_path)


def run_stereo_units(executor: Executor, units: list[StereoFrameUnit], record, *, desc: str,
                     total: int, progress: bool) -> None:
    """Run ``units`` on ``executor`` with one progress bar over ``total`` frames (those done before count
    as done); ``record(frame, entry or None, outcome)`` is called in this process as each finishes
    (``entry`` None: the unit failed, ``outcome.error`` says why)."""

    def done(outcome: UnitOutcome) -> None:
        record(outcome.unit.frame, outcome.value if outcome.ok else None, outcome)

    map_units_with_progress(executor, run_stereo_frame_unit, units, done, desc=desc, total=total,
                            progress=progress)
