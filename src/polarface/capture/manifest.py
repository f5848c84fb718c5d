"""The capture store's manifest and frame markers: schema, reading, writing and checks against the files.

``manifest.json`` lists the completed frames (index, timestamp, raw file per camera, derived state,
demosaicing method) and, when some camera's analyzers are not ideal, the models demosaicing applied
(``analyzers``: camera id -> ``{"extinction_ratio", "analyzer_angles_deg"}`` or one per colour;
``docs/sensors.md``) and the channel gains it divided by where they are not 1 (``channel_gains``: camera
id -> R, G, B); ``frames/<frame:06d>.json`` is the completion marker of one frame, written last.
The manifest is rebuilt from the markers after every frame. Layout: ``docs/capture_store.md``.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

import numpy as np

from polarface.capture.analyzers import applied_analyzers
from polarface.capture.demosaic import applied_gains
from polarface.capture.observations import OBSERVATION_NAMES
from polarface.capture.rig import Camera, Rig
from polarface.io.atomic import write_json_atomic
from polarface.io.images import image_header, read_png
from polarface.io.storage import PathOrUrl, StoragePath, storage_path

__all__ = [
    "DERIVED_ZARR",
    "MANIFEST_FORMAT",
    "MANIFEST_JSON",
    "MANIFEST_VERSION",
    "FrameRecord",
    "frame_marker_path",
    "manifest_problems",
    "raw_bit_depth_ok",
    "raw_digest",
    "read_frame_marker",
    "read_manifest",
    "write_manifest",
]

#: The capture store's marker: its manifest, at the store's root.
MANIFEST_JSON = "manifest.json"
#: The capture store's derived arrays (Stokes observations), beside the manifest (``capture.store``).
DERIVED_ZARR = "derived.zarr"
#: ``format`` field of ``manifest.json``.
MANIFEST_FORMAT = "polarface-capture"
#: ``version`` field of ``manifest.json``.
MANIFEST_VERSION = 1


@dataclass(frozen=True)
class FrameRecord:
    """One frame of the manifest.

    Attributes:
        index: frame index (>= 0), the slot along axis 0 of the derived arrays.
        timestamp: seconds since the start of the sequence.
        raw: camera id -> raw file path relative to the store root.
        derived: True when the derived arrays of the polarimetric cameras are complete.
    """

    index: int
    timestamp: float
    raw: dict[str, str]
    derived: bool


def raw_bit_depth_ok(raw: np.ndarray, camera: Camera) -> None:
    """Raise ``ValueError`` if ``raw`` does not fit ``camera`` (dtype, size, bit depth, range)."""
    if not np.issubdtype(raw.dtype, np.integer):
        raise ValueError(f"raw frame of camera '{camera.id}' must be integer counts; got dtype {raw.dtype}")
    expected = (camera.height, camera.width) if camera.sensor != "rgb" else None
    if expected and raw.shape != expected:
        raise ValueError(f"raw frame of camera '{camera.id}' has shape {raw.shape}; rig declares {expected}")
    if camera.sensor == "rgb" and raw.shape[:2] != (camera.height, camera.width):
        raise ValueError(
            f"image of camera '{camera.id}' has shape {raw.shape}; rig declares "
            f"{(camera.height, camera.width)}"
        )
    if camera.bit_depth > 8 and raw.dtype == np.uint8:
        raise ValueError(
            f"raw frame of camera '{camera.id}' is 8-bit but the rig declares bit_depth {camera.bit_depth}"
        )
    if raw.size and (raw.min() < 0 or raw.max() > 2**camera.bit_depth - 1):
        raise ValueError(
            f"raw frame of camera '{camera.id}' has values up to {raw.max()}, "
            f"beyond bit_depth {camera.bit_depth}"
        )


def raw_digest(raw: np.ndarray) -> str:
    """SHA-1 of a raw frame's counts and shape: what a frame marker records per camera (``digests``)."""
    return hashlib.sha1(np.ascontiguousarray(raw).tobytes() + str(raw.shape).encode()).hexdigest()


def read_frame_marker(path: PathOrUrl) -> dict:
    """A frame's completion marker ``frames/<frame:06d>.json`` (a JSON object with ``frame_index``,
    ``timestamp``, ``raw``, ``derived``).

    Raises:
        FileNotFoundError: no marker. ValueError: not such an object (truncated, damaged), naming the file.
    """
    path = storage_path(path)
    try:
        marker = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"frame marker '{path}' is not valid JSON ({exc}): the capture store is damaged; "
                         "remove the marker and rerun the ingest (or simulate) that wrote the store to "
                         "rewrite the frame") from None
    fields = ("frame_index", "timestamp", "raw", "derived")
    if not isinstance(marker, dict) or not all(key in marker for key in fields):
        raise ValueError(f"frame marker '{path}' must be an object with the fields {list(fields)}; remove it "
                         "and rerun the ingest (or simulate) that wrote the store to rewrite the frame")
    return marker


def frame_marker_path(root: PathOrUrl, frame_index: int) -> StoragePath:
    """Path of the completion marker ``frames/<frame:06d>.json`` of a frame of the store at ``root``."""
    return storage_path(root) / "frames" / f"{frame_index:06d}.json"


def write_manifest(root: PathOrUrl, rig: Rig, sequence: str, *, complete: bool) -> dict:
    """Rebuild ``manifest.json`` from the frame markers (in index order), write it atomically, return it."""
    root = storage_path(root)
    frames = []
    for path in sorted((root / "frames").glob("[0-9]*.json")):
        marker = read_frame_marker(path)
        frames.append(
            {
                "index": marker["frame_index"],
                "timestamp": marker["timestamp"],
                "raw": marker["raw"],
                "derived": marker["derived"],
                "method": marker.get("method"),
            }
        )
    frames.sort(key=lambda f: f["index"])
    manifest = {
        "format": MANIFEST_FORMAT,
        "version": MANIFEST_VERSION,
        "sequence": sequence,
        "complete": complete,
        "frame_count": len(frames),
        "cameras": [c.id for c in rig.cameras],
        "derived_store": DERIVED_ZARR,
        "observations": list(OBSERVATION_NAMES),
        "frames": frames,
    }
    analyzers = applied_analyzers(rig)
    if analyzers:  # absent: every camera ideal, nothing applied (ideal stores keep their bytes)
        manifest["analyzers"] = analyzers
    gains = applied_gains(rig)
    if gains:  # absent: unit gains (stores written before the gains existed keep their bytes)
        manifest["channel_gains"] = gains
    write_json_atomic(root / MANIFEST_JSON, manifest)
    return manifest


def read_manifest(path: PathOrUrl) -> dict:
    """The parsed ``manifest.json`` at ``path`` (a local path or a URL).

    Raises:
        ValueError: invalid JSON, wrong format or sequence, malformed or duplicated frames.
    """
    path = storage_path(path)
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"manifest '{path}' is not valid JSON: {exc}") from exc
    if manifest.get("format") != MANIFEST_FORMAT:
        raise ValueError(f"manifest '{path}': field 'format' must be {MANIFEST_FORMAT!r}")
    if manifest.get("sequence") not in ("static", "dynamic"):
        raise ValueError(f"manifest '{path}': field 'sequence' must be 'static' or 'dynamic'")
    frames = manifest.get("frames")
    if not isinstance(frames, list) or any(not {"index", "timestamp", "raw"} <= set(f) for f in frames):
        raise ValueError(f"manifest '{path}': field 'frames' must list objects with index, timestamp, raw")
    indices = [f["index"] for f in frames]
    if len(set(indices)) != len(indices):
        raise ValueError(f"manifest '{path}': duplicated frame indices")
    return manifest


def manifest_problems(
    root: PathOrUrl, rig: Rig, frames: list[FrameRecord], *, deep: bool = False
) -> list[str]:
    """Every disagreement between the manifest's ``frames`` and the files of the store at ``root``.

    Missing raw file or frame marker, camera not in the rig, wrong image size or bit depth, raw files
    not in the manifest; ``deep`` also reads every raw frame's values (:func:`raw_bit_depth_ok`).
    """
    root = storage_path(root)
    problems: list[str] = []
    listed: set[str] = set()
    camera_sets = set()
    markers = {path.name for path in (root / "frames").glob("[0-9]*.json")}  # one listing, not one per frame
    for frame in frames:
        if frame_marker_path(root, frame.index).name not in markers:
            problems.append(
                f"frame {frame.index}: completion marker frames/{frame.index:06d}.json is missing"
            )
        camera_sets.add(tuple(sorted(frame.raw)))
        for cam_id, relative in frame.raw.items():
            listed.add(relative)
            try:
                camera = rig.camera(cam_id)
            except ValueError as exc:
                problems.append(f"frame {frame.index}: {exc}")
                continue
            path = root / relative
            try:
                width, height, channels, bits = image_header(path)
            except FileNotFoundError:
                problems.append(f"frame {frame.index}: raw file '{relative}' of camera '{cam_id}' is missing")
                continue
            except ValueError as exc:
                problems.append(f"frame {frame.index}: raw file '{relative}' is not an image ({exc})")
                continue
            if (height, width) != (camera.height, camera.width):
                problems.append(
                    f"frame {frame.index}: '{relative}' is {width}x{height}, camera "
                    f"'{cam_id}' declares {camera.width}x{camera.height}"
                )
            if camera.bit_depth > 8 and bits <= 8:
                problems.append(
                    f"frame {frame.index}: '{relative}' is {bits}-bit ({channels} channel(s)), "
                    f"camera '{cam_id}' declares bit_depth {camera.bit_depth}"
                )
            if deep:
                try:
                    raw_bit_depth_ok(read_png(path), camera)
                except ValueError as exc:
                    problems.append(f"frame {frame.index}: '{relative}': {exc}")
    if len(camera_sets) > 1:
        problems.append(f"frames hold different camera sets: {sorted(camera_sets)}")
    raw_dir = root / "raw"
    if raw_dir.is_dir():
        for path in sorted(raw_dir.glob("*/*")):
            relative = path.relative_to(root).as_posix()
            if not path.name.startswith(".tmp-") and relative not in listed:
                problems.append(f"raw file '{relative}' is not in the manifest")
    return problems
