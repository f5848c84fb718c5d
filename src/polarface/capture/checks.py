"""Checks of a capture store before a stage reads it, each raising ValueError that names the store and
the file: a finished manifest, a derived store whose first chunks read, stereo pairs that rectify, raw
images that are whole. The stages (``polarface.pipeline``) run them before anything is written.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

from polarface.capture.manifest import DERIVED_ZARR, MANIFEST_JSON
from polarface.capture.store import CaptureStore
from polarface.geometry import rectify_pair
from polarface.io.storage import StoragePath, UrlPath, open_zarr_group

__all__ = [
    "check_capture_manifest",
    "check_derived_store",
    "check_raw_images_whole",
    "check_stereo_pairs",
    "raw_image_cameras",
]

#: The last 12 bytes of every PNG file: the empty ``IEND`` chunk (length 0, type, CRC).
_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"


def check_capture_manifest(store: CaptureStore) -> None:
    """The capture's ``manifest.json`` describes a finished capture whose frame count is its frame list's."""
    path = store.root / MANIFEST_JSON
    manifest = store.manifest
    if manifest.get("complete") is not True:
        raise ValueError(
            f"'{path}': 'complete' is {manifest.get('complete')!r}: the capture was not finalized "
            "(rerun the capture or ingest to completion)"
        )
    count = manifest.get("frame_count")
    listed = len(manifest.get("frames") or [])
    if count is not None and (isinstance(count, bool) or count != listed):
        raise ValueError(f"'{path}': 'frame_count' is {count!r} but the manifest lists {listed} frames")


def check_derived_store(store: CaptureStore) -> None:
    """Read ``derived.zarr``'s metadata and the first chunk of each of its arrays (corrupt metadata or
    chunks fail here, naming the store, before any output is written)."""
    path = store.root / DERIVED_ZARR
    if not path.is_dir():
        return  # CaptureStore reports a missing store where it reads it
    try:
        root = open_zarr_group(path, "r")
        groups = [root[name] for name in ("stacks", "masks") if name in root]
        for group in groups:
            for _, array in group.arrays():
                if array.shape and array.shape[0] > 0:
                    _ = array[(0, *(slice(0, 1) for _ in array.shape[1:]))]
    except Exception as exc:  # zarr/codec errors (JSON, blosc RuntimeError ...) share no base class
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise ValueError(f"capture store '{path}' cannot be read: {reason}") from exc


def check_stereo_pairs(store: CaptureStore) -> None:
    """ValueError unless the capture's rig has stereo pairs (else the message points to ``--mesh`` /
    ``--poses``) whose calibrations rectify (naming the pair)."""
    for camera_a, camera_b in store.rig.stereo_camera_pairs():
        try:
            rectify_pair(camera_a.pinhole(), camera_b.pinhole())
        except ValueError as exc:
            raise ValueError(
                f"rig of '{store.root}': stereo pair {camera_a.id} + {camera_b.id}: {exc}"
            ) from exc


def raw_image_cameras(store: CaptureStore) -> list[str]:
    """Ids of the cameras whose raw images the stages read: the stereo pairs' (stereo) and every camera
    that is not polarimetric (tracking); the polarimetric cameras are read from ``derived.zarr``."""
    ids = {camera.id for pair in store.rig.stereo_camera_pairs() for camera in pair}
    ids.update(camera.id for camera in store.rig.cameras if camera.role != "polarimetric")
    return sorted(ids)


def _tail(path: StoragePath, size: int) -> bytes:
    """The last ``size`` bytes of a file (fewer when it is shorter)."""
    if isinstance(path, UrlPath):
        return bytes(path.fs.cat_file(path.path, start=-size))
    with open(path, "rb") as handle:
        handle.seek(0, os.SEEK_END)
        handle.seek(max(handle.tell() - size, 0))
        return handle.read(size)


def check_raw_images_whole(store: CaptureStore, cameras: Sequence[str] | None = None) -> None:
    """Every raw PNG image of ``cameras`` (None: :func:`raw_image_cameras`) in every frame of ``store`` ends
    with PNG's end chunk: a truncated file (an interrupted copy or download) is found by one small
    read per file, before any work, rather than by the stereo or the tracking minutes later. Corruption
    that keeps a file's length is found where the file is decoded (an error naming it).

    Raises:
        ValueError: naming the store, the file, its frame and camera.
    """
    wanted = set(raw_image_cameras(store) if cameras is None else cameras)
    for record in store.frames:
        for camera_id, relative in sorted(record.raw.items()):
            if camera_id not in wanted or not relative.lower().endswith(".png"):
                continue
            path = store.root / relative
            try:
                whole = _tail(path, len(_PNG_END)) == _PNG_END
            except FileNotFoundError:
                raise ValueError(f"capture store '{store.root}': raw image '{relative}' (frame "
                                 f"{record.index}, camera {camera_id}) is missing") from None
            if not whole:
                raise ValueError(
                    f"capture store '{store.root}': raw image '{relative}' (frame {record.index}, camera "
                    f"{camera_id}) is truncated (it does not end with PNG's IEND chunk); copy or ingest that "
                    "frame again"
                )
