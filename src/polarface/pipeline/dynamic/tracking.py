"""The dynamic stage's sequence geometry in ``RESULT/tracking`` (:mod:`polarface.pipeline.dynamic.stage`):
each frame's stereo mesh, the reference mesh's rigid alignment to the first frame, and its tracking
through the sequence. ``tracking/tracking.json`` holds the capture identity, the configuration and every
step's results (written after each step, so a run resumes); a folder written for another capture or
configuration is refused. Layout: ``docs/result_folder.md``.

Each frame's stereo mesh is an executor unit (:class:`polarface.pipeline.geometry.frames.StereoFrameUnit`):
the frames' stereo runs on the stage's executor (in this process, or as Ray tasks), each unit writing
``tracking/stereo/NNNNNN.ply`` itself; ``tracking.json`` (its ``frames`` and ``executor``) is written
here as units finish. A frame whose unit fails is reported and left out (no surface to track against)
and redone by the next run. The alignment and the tracking, sequential by nature, run in this process.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from polarface.capture.store import CaptureStore
from polarface.executors import Executor, LocalExecutor, UnitOutcome
from polarface.geometry.mesh import TriangleMesh, load_mesh, sample_surface
from polarface.geometry.point_cloud import PointCloud
from polarface.geometry.registration import RegistrationConfig, register_pair_starts
from polarface.geometry.tracked_file import load_tracked, save_tracked
from polarface.geometry.tracking import (
    TrackedSequence,
    TrackingConfig,
    TrackingFrame,
    track_mesh,
)
from polarface.io import read_json_object, write_json_atomic
from polarface.io.recorded_paths import resolve_recorded_path
from polarface.pipeline.geometry import GeometryConfig, StereoFrameUnit, run_stereo_units
from polarface.results import ResultFolder, layout
from polarface.results.fingerprint import same_input

__all__ = ["TrackingFolder", "align_reference", "stereo_pass", "track_sequence"]

LOGGER = logging.getLogger(__name__)


class TrackingFolder:
    """``RESULT/tracking``: the summary (written after every step) and its files."""

    def __init__(self, root: Path, header: dict[str, Any]) -> None:
        self.root = root
        self.summary: dict[str, Any] = {**header, "frames": {}}
        path = root / layout.TRACKING_JSON
        if path.is_file():
            previous = read_json_object(path)
            for key in ("capture", "config"):
                same = same_input(previous.get(key), header[key]) if key == "capture" else \
                    previous.get(key) == header[key]
                if not same:
                    raise ValueError(
                        f"'{path}' was written for another dynamic {key} (recorded "
                        f"{_short(previous.get(key))}); rerun with the same capture and options, or into a "
                        f"new copy of the static RESULT (or delete '{root}' and '{root.parent / 'frames'}' "
                        "to start the dynamic stage again)"
                    )
            self.summary = {**previous, **header}

    def stereo_path(self, frame: int) -> Path:
        """``tracking/stereo/NNNNNN.ply``: the frame's stereo mesh."""
        return self.root / "stereo" / f"{frame:06d}.ply"

    def save(self) -> None:
        """Write ``tracking.json`` atomically."""
        write_json_atomic(self.root / layout.TRACKING_JSON, self.summary)


def _short(value: Any) -> str:
    if isinstance(value, dict) and "sha256" in value:
        return f"sha256 {str(value['sha256'])[:12]}"
    return "another configuration"


def stereo_pass(store: CaptureStore, tracking: TrackingFolder, frames: list[int], config: GeometryConfig,
                progress: bool, executor: Executor | None = None) -> float:
    """Each frame's stereo mesh into ``tracking/stereo`` (frames already done are skipped), as units of
    ``executor`` (None: in this process, in order); seconds. A frame whose unit fails is logged and left
    without an entry (the next run redoes it)."""
    started = time.perf_counter()
    executor = executor or LocalExecutor()
    entries = tracking.summary["frames"]
    placements = tracking.summary.setdefault("executor", {}).setdefault("units", {})
    tracking.summary["executor"] = {**executor.describe(), "units": placements}
    units = [StereoFrameUnit(store.root.absolute(), frame, config, tracking.stereo_path(frame).absolute())
             for frame in frames if str(frame) not in entries]

    def record(frame: int, entry: dict[str, Any] | None, outcome: UnitOutcome) -> None:
        placements[str(frame)] = outcome.placement()
        if entry is None:
            LOGGER.warning("dynamic frame %d: stereo failed: %s", frame, outcome.error)
        else:
            entries[str(frame)] = entry
        tracking.save()

    run_stereo_units(executor, units, record, desc="dynamic: stereo", total=len(frames), progress=progress)
    tracking.summary["frames"] = {str(f): entries[str(f)] for f in frames if str(f) in entries}
    tracking.save()
    return time.perf_counter() - started


def _surface_cloud(mesh: TriangleMesh, spacing_mm: float = 0.7, seed: int = 0) -> PointCloud:
    """Points sampled on ``mesh`` about ``spacing_mm`` apart (area-weighted, deterministic) with the face
    normals: a mesh's vertices can be centimetres apart (a decimated reference), too sparse for the
    correspondence distances of the alignment."""
    count = int(np.clip(mesh.face_areas().sum() / spacing_mm**2, 1000, 400_000))
    points, faces = sample_surface(mesh.vertices, mesh.faces, count, seed)
    return PointCloud.from_arrays(points, mesh.face_normals()[faces])


def _start_poses(folder: ResultFolder, count: int = 12) -> list[np.ndarray]:
    """Starts of the alignment: the identity (stereo geometry's model frame is the rig world of the static
    reference frame) and up to ``count`` of the static frames' model -> rig-world poses, evenly spread
    (a given mesh has its own model frame; the subject sits in the dynamic capture as in one of them)."""
    from polarface.geometry.poses import load_poses

    path = resolve_recorded_path(folder.root, folder.stage_record("prepare").get("poses"))
    if path is None or not path.is_file():
        return [np.eye(4)]
    poses = load_poses(path)
    rows = np.unique(np.linspace(0, len(poses) - 1, min(count, len(poses))).round().astype(int))
    return [np.eye(4), *(poses[row] for row in rows)]


def align_reference(folder: ResultFolder, reference: TriangleMesh, tracking: TrackingFolder, first: int,
                    config: RegistrationConfig, min_fitness: float) -> np.ndarray:
    """The rigid transform static model frame -> the dynamic capture's rig world (recorded once): the ICP
    explaining most of the first frame's surface among the starts of :func:`_start_poses`; ValueError when
    it explains less than ``min_fitness`` of it, or the frame has no stereo surface."""
    recorded = tracking.summary.get("alignment")
    if recorded is not None:
        return np.asarray(recorded["transform"], dtype=np.float64)
    path = tracking.stereo_path(first)
    if not path.is_file():
        reason = tracking.summary["frames"].get(str(first), {}).get("error", "no stereo mesh")
        raise ValueError(
            f"the first dynamic frame {first} has no stereo surface ({reason}): the reference mesh cannot "
            "be placed in the dynamic capture"
        )
    source, target = _surface_cloud(reference), _surface_cloud(load_mesh(path))
    trials = register_pair_starts(source, target, _start_poses(folder), config)
    aligned = max(trials, key=lambda trial: (round(trial.target_fitness, 3), -trial.rmse_mm))
    if aligned.target_fitness < min_fitness:
        raise ValueError(
            f"the reference mesh does not fit the first dynamic frame {first}'s stereo surface (ICP: "
            f"{100 * aligned.target_fitness:.0f} % of the frame's surface explained, fewer than "
            f"{100 * min_fitness:.0f} %): is it the same subject and rig?"
        )
    tracking.summary["alignment"] = {
        "frame": first, "transform": aligned.transform.tolist(), "fitness": aligned.target_fitness,
        "rmse_mm": aligned.rmse_mm,
    }
    tracking.save()
    return aligned.transform


def _tracking_images(store: CaptureStore, frame: int) -> dict[str, np.ndarray]:
    """``camera id -> (H, W)`` float32 image of a frame: the polarimetric cameras' subsurface image
    ``I_sss`` (cross-polarized: no specular highlights) and the stereo cameras' black-corrected raw,
    averaged over colour channels."""
    images = {}
    for camera in store.rig.cameras:
        if camera.role == "polarimetric":
            image = store.observation("i_sss", frame, camera.id)  # a damaged chunk: named by the store
        else:
            image = store.read_raw(frame, camera.id).astype(np.float32) - camera.black_level
        image = image.mean(axis=-1) if image.ndim == 3 else image
        images[camera.id] = np.clip(image, 0.0, None).astype(np.float32)
    return images


def track_sequence(store: CaptureStore, tracking: TrackingFolder, reference: TriangleMesh, frames: list[int],
                   config: TrackingConfig, progress: bool) -> tuple[TrackedSequence, float]:
    """The reference mesh (placed at ``frames[0]``) tracked through ``frames``
    (:func:`polarface.geometry.tracking.track_mesh`) into ``tracking/tracked.npz``, or the saved tracking
    when it covers the same frames and vertices; ``(tracking, seconds it took)``."""
    path = tracking.root / layout.TRACKED_NPZ
    if path.is_file():
        tracked = load_tracked(path)
        if list(tracked.frames) == frames and tracked.vertices.shape[1] == reference.vertex_count:
            return tracked, float(tracking.summary.get("tracking_s", 0.0))
    started = time.perf_counter()

    def load_frame(frame: int) -> TrackingFrame:
        surface_path = tracking.stereo_path(frame)
        surface = load_mesh(surface_path) if surface_path.is_file() else None
        return TrackingFrame(frame, _tracking_images(store, frame), surface)

    cameras = {camera.id: camera.pinhole() for camera in store.rig.cameras}
    tracked = track_mesh(reference, cameras, load_frame, frames, config, progress=progress)
    save_tracked(path, tracked)
    seconds = time.perf_counter() - started
    tracking.summary.update({"tracking": tracked.to_json(), "tracking_s": seconds})
    tracking.save()
    return tracked, seconds
