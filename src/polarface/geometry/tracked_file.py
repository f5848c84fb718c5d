"""The file of a tracked sequence (``RESULT/tracking/tracked.npz``, docs/result_folder.md): a
:class:`polarface.geometry.tracking.TrackedSequence` written atomically to a local path or a URL and read
back with its arrays checked against each other."""

from __future__ import annotations

import numpy as np

from polarface.geometry.tracking import TrackedSequence
from polarface.io import atomic_path
from polarface.io.storage import PathOrUrl, StoragePath, local_copy, storage_path

__all__ = ["load_tracked", "save_tracked"]


def save_tracked(path: PathOrUrl, tracked: TrackedSequence) -> StoragePath:
    """Write ``tracked`` to an ``.npz`` file (a local path or a URL) atomically; returns the path."""
    target = storage_path(path)
    if target.suffix != ".npz":
        raise ValueError(f"argument 'path' must end in .npz; got {target}")
    failed_frames = np.array(sorted(tracked.failed), np.int64)
    with atomic_path(target) as tmp, open(tmp, "wb") as handle:
        np.savez_compressed(
            handle,
            frames=np.asarray(tracked.frames, np.int64),
            vertices=np.asarray(tracked.vertices, np.float64),
            confidence=np.asarray(tracked.confidence, np.float32),
            anchors=np.asarray(tracked.anchors, np.int64),
            failed_frames=failed_frames,
            failed_reasons=np.array([tracked.failed[int(f)] for f in failed_frames], dtype=str),
        )
    return target


def load_tracked(path: PathOrUrl) -> TrackedSequence:
    """Read a :func:`save_tracked` file (a local path or a URL).

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        ValueError: naming the file when it is not a tracked sequence or its arrays disagree.
    """
    source = storage_path(path)
    if not source.is_file():
        raise FileNotFoundError(f"tracked sequence file {source} does not exist")
    names = ("frames", "vertices", "confidence", "anchors", "failed_frames", "failed_reasons")
    try:
        with local_copy(source) as local, np.load(local, allow_pickle=False) as data:
            arrays = {name: data[name] for name in names}
    except (OSError, ValueError, KeyError) as error:
        raise ValueError(f"{source}: not a tracked sequence ({error})") from error
    frames, vertices, confidence = arrays["frames"], arrays["vertices"], arrays["confidence"]
    count = len(frames)
    failed_count = len(arrays["failed_frames"])
    if (frames.ndim != 1 or vertices.ndim != 3 or vertices.shape[::2] != (count, 3)
            or confidence.shape != vertices.shape[:2] or len(arrays["failed_reasons"]) != failed_count):
        raise ValueError(f"{source}: arrays disagree: frames {frames.shape}, vertices {vertices.shape}, "
                         f"confidence {confidence.shape}")
    failed = {int(f): str(r) for f, r in zip(arrays["failed_frames"], arrays["failed_reasons"], strict=True)}
    return TrackedSequence(tuple(int(f) for f in frames), vertices.astype(np.float64),
                           confidence.astype(np.float32), tuple(int(a) for a in arrays["anchors"]), failed)
