"""The geometry stage: a capture's stereo pairs -> per-frame depth and clouds, registration of the
sequence, the reference mesh fused from all frames with a cylindrical texture atlas (paper Sec.
"Geometry Reconstruction and Tracking"; supplement: all frames merged into the reference frame).

``reconstruct_geometry(CAPTURE, GEOM)`` writes (``docs/geometry.md``, "Geometry from stereo")::

    GEOM/
      geometry.json          configuration, capture identity, reference frame, rejected frames (with
                             reasons), registration residuals, atlas, timings, peak memory
      mesh.obj               reference mesh with its cylindrical UVs, refined photometrically
                             (GeometryConfig.surface_refinement); model frame = the rig world at the
                             reference frame, mm
      poses.json             model -> rig world 4x4 per capture frame (polarface.geometry.poses format)
      frames/NNNNNN.ply      each frame's fused stereo mesh, rig world, mm (only with
                             GeometryConfig.frame_meshes / ``polarface geometry --frame-meshes``)
      clouds/NNNNNN.npz      each frame's fused stereo point cloud (polarface.geometry.point_cloud)
      previews/*.png         depth and confidence of the reference frame's pairs, mesh renders, residuals
      report.html            the stage's report page

Frames are processed one at a time (memory bounded per frame) and skipped when their cloud exists, so
an interrupted run resumes; ``geometry.json`` records the capture and configuration, and a
folder written with others is refused.

Each frame but the reference frame is an executor unit
(:class:`polarface.pipeline.geometry.frames.StereoFrameUnit`, shared with the dynamic stage's stereo
pass; :mod:`polarface.executors`): it reads the frame's raw stereo images from
the capture and writes ``clouds/NNNNNN.npz`` (and ``frames/NNNNNN.ply`` before it) itself, atomically;
this process computes the reference frame first (a capture whose reference frame gives no geometry
writes nothing), writes ``geometry.json`` as frames finish, and registers and fuses the
sequence after them. A frame whose unit fails is rejected with its reason, like a frame with fewer
than 16 confident points (or, meshed, without a surface), and retried by the next run.
``geometry.json``'s ``executor`` records where each frame ran.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import resource
import socket
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from polarface.capture import CaptureStore, check_stereo_pairs
from polarface.executors import Executor, LocalExecutor, UnitOutcome
from polarface.executors.timing import StageClock
from polarface.geometry.atlas import (
    CylindricalAtlasConfig,
    cylindrical_atlas,
    default_axis_point,
    head_axis_from_poses,
    head_axis_point_from_poses,
)
from polarface.geometry.fusion import fuse_registered, poisson_mesh
from polarface.geometry.mesh import save_obj
from polarface.geometry.point_cloud import PointCloud, load_point_cloud
from polarface.geometry.poses import save_poses
from polarface.geometry.registration import register_sequence
from polarface.io import read_json_object, write_json_atomic
from polarface.pipeline.geometry.config import GeometryConfig
from polarface.pipeline.geometry.frames import (
    StereoFrameUnit,
    frame_geometry,
    run_stereo_units,
    write_frame_geometry,
)
from polarface.results.fingerprint import RecordMismatchError, fingerprint_differences, same_input
from polarface.results.layout import GEOMETRY_JSON
from polarface.texture.photometric import refine_surface

__all__ = ["reconstruct_geometry"]

LOGGER = logging.getLogger(__name__)


def _paths(out: Path, frame: int, meshes: bool = False) -> tuple[Path, Path | None]:
    """A frame's cloud and (``meshes``, else None) mesh files in ``out``."""
    return out / "clouds" / f"{frame:06d}.npz", out / "frames" / f"{frame:06d}.ply" if meshes else None


#: The configuration that makes the per-frame files; the rest (registration, reference mesh, atlas) is
#: recomputed by every run, so a resumed run may change it.
_FRAME_KEYS = ("stereo", "frame_voxel_mm", "frame_poisson", "frame_meshes")


def _check_resume(out: Path, header: dict[str, Any]) -> dict[str, Any]:
    """The previous summary when ``out`` holds a run of this capture whose frames were made with this
    configuration (:data:`_FRAME_KEYS`); ValueError otherwise."""
    path = out / GEOMETRY_JSON
    if not path.exists():
        return {}
    previous = read_json_object(path)
    if not same_input(previous.get("capture"), header["capture"]):
        raise ValueError(
            f"'{out}' holds a geometry stage run of another capture; choose another output folder"
        )
    old, new = previous.get("config") or {}, header["config"]
    changed = fingerprint_differences({key: old.get(key) for key in _FRAME_KEYS},
                                      {key: new.get(key) for key in _FRAME_KEYS}, "config.")
    if changed:
        raise RecordMismatchError(
            f"'{out}' holds a geometry stage run whose frames were made with another configuration; "
            "choose another output folder",
            changed,
        )
    return previous


def _front_direction(store: CaptureStore, centre: np.ndarray) -> np.ndarray:
    """Unit direction from ``centre`` towards the polarimetric cameras (the face's side)."""
    cameras = store.rig.polarimetric_cameras() or store.rig.cameras
    towards = np.mean([camera.centre_mm for camera in cameras], axis=0) - centre
    return towards / max(float(np.linalg.norm(towards)), 1e-9)


def reconstruct_geometry(
    capture: str | Path,
    out: str | Path,
    config: GeometryConfig | None = None,
    *,
    progress: bool = True,
    executor: Executor | None = None,
) -> dict[str, Any]:
    """Run the geometry stage of ``capture`` into ``out`` (module docstring); returns the summary.

    Args:
        config: the stage's options (None: :class:`GeometryConfig`'s defaults, the paper rig).
        executor: runs the frames but the reference frame (:class:`StereoFrameUnit`); None: in this
            process, in order. It is started before anything is written and left open.

    Raises:
        ValueError: the rig has no stereo pair or a pair's calibration is broken (nothing written), no
            frame gives a usable cloud, or ``out`` holds a run with another capture or configuration.
    """
    from polarface.results.fingerprint import capture_identity

    started = time.perf_counter()
    config = config if config is not None else GeometryConfig()
    executor = executor or LocalExecutor()
    store = CaptureStore.open(capture)
    check_stereo_pairs(store)  # fails before anything is written
    frames = [record.index for record in store.frames]
    if not frames:
        raise ValueError(f"capture '{capture}' has no complete frame")
    reference = frames[len(frames) // 2] if config.reference_frame is None else int(config.reference_frame)
    if reference not in frames:
        raise ValueError(f"argument 'reference_frame': frame {reference} is not in the capture {frames}")
    out = Path(out)
    header = {
        "format": "polarface-geometry", "version": 1, "capture": capture_identity(store.root),
        "config": config.to_json(), "reference_frame": reference, "complete": False,
    }
    previous = _check_resume(out, header)
    executor.start()
    placements = dict(previous.get("executor", {}).get("units", {}))
    entries = _frame_pass(store, out, frames, reference, config, header, dict(previous.get("frames", {})),
                          (executor, placements), progress)
    stereo_s = time.perf_counter() - started
    failed = {f: entries[str(f)]["error"] for f in frames if "error" in entries[str(f)]}
    usable = [f for f in frames if f not in failed]

    def load(frame: int) -> PointCloud:
        return load_point_cloud(_paths(out, frame)[0])

    timings = {"stereo_and_frame_meshes_s": stereo_s}
    clock = StageClock(timings)
    registration = register_sequence(usable, load, reference, config.registration, progress=progress)
    poses = _all_poses(frames, usable, registration.poses)
    clock.lap("registration_s")
    fused = fuse_registered(usable, load, registration, config.reference_voxel_mm)
    clock.lap("fusion_s")
    atlas = _reference_atlas(store, poses, frames.index(reference), fused, config)
    clock.lap("reference_mesh_and_atlas_s")
    refinement = None
    if config.surface_refinement is not None:
        accepted = {f: poses[row] for row, f in enumerate(frames)
                    if f in usable and f not in registration.rejected}
        refinement = refine_surface(store, atlas.mesh, accepted, config.surface_refinement,
                                    resolution=config.texture_resolution, progress=progress)
        atlas = dataclasses.replace(atlas, mesh=refinement.mesh)
        clock.lap("surface_refinement_s")
    save_obj(out / "mesh.obj", atlas.mesh)
    save_poses(out / "poses.json", poses)
    timings["total_s"] = time.perf_counter() - started  # the report page shows this one
    flagged = {} if refinement is None else {
        f: f"surface refinement: its views agree on no surface (score {refinement.frame_scores[f]:.3f}, "
           f"below min_frame_score x the median frame's): a wrong pose" for f in refinement.flagged_frames
    }
    rejected = {str(f): reason for f, reason in {**failed, **registration.rejected, **flagged}.items()}
    summary = {
        **header,
        "complete": True,
        "frames": entries,
        "rejected_frames": rejected,
        "registration": registration.to_json(),
        "atlas": atlas.to_json(),
        "surface_refinement": refinement.to_json() if refinement is not None else None,
        "mesh": {"vertices": atlas.mesh.vertex_count, "faces": atlas.mesh.face_count},
        "timings": timings,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "executor": {**executor.describe(), "units": {k: placements[k] for k in sorted(placements, key=int)}},
    }
    from polarface.report.geometry import write_geometry_report

    write_geometry_report(out, summary, atlas.mesh, poses, store.rig, frames,
                          surface_offset_mm=None if refinement is None else refinement.offset_mm,
                          surface_seen=None if refinement is None else
                          refinement.views >= config.surface_refinement.min_views)
    clock.lap("report_s")
    timings["total_s"] = time.perf_counter() - started  # with the report
    write_json_atomic(out / GEOMETRY_JSON, summary)
    return summary


def _frame_pass(store: CaptureStore, out: Path, frames: list[int], reference: int, config: GeometryConfig,
                header: dict[str, Any], entries: dict[str, Any], run: tuple[Executor, dict[str, Any]],
                progress: bool) -> dict[str, Any]:
    """Stereo (and meshes, with ``config.frame_meshes``) of every frame not done yet: the reference frame
    first, in this process (a capture whose reference frame gives no geometry writes nothing), then the
    others as units of ``run = (executor, placements)`` (each frame's placement recorded in
    ``placements``; a failed unit becomes an entry with its ``error``, redone by the next run: it wrote no
    cloud); returns the per-frame summary entries in frame order."""
    executor, placements = run

    def save() -> None:  # geometry.json after every frame: a stopped run resumes with its entries
        write_json_atomic(out / GEOMETRY_JSON, {**header, "frames": entries,
                                                "executor": {**executor.describe(), "units": placements}})

    done = {f for f in frames if _paths(out, f)[0].exists() and str(f) in entries}
    first = None
    if reference not in done:
        started = time.perf_counter()
        first = frame_geometry(store, reference, config, mesh=config.frame_meshes)
        if first.error is not None:
            raise ValueError(
                f"the reference frame {reference} has no usable stereo geometry ({first.error}); check "
                "the stereo images, choose another reference frame, or give the geometry ('--mesh MESH "
                "--poses POSES')"
            )
        out.mkdir(parents=True, exist_ok=True)
        cloud_path, mesh_path = _paths(out, reference, config.frame_meshes)
        entries[str(reference)] = write_frame_geometry(first, mesh_path, cloud_path)
        placements[str(reference)] = UnitOutcome(
            reference, seconds=time.perf_counter() - started, host=socket.gethostname(), pid=os.getpid()
        ).placement()
    save()
    root = out.absolute()
    units = [StereoFrameUnit(store.root.absolute(), frame, config,
                             *reversed(_paths(root, frame, config.frame_meshes)))
             for frame in frames if frame != reference and frame not in done]

    def record(frame: int, entry: dict[str, Any] | None, outcome: UnitOutcome) -> None:
        entries[str(frame)] = entry if entry is not None else {"error": f"unit failed: {outcome.error}"}
        placements[str(frame)] = outcome.placement()
        save()

    previews = None  # the reference frame's depth previews, unless it was done before
    with ThreadPoolExecutor(max_workers=1) as thread:  # previews overlap the units, not delay them
        if first is not None:
            from polarface.report.geometry import write_depth_previews

            previews = thread.submit(write_depth_previews, out / "previews", first.pairs)
        run_stereo_units(executor, units, record, desc="geometry: stereo", total=len(frames),
                         progress=progress)
    if previews is not None:
        previews.result()
    return {str(frame): entries[str(frame)] for frame in frames}


def _reference_atlas(store: CaptureStore, poses: np.ndarray, reference_row: int, fused: PointCloud,
                     config: GeometryConfig):
    """The reference mesh of the fused cloud with its cylindrical atlas (``CylindricalAtlas``): the axis is
    the chair's rotation axis from the poses (a sequence that hardly turns falls back to a circle fit)."""
    mesh = poisson_mesh(fused, config.reference_poisson)
    axis = head_axis_from_poses(poses, reference=reference_row)
    try:
        centre = head_axis_point_from_poses(poses, axis, reference=reference_row)
    except ValueError:
        centre = default_axis_point(mesh.vertices, axis)
    return cylindrical_atlas(
        mesh, axis, centre, _front_direction(store, centre),
        CylindricalAtlasConfig(resolution=int(config.texture_resolution)),
    )


def _all_poses(frames: list[int], usable: list[int], poses: np.ndarray) -> np.ndarray:
    """One pose per capture frame: a frame without a cloud takes its nearest usable neighbour's pose."""
    by_frame = dict(zip(usable, np.asarray(poses), strict=True))
    result = []
    for frame in frames:
        nearest = min(usable, key=lambda f: (abs(f - frame), f))
        result.append(by_frame[nearest])
    return np.stack(result)
