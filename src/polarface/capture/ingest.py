"""Build a capture store from a directory of raw frames (the ``polarface ingest`` command).

RAW_DIR layout (documented in ``docs/capture_store.md``)::

    RAW_DIR/
      <camera_id>/<frame>.png     one raw frame per camera and frame; <frame> is an integer
                                  (``12.png`` or ``000012.png``); .tif/.tiff also accepted
      timestamps.csv              optional: header ``frame,timestamp_s``; default frame / fps

Every sub-folder must be a camera of the rig; every polarimetric camera needs a folder; every
camera must hold the same frame numbers (a frame missing for one camera is an error naming it).

Nothing half-written: every raw file is decoded and checked against its camera (readable, size, bit
depth, range) before anything is written, and an error names the file; a run that fails removes the
store it created (or, resuming, leaves the frames that were complete before; a frame without its
marker is redone by the next run, and stale ``.tmp-*`` files are removed by it).

Each frame is one executor unit (:class:`IngestUnit`, :func:`run_ingest_unit`;
:mod:`polarface.executors`): it reads its raw files and writes its raw PNGs, its derived chunks and its
marker into the store itself; the submitting process sizes the derived arrays first, rebuilds
``manifest.json`` as frames finish and finalizes the store after them
(:mod:`polarface.capture.store_writer`, "Frames written in parallel"). ``CAPTURE/ingest.json`` records the
executor, the seconds and the host of every frame, the timings and the non-ideal analyzer models
demosaicing applied (``analyzers``, None when every camera is ideal; ``docs/sensors.md``).
"""

from __future__ import annotations

import csv
import dataclasses
import itertools
import math
import os
import time
from pathlib import Path
from typing import Any, Literal

from tqdm import tqdm

from polarface.capture.analyzers import applied_analyzers
from polarface.capture.demosaic import DemosaicMethod
from polarface.capture.manifest import (
    MANIFEST_JSON,
    raw_bit_depth_ok,
    raw_digest,
    read_frame_marker,
    read_manifest,
)
from polarface.capture.rig import Rig
from polarface.capture.store import CaptureStore
from polarface.executors import Executor, LocalExecutor, UnitOutcome, map_units_with_progress
from polarface.io.atomic import write_json_atomic
from polarface.io.images import read_png
from polarface.io.storage import PathOrUrl, StoragePath, remove_tree, storage_path

__all__ = [
    "INGEST_JSON", "RAW_SUFFIXES", "IngestUnit", "check_raw_files", "check_store_inputs", "ingest_directory",
    "run_ingest_unit", "scan_raw_directory",
]

#: File suffixes recognised as raw frames.
RAW_SUFFIXES = (".png", ".tif", ".tiff")
#: The ingest record in the capture store (executor, per-frame placement, timings).
INGEST_JSON = "ingest.json"


def scan_raw_directory(raw_dir: str | os.PathLike[str], rig: Rig) -> dict[int, dict[str, Path]]:
    """Map frame number -> camera id -> raw file of a RAW_DIR, checked against the rig.

    Raises:
        FileNotFoundError: if ``raw_dir`` does not exist.
        ValueError: unknown camera folder, missing polarimetric camera, a file name that is not a
            frame number, or a frame missing for some camera.
    """
    root = Path(raw_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"raw directory '{root}' does not exist")
    frames: dict[int, dict[str, Path]] = {}
    cameras = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    for folder in cameras:
        rig.camera(folder.name)  # raises naming the camera
        for path in sorted(folder.iterdir()):
            if path.name.startswith(".") or path.suffix.lower() not in RAW_SUFFIXES:
                continue
            try:
                number = int(path.stem)
            except ValueError as exc:
                raise ValueError(f"raw file '{path}' is not named by a frame number") from exc
            camera_files = frames.setdefault(number, {})
            if folder.name in camera_files:
                raise ValueError(f"frame {number} appears twice for camera '{folder.name}': "
                                 f"'{camera_files[folder.name]}' and '{path}'")
            camera_files[folder.name] = path
    present = {p.name for p in cameras}
    missing = [c.id for c in rig.polarimetric_cameras() if c.id not in present]
    if missing:
        raise ValueError(f"raw directory '{root}' has no folder for polarimetric camera(s) {missing}")
    if not frames:
        raise ValueError(f"raw directory '{root}' holds no raw frames ({', '.join(RAW_SUFFIXES)})")
    for number, files in sorted(frames.items()):
        lacking = sorted(present - set(files))
        if lacking:
            raise ValueError(f"frame {number} is missing for camera(s) {lacking} in '{root}'")
    return frames


def check_raw_files(
    frames: dict[int, dict[str, Path]], rig: Rig, *, progress: bool = False
) -> dict[int, dict[str, str]]:
    """Decode every raw file of :func:`scan_raw_directory` and check it against its camera.

    One file is in memory at a time.

    Returns:
        frame number -> camera id -> digest of the raw counts (what a frame marker records:
        :func:`polarface.capture.manifest.raw_digest`).

    Raises:
        ValueError: naming the first file that is unreadable (truncated, not an image) or does not fit
            its camera (not integer, wrong size, 8-bit for a deeper camera, values beyond the bit depth).
    """
    files = [(number, cam_id, path) for number in sorted(frames)
             for cam_id, path in sorted(frames[number].items())]
    digests: dict[int, dict[str, str]] = {}
    for number, cam_id, path in tqdm(files, desc="check raw", unit="file", disable=not progress):
        try:
            raw = read_png(path)
            raw_bit_depth_ok(raw, rig.camera(cam_id))
        except (ValueError, FileNotFoundError) as exc:
            reason = str(exc)
            raise ValueError(reason if str(path) in reason else f"raw file '{path}': {reason}") from exc
        digests.setdefault(number, {})[cam_id] = raw_digest(raw)
    return digests


def _timestamps(root: Path, numbers: list[int], fps: float) -> dict[int, float]:
    """Frame number -> timestamp (s): ``timestamps.csv`` (one row per frame, strictly increasing with the
    frame number) or ``frame / fps``.

    Raises:
        ValueError: naming the file and the line: a bad header or value, a frame listed twice, a frame
            without a row, two frames with one timestamp or timestamps that decrease.
    """
    path = root / "timestamps.csv"
    if not path.is_file():
        return {n: n / fps for n in numbers}
    out: dict[int, float] = {}
    lines: dict[int, int] = {}
    with path.open(newline="", encoding="utf-8") as handle:
        reader = csv.DictReader(handle)
        if reader.fieldnames is None or not {"frame", "timestamp_s"} <= set(reader.fieldnames):
            raise ValueError(f"'{path}' must have the header 'frame,timestamp_s'")
        for line, row in enumerate(reader, start=2):
            try:
                frame, seconds = int(row["frame"]), float(row["timestamp_s"])
            except (TypeError, ValueError) as exc:
                raise ValueError(f"'{path}' line {line}: bad frame or timestamp_s") from exc
            if not math.isfinite(seconds):
                raise ValueError(f"'{path}' line {line}: timestamp_s must be finite; got {seconds}")
            if frame in out:
                raise ValueError(f"'{path}' line {line}: frame {frame} is listed again (line {lines[frame]})")
            out[frame], lines[frame] = seconds, line
    missing = [n for n in numbers if n not in out]
    if missing:
        raise ValueError(f"'{path}' has no timestamp for frame(s) {missing[:10]}")
    for before, after in itertools.pairwise(numbers):
        if out[after] == out[before]:
            raise ValueError(
                f"'{path}' line {lines[after]}: frame {after} has the timestamp of frame {before} (line "
                f"{lines[before]}, {out[after]} s); every frame needs its own time"
            )
        if out[after] < out[before]:
            raise ValueError(
                f"'{path}': timestamps must not decrease with the frame number; frame {after} "
                f"({out[after]} s) comes before frame {before} ({out[before]} s)"
            )
    return out


def check_store_inputs(
    out: PathOrUrl,
    rig: Rig,
    frames: dict[int, dict[str, Path]],
    digests: dict[int, dict[str, str]],
    times: dict[int, float],
    *,
    sequence: str,
    method: DemosaicMethod,
) -> None:
    """Refuse to continue a capture store that holds frames of other inputs (nothing is written).

    A rerun of ``ingest`` into its own store resumes: the frames whose markers record the same raw
    content, timestamp and demosaicing method are skipped. Anything else would overwrite (or, for frames
    RAW_DIR lacks, keep beside the new ones) what an earlier run stored from other inputs.

    Raises:
        ValueError: naming what differs (the rig, the sequence kind; per frame the raw file, timestamp or
            method; the frames RAW_DIR lacks) and the way out (``--force`` or another ``--out``).
    """
    root = storage_path(out)
    if not (root / "rig.json").exists():
        return
    problems = []
    if Rig.load(root / "rig.json").model_dump(mode="json") != rig.model_dump(mode="json"):
        problems.append("its rig.json differs from --rig")
    manifest = root / MANIFEST_JSON
    if manifest.exists():
        recorded = read_manifest(manifest)["sequence"]
        if recorded != sequence:
            problems.append(f"it holds a {recorded} sequence, not a {sequence} one")
    lacking = []
    for path in sorted((root / "frames").glob("[0-9]*.json")):
        marker = read_frame_marker(path)
        number = int(marker["frame_index"])
        if number not in frames:
            lacking.append(number)
            continue
        recorded = marker.get("digests", {})
        for camera in sorted(set(recorded) | set(digests[number])):
            if camera not in frames[number]:
                problems.append(f"frame {number} has camera '{camera}', which RAW_DIR lacks")
            elif recorded.get(camera) != digests[number][camera]:
                problems.append(f"frame {number} of camera '{camera}' holds other raw data than "
                                f"'{frames[number][camera]}'")
        if float(marker["timestamp"]) != times[number]:
            problems.append(f"frame {number} has timestamp {marker['timestamp']} s, not {times[number]} s")
        if marker.get("derived") and marker.get("method") != method:
            problems.append(f"frame {number} was demosaiced with '{marker.get('method')}', not '{method}'")
    if lacking:
        listed = f"{lacking[:10]}{' ...' if len(lacking) > 10 else ''}"
        problems.append(f"it holds frame(s) {listed}, which RAW_DIR lacks")
    if problems:
        more = f" (and {len(problems) - 3} more)" if len(problems) > 3 else ""
        raise ValueError(
            f"capture store '{root}' was ingested from other inputs: {'; '.join(problems[:3])}{more}; pass "
            "--force to replace it or choose another --out"
        )


@dataclasses.dataclass(frozen=True)
class IngestUnit:
    """One frame of :func:`ingest_directory` as an executor unit: where its inputs are, not the inputs.

    Attributes:
        store: the capture store being written (made by :meth:`CaptureStore.create`; absolute path or URL).
        frame: the frame number (the slot on the derived arrays' axis 0).
        timestamp: its timestamp (s).
        raw_files: ``(camera id, raw file)`` pairs of the frame (absolute paths).
        method: demosaicing method.
    """

    store: StoragePath
    frame: int
    timestamp: float
    raw_files: tuple[tuple[str, Path], ...]
    method: DemosaicMethod = "residual"


def run_ingest_unit(unit: IngestUnit) -> dict[str, Any]:
    """Store one frame (:class:`IngestUnit`): its raw PNGs, derived chunks and marker, not the manifest
    (:meth:`CaptureStore.add_frame` with ``update_manifest=False``); a frame already stored with the same
    raw content is skipped. Returns ``{"written": bool}``.

    Raises:
        ValueError, FileNotFoundError: a raw file cannot be read or does not fit its camera (reported by
            the executor as the frame's failure).
    """
    store = CaptureStore.open_writer(unit.store)
    raws = {camera_id: read_png(path) for camera_id, path in unit.raw_files}
    written = store.add_frame(unit.frame, unit.timestamp, raws, method=unit.method, update_manifest=False)
    return {"written": bool(written)}


def ingest_directory(
    raw_dir: str | os.PathLike[str],
    rig: Rig,
    out: PathOrUrl,
    *,
    sequence: Literal["static", "dynamic"] = "static",
    method: DemosaicMethod = "residual",
    fps: float = 20.0,
    progress: bool = True,
    executor: Executor | None = None,
) -> CaptureStore:
    """Validate a RAW_DIR against the rig, then store every frame with derived arrays (resumable).

    Args:
        raw_dir: the RAW_DIR (see the module docstring).
        rig: the rig.
        out: capture store directory (created, or resumed when it was ingested from the same inputs:
            :func:`check_store_inputs`): a local path or a URL (:func:`polarface.io.storage.storage_path`).
        sequence: ``static`` (revolving chair) or ``dynamic`` (expressions).
        method: demosaicing method.
        fps: frame rate used for timestamps when there is no ``timestamps.csv`` (paper: 20 fps).
        progress: show a tqdm progress bar.
        executor: runs the frames (:class:`IngestUnit`); None: in this process, in order. It is started
            after the raw files are checked and before anything is written, and left open.

    Returns:
        The finalised, validated :class:`CaptureStore`.

    Raises:
        ValueError: a bad RAW_DIR, raw file, timestamp or ``fps``, or a store ``out`` that holds frames of
            other inputs (nothing written), or frames that failed
            in their units (named with their reasons, once the other units are done; as for any failure,
            a store this run created is removed, a resumed one keeps its complete frames).
    """
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"argument 'fps' must be finite and > 0; got {fps}")
    started = time.perf_counter()
    root = Path(raw_dir)
    frames = scan_raw_directory(root, rig)
    times = _timestamps(root, sorted(frames), fps)
    digests = check_raw_files(frames, rig, progress=progress)
    out = storage_path(out)
    check_store_inputs(out, rig, frames, digests, times, sequence=sequence, method=method)
    executor = executor or LocalExecutor()
    executor.start()
    check_s = time.perf_counter() - started
    created = not out.exists()
    fresh = created or not (out / "rig.json").exists()
    try:
        store = CaptureStore.create(out, rig, sequence=sequence)
        store.reserve_frames(max(frames) + 1)
        units = [IngestUnit(out.absolute() if isinstance(out, Path) else out, number, times[number],
                            tuple((cam, path.absolute()) for cam, path in sorted(frames[number].items())),
                            method) for number in sorted(frames)]
        placements = _ingest_units(store, units, executor, progress)
        store.finalize()
    except BaseException:
        if created or (fresh and (out / "rig.json").exists()):  # this run created the store
            _remove_created(out, created)
        raise
    write_json_atomic(out / INGEST_JSON, {
        "format": "polarface-ingest", "version": 1, "raw_dir": str(root.absolute()), "method": method,
        "analyzers": applied_analyzers(rig), "frames": sorted(frames),
        "executor": {**executor.describe(), "units": placements},
        "timings": {"check_s": check_s, "total_s": time.perf_counter() - started},
    })
    return store


def _ingest_units(store: CaptureStore, units: list[IngestUnit], executor: Executor,
                  progress: bool) -> dict[str, dict[str, Any]]:
    """Run the frames' units, rebuilding the manifest as each finishes; their placements by frame.

    Raises:
        ValueError: naming the frames that failed and why (the others are stored).
    """
    placements: dict[str, dict[str, Any]] = {}
    failed: dict[int, str] = {}

    def done(outcome: UnitOutcome) -> None:
        placements[str(outcome.unit.frame)] = {**outcome.placement(), **(outcome.value or {})}
        if outcome.ok:
            store.write_manifest()
        else:
            failed[outcome.unit.frame] = outcome.error

    map_units_with_progress(executor, run_ingest_unit, units, done, desc="ingest", progress=progress)
    if failed:
        reasons = "; ".join(f"frame {frame}: {reason}" for frame, reason in sorted(failed.items()))
        raise ValueError(f"ingest into '{store.root}': {len(failed)} frame(s) failed: {reasons}")
    return {frame: placements[frame] for frame in sorted(placements, key=int)}


def _remove_created(out: StoragePath, created: bool) -> None:
    """Remove a store this run created: the folder, or its content when the folder was there (empty)."""
    if created:
        remove_tree(out)
        return
    for child in out.iterdir():
        if isinstance(child, Path) and child.is_symlink():
            child.unlink(missing_ok=True)
        else:
            remove_tree(child)
