"""The capture store: raw frames, manifest and chunked derived arrays of one capture session.

Layout (documented in ``docs/capture_store.md``)::

    CAPTURE/
      rig.json                    the rig (polarface.capture.rig.Rig)
      manifest.json               frames, timestamps, sequence kind, raw file names (rewritten after
                                  every frame; ``complete`` becomes true in finalize); ``analyzers``:
                                  the non-ideal analyzer models demosaicing applied (docs/sensors.md)
      raw/<camera_id>/<frame:06d>.png   raw counts, 16-bit PNG (8-bit for <= 8-bit cameras)
      frames/<frame:06d>.json     completion marker of one frame (written last, atomically)
      derived.zarr/               zarr v3 group (Blosc-LZ4 + shuffle), one slot per frame index on axis 0:
        stacks/<camera_id>        float32 (F, 4, H, W[, 3])  I0, I45, I90, I135
        masks/<camera_id>         uint8   (F, H, W)  bit 0 saturated, bit 1 repaired defect
        spectral/stacks           float32 (F, 4, H, W, 6)  the two Dolby cameras merged on the
                                  reference camera's grid (plane fallback of
                                  polarface.capture.observations.merge_six_channels)
        spectral/valid            uint8   (F, H, W)  1 where both cameras see the pixel unsaturated

Observations (i_sss, i_zeta, i_s, dop, aolp) are derived on read from the stored stacks, for the
requested region only (:meth:`CaptureStore.observation`, :meth:`CaptureStore.spectral_observation`):
they cost no disk and cannot disagree with the stacks.

Writing (atomicity, frames written in parallel by executor units): :mod:`polarface.capture.store_writer`.

Where: ``CAPTURE`` is a local path or an fsspec URL (``file://``, ``memory://``, ``s3://bucket/key``;
:func:`polarface.io.storage.storage_path`). On a URL every file is put whole (temporary key, then moved)
and ``derived.zarr`` goes through zarr's fsspec store, whose chunks are single object puts.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from polarface.capture.demosaic import PolarizationStack
from polarface.capture.derived_chunks import damaged_chunk_message, missing_chunk_message
from polarface.capture.manifest import (
    DERIVED_ZARR,
    MANIFEST_JSON,
    FrameRecord,
    frame_marker_path,
    manifest_problems,
    read_manifest,
)
from polarface.capture.observations import OBSERVATION_NAMES, observations_from_stack
from polarface.capture.rig import Rig
from polarface.capture.store_writer import CaptureStoreWriter
from polarface.io.images import read_png
from polarface.io.storage import PathOrUrl, StoragePath, open_zarr_group, storage_path

__all__ = ["CaptureStore"]


def _observation(intensities: np.ndarray, name: str) -> np.ndarray:
    flags = np.zeros(intensities.shape[1:3], dtype=bool)
    return getattr(observations_from_stack(PolarizationStack(intensities, flags, flags)), name)


class CaptureStore(CaptureStoreWriter):
    """A capture store directory (see the module docstring). Use :meth:`create` or :meth:`open`."""

    def __init__(self, root: PathOrUrl, rig: Rig, sequence: str, chunk: int = 512) -> None:
        self.root = storage_path(root)
        self.rig = rig
        self.sequence = sequence
        self.chunk = chunk
        self.plane_distance_mm: float | None = None  # None: the rig's convergence distance
        self._group = None
        self._manifest: dict | None = None

    # ----------------------------------------------------------------------------------- reader
    @classmethod
    def open(cls, path: PathOrUrl, *, validate: bool = True) -> CaptureStore:
        """Open an existing store, at a local path or a URL (reads ``rig.json`` and ``manifest.json``;
        validates by default).

        Raises:
            FileNotFoundError: if the store, its rig or its manifest is missing.
            ValueError: on an invalid rig/manifest, files that disagree with the manifest, or a URL of an
                unknown protocol or missing package.
        """
        root = storage_path(path)
        manifest_path = root / MANIFEST_JSON
        if not manifest_path.is_file():
            raise FileNotFoundError(f"'{root}' is not a capture store: no {MANIFEST_JSON}")
        rig = Rig.load(root / "rig.json")
        manifest = read_manifest(manifest_path)
        store = cls(root, rig, manifest["sequence"])
        store._manifest = manifest
        if validate:
            store.validate()
        return store

    @property
    def manifest(self) -> dict:
        """The parsed ``manifest.json``, read once per store object (one request per read at a URL) and
        refreshed by this object's own writes; reopen the store to see frames another process added."""
        if self._manifest is None:
            self._manifest = read_manifest(self.root / MANIFEST_JSON)
        return self._manifest

    @property
    def frames(self) -> list[FrameRecord]:
        """Frames listed in the manifest, in index order."""
        return [
            FrameRecord(int(f["index"]), float(f["timestamp"]), dict(f["raw"]), bool(f.get("derived", False)))
            for f in self.manifest["frames"]
        ]

    def __iter__(self) -> Iterator[FrameRecord]:
        return iter(self.frames)

    def validate(self, *, deep: bool = False) -> None:
        """Check the manifest against the files; ``deep`` also reads every raw frame's values.

        Raises:
            ValueError: listing every problem (missing raw file or frame marker, camera not in the
                rig, wrong image size or bit depth, raw files not in the manifest).
        """
        problems = manifest_problems(self.root, self.rig, self.frames, deep=deep)
        if problems:
            raise ValueError(f"capture store '{self.root}' is invalid:\n  " + "\n  ".join(problems))

    def has_frame(self, frame_index: int) -> bool:
        """True when frame ``frame_index`` was written completely (its completion marker exists)."""
        return self._marker(int(frame_index)).is_file()

    def read_raw(self, frame_index: int, camera_id: str) -> np.ndarray:
        """Raw counts of one frame of one camera, as stored."""
        record = self._record(frame_index)
        if camera_id not in record.raw:
            raise ValueError(f"frame {frame_index} has no raw frame for camera '{camera_id}'")
        return read_png(self.root / record.raw[camera_id])

    def stack(
        self, frame_index: int, camera_id: str, region: tuple[slice, slice] | None = None
    ) -> np.ndarray:
        """Float32 ``(4, h, w[, 3])`` I0/I45/I90/I135 of a frame, read lazily (only ``region``).

        Raises:
            ValueError: the frame is not complete, or a chunk of it is missing or cannot be decoded
                (naming the chunk file, the array and the frame).
        """
        rows, cols = region or (slice(None), slice(None))
        return self._read_derived(f"stacks/{camera_id}", frame_index, (slice(None), rows, cols))

    def mask(self, frame_index: int, camera_id: str, region: tuple[slice, slice] | None = None) -> np.ndarray:
        """uint8 ``(h, w)`` mask bits (1 saturated, 2 repaired defect) of a frame (errors: :meth:`stack`)."""
        rows, cols = region or (slice(None), slice(None))
        return self._read_derived(f"masks/{camera_id}", frame_index, (rows, cols))

    def observation(
        self, name: str, frame_index: int, camera_id: str, region: tuple[slice, slice] | None = None
    ) -> np.ndarray:
        """One observation image (``i_sss``, ``i_zeta``, ``i_s``, ``dop``, ``aolp``), float32
        ``(h, w[, 3])``, computed from the stored stack of ``region`` only."""
        if name not in OBSERVATION_NAMES:
            raise ValueError(f"argument 'name' must be one of {OBSERVATION_NAMES}; got {name!r}")
        return _observation(self.stack(frame_index, camera_id, region), name)

    # -------------------------------------------------------------------------------- internals
    def _marker(self, frame_index: int) -> StoragePath:
        return frame_marker_path(self.root, frame_index)

    def _record(self, frame_index: int) -> FrameRecord:
        for frame in self.frames:
            if frame.index == frame_index:
                return frame
        raise ValueError(f"frame {frame_index} is not in the manifest of '{self.root}'")

    def _zarr(self, mode: str = "a"):
        if self._group is None or mode == "a":
            try:
                self._group = open_zarr_group(self.root / DERIVED_ZARR, mode)
            except ValueError as exc:  # a zarr.json that is not JSON (JSONDecodeError) or not zarr's
                raise ValueError(f"capture store '{self.root}': the metadata of '{DERIVED_ZARR}' cannot be "
                                 f"read ({DERIVED_ZARR}/zarr.json: {exc})") from None
        return self._group

    def _derived_array(self, name: str, frame_index: int):
        record = self._record(frame_index)
        if not record.derived:
            raise ValueError(f"frame {frame_index} has no completed derived arrays (rerun ingest)")
        try:
            return self._zarr("r")[name]
        except (KeyError, FileNotFoundError) as exc:
            raise ValueError(f"derived array '{name}' is missing from '{self.root}/{DERIVED_ZARR}'") from exc
        except ValueError as exc:  # the array's (or its parent group's) zarr.json is damaged
            if str(exc).startswith(f"capture store '{self.root}'"):
                raise
            raise ValueError(f"capture store '{self.root}': the metadata of derived array '{name}' cannot be "
                             f"read ({DERIVED_ZARR}/{name}/zarr.json: {exc})") from None

    def _read_derived(self, name: str, frame_index: int, region: tuple) -> np.ndarray:
        """``array[frame_index, *region]`` of derived array ``name``, refusing a chunk that cannot be decoded
        or (float arrays, NaN-filled where never written) is missing, naming it (:mod:`.derived_chunks`)."""
        array = self._derived_array(name, frame_index)
        selection = (frame_index, *region)
        try:
            values = np.asarray(array[selection])
        except Exception as exc:
            raise ValueError(damaged_chunk_message(self.root, array, name, frame_index, selection, exc)) \
                from None
        if values.dtype.kind == "f" and np.isnan(values).any():
            message = missing_chunk_message(self.root, array, name, frame_index, selection)
            if message is not None:
                raise ValueError(message)
        return values

    @property
    def spectral_reference(self) -> str | None:
        """Reference camera of the six-channel merge: the first polarimetric colour camera, when the
        polarimetric colour cameras' ``colour_channels`` cover channels 0..5 exactly; else None."""
        cameras = [c for c in self.rig.polarimetric_cameras() if c.sensor == "color-polarization"]
        channels = sorted(v for c in cameras for v in c.colour_channels.values())
        return cameras[0].id if channels == list(range(6)) else None

    def spectral_stack(self, frame_index: int, region: tuple[slice, slice] | None = None) -> np.ndarray:
        """Float32 ``(4, h, w, 6)`` six-channel I0/I45/I90/I135 on the reference grid, read lazily (errors as
        :meth:`stack`)."""
        rows, cols = region or (slice(None), slice(None))
        return self._read_derived("spectral/stacks", frame_index, (slice(None), rows, cols))

    def spectral_observation(
        self, name: str, frame_index: int, region: tuple[slice, slice] | None = None
    ) -> np.ndarray:
        """One six-channel observation float32 ``(h, w, 6)`` on the reference grid (from the stack)."""
        if name not in OBSERVATION_NAMES:
            raise ValueError(f"argument 'name' must be one of {OBSERVATION_NAMES}; got {name!r}")
        return _observation(self.spectral_stack(frame_index, region), name)

    def spectral_valid(self, frame_index: int, region: tuple[slice, slice] | None = None) -> np.ndarray:
        """bool ``(h, w)``: the merged pixel is seen unsaturated by both cameras."""
        rows, cols = region or (slice(None), slice(None))
        return self._read_derived("spectral/valid", frame_index, (rows, cols)).astype(bool)
