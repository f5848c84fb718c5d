"""Writing a capture store: create or resume it, add frames (raw PNGs, derived arrays, markers), the manifest.

The writing methods of :class:`polarface.capture.store.CaptureStore`, which mixes them in (the layout
and the reading methods: :mod:`polarface.capture.store`). Derived arrays: float32 stacks
``(F, 4, H, W[, 3|6])`` (NaN where not written) and uint8 masks ``(F, H, W)``, in chunks of one frame,
one analyzer and at most ``chunk`` x ``chunk`` pixels.

Atomicity: raw PNGs and JSON files are written through :mod:`polarface.io.atomic`; zarr chunks are
written before a frame's marker, and a marker is removed before its frame is rewritten, so a crash
leaves either a complete frame or a frame without marker, which readers refuse and a rerun redoes.
Arrays grow along the frame axis; one frame of one camera is in memory at a time.

Frames written in parallel (executor units): one frame per chunk along axis 0, so frames never share
a chunk; the submitting process sizes the arrays first (:meth:`CaptureStore.reserve_frames`), a unit
opens the store with :meth:`CaptureStore.open_writer` and adds its frame with ``update_manifest=False``,
and the submitting process rebuilds the manifest (:meth:`CaptureStore.write_manifest`) and finalizes.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Literal, Self

import numpy as np

from polarface.capture.analyzers import applied_analyzers
from polarface.capture.demosaic import DemosaicMethod, PolarizationStack, applied_gains, demosaic_camera
from polarface.capture.manifest import (
    DERIVED_ZARR,
    MANIFEST_JSON,
    raw_bit_depth_ok,
    raw_digest,
    read_frame_marker,
    read_manifest,
    write_manifest,
)
from polarface.capture.observations import merge_six_channels
from polarface.capture.rig import Camera, Rig
from polarface.io.atomic import write_json_atomic
from polarface.io.images import write_png
from polarface.io.storage import PathOrUrl, StoragePath, storage_path

_POLARIZATION = ("mono-polarization", "color-polarization")


def _remove_stale_temporaries(root: StoragePath) -> None:
    """Delete the temporaries an interrupted atomic write left (nothing ever reads them): our ``.tmp-*``
    files (keys on a URL) and, on a local store, zarr's ``<chunk>.<uuid>.partial`` files under
    ``derived.zarr`` (zarr writes a chunk there and renames it; a process killed in between leaves it
    behind; zarr's fsspec store puts a chunk in one piece and leaves none)."""
    for pattern in (".tmp-*", "raw/*/.tmp-*", "frames/.tmp-*"):
        for path in root.glob(pattern):
            if path.is_file():
                path.unlink(missing_ok=True)
    derived = root / DERIVED_ZARR
    if isinstance(derived, Path) and derived.is_dir():
        for path in derived.rglob("*.partial"):
            if path.is_file():
                path.unlink(missing_ok=True)


class CaptureStoreWriter:
    """The writing methods of :class:`polarface.capture.store.CaptureStore` (a mixin: it uses the store's
    ``root``, ``rig``, ``sequence``, ``chunk``, ``plane_distance_mm`` and reading helpers; its constructors
    return the class they are called on, the store)."""

    @classmethod
    def create(
        cls,
        path: PathOrUrl,
        rig: Rig,
        *,
        sequence: Literal["static", "dynamic"] = "static",
        chunk: int = 512,
    ) -> Self:
        """Create a store, or reopen an unfinished/finished one with the same rig to resume.

        Stale ``.tmp-*`` files of a killed run (in the root, ``raw/<camera>/`` and ``frames/``) are
        removed first; a folder holding nothing else counts as empty. ``path`` is a local path or a URL.

        Raises:
            ValueError: on a bad ``sequence``, an existing store with a different rig, or a URL of an
                unknown protocol or missing package.
        """
        if sequence not in ("static", "dynamic"):
            raise ValueError(f"argument 'sequence' must be 'static' or 'dynamic'; got {sequence!r}")
        root = storage_path(path)
        rig_path = root / "rig.json"
        _remove_stale_temporaries(root)
        if rig_path.exists():
            existing = Rig.load(rig_path)
            if existing.model_dump(mode="json") != rig.model_dump(mode="json"):
                raise ValueError(f"store '{root}' exists with a different rig.json; choose another output")
            manifest_path = root / MANIFEST_JSON
            held = read_manifest(manifest_path)["sequence"] if manifest_path.exists() else sequence
            if held != sequence:
                raise ValueError(f"store '{root}' holds a {held} sequence, not a {sequence} one; choose "
                                 "another output")
        else:
            if root.exists() and any(root.iterdir()):
                raise ValueError(f"output '{root}' exists and is not a capture store")
            root.mkdir(parents=True, exist_ok=True)
            rig.save(rig_path)
        (root / "frames").mkdir(exist_ok=True)
        store = cls(root, rig, sequence, chunk)
        store._write_manifest(complete=False)
        return store

    @classmethod
    def open_writer(cls, path: PathOrUrl, *, chunk: int = 512) -> Self:
        """Open a store that :meth:`create` made (finished or not) to add frames from a unit: nothing is
        validated, removed or written (module docstring).

        Raises:
            FileNotFoundError: the store has no ``rig.json`` or ``manifest.json``.
            ValueError: an invalid rig or manifest.
        """
        root = storage_path(path)
        for name in ("rig.json", MANIFEST_JSON):
            if not (root / name).is_file():
                raise FileNotFoundError(f"'{root}' is not a capture store being written: no {name}")
        return cls(root, Rig.load(root / "rig.json"), read_manifest(root / MANIFEST_JSON)["sequence"],
                   chunk)

    def reserve_frames(self, frame_count: int) -> None:
        """Create or grow every derived array to hold frames ``0 .. frame_count - 1`` (shapes from the rig),
        so that units adding frames write chunks only, never array metadata; larger arrays are kept.

        Raises:
            ValueError: ``frame_count < 1``, or an existing array's shape disagrees with the rig.
        """
        if int(frame_count) < 1:
            raise ValueError(f"argument 'frame_count' must be >= 1; got {frame_count}")
        last = int(frame_count) - 1
        for camera in self.rig.polarimetric_cameras():
            if camera.sensor not in _POLARIZATION:
                continue
            image = (camera.height, camera.width)
            colour = (3,) if camera.sensor == "color-polarization" else ()
            self._ensure(f"stacks/{camera.id}", last, (4, *image, *colour), "float32", 1)
            self._ensure(f"masks/{camera.id}", last, image, "uint8", 0)
        if self.spectral_reference is not None:
            reference = self.rig.camera(self.spectral_reference)
            image = (reference.height, reference.width)
            self._ensure("spectral/stacks", last, (4, *image, 6), "float32", 1)
            self._ensure("spectral/valid", last, image, "uint8", 0)

    def add_frame(
        self,
        frame_index: int,
        timestamp: float,
        raws: Mapping[str, np.ndarray],
        *,
        process: bool = True,
        method: DemosaicMethod = "residual",
        update_manifest: bool = True,
    ) -> bool:
        """Store one frame: raw PNGs, then (``process``) stacks, masks and observations, then the marker.

        A frame whose marker records the same raw content (and derived state) is skipped (resume).

        Args:
            frame_index: slot >= 0.
            timestamp: seconds.
            raws: camera id -> raw counts ``(H, W)`` (integer); every polarimetric camera of the rig.
            process: compute the derived arrays.
            method: demosaicing method.
            update_manifest: rebuild ``manifest.json`` after the frame (False in a unit running beside
                others: the submitting process rebuilds it; module docstring).

        Returns:
            True if the frame was written, False if skipped as already complete.

        Raises:
            ValueError: unknown camera, missing polarimetric camera, wrong size/bit depth/dtype.
        """
        if int(frame_index) != frame_index or frame_index < 0:
            raise ValueError(f"argument 'frame_index' must be a non-negative integer; got {frame_index}")
        if not np.isfinite(timestamp):
            raise ValueError(f"argument 'timestamp' must be finite; got {timestamp}")
        frame_index = int(frame_index)
        for cam_id in raws:
            self.rig.camera(cam_id)
        missing = [c.id for c in self.rig.polarimetric_cameras() if c.id not in raws]
        if missing:
            raise ValueError(f"frame {frame_index}: raw frames missing for polarimetric camera(s) {missing}")
        arrays = {cam_id: np.asarray(raw) for cam_id, raw in raws.items()}
        for cam_id, raw in arrays.items():
            raw_bit_depth_ok(raw, self.rig.camera(cam_id))
        digests = {cam_id: raw_digest(raw) for cam_id, raw in arrays.items()}
        analyzers = applied_analyzers(self.rig) if process else None
        gains = applied_gains(self.rig) if process else None
        marker_path = self._marker(frame_index)
        if marker_path.exists():
            old = read_frame_marker(marker_path)
            if (
                old.get("digests") == digests
                and old.get("derived", False) >= process
                and (not process or (old.get("method"), old.get("analyzers"), old.get("channel_gains"))
                     == (method, analyzers, gains))
            ):
                return False
            marker_path.unlink()  # the frame is rewritten: untrust it first
            if update_manifest:
                self._write_manifest(complete=False)
        raw_paths = {}
        for cam_id, raw in arrays.items():
            relative = f"raw/{cam_id}/{frame_index:06d}.png"
            bit_depth = 8 if self.rig.camera(cam_id).bit_depth <= 8 else 16
            write_png(self.root / relative, raw, bit_depth=bit_depth)
            raw_paths[cam_id] = relative
        if process:
            stacks = {}
            for camera in self.rig.polarimetric_cameras():
                if camera.sensor in _POLARIZATION:
                    stacks[camera.id] = self._write_derived(frame_index, camera, arrays[camera.id], method)
            if self.spectral_reference is not None:
                self._write_spectral(frame_index, stacks)
        marker = {
            "frame_index": frame_index,
            "timestamp": float(timestamp),
            "raw": raw_paths,
            "digests": digests,
            "derived": bool(process),
            "method": method if process else None,
        }
        if analyzers:
            marker["analyzers"] = analyzers  # absent: ideal analyzers, nothing applied (docs/sensors.md)
        if gains:
            marker["channel_gains"] = gains  # absent: unit gains, nothing applied
        write_json_atomic(marker_path, marker)
        if update_manifest:
            self._write_manifest(complete=False)
        return True

    def write_manifest(self) -> dict:
        """Rebuild ``manifest.json`` from the frame markers, not complete yet (the submitting process of
        parallel units, as they finish); returns it."""
        return self._write_manifest(complete=False)

    def finalize(self) -> dict:
        """Write ``manifest.json`` listing every completed frame, then validate the store."""
        manifest = self._write_manifest(complete=True)
        self.validate()
        return manifest

    # -------------------------------------------------------------------------------- internals
    def _ensure(self, name: str, frame_index: int, tail: tuple[int, ...], dtype: str, spatial_axis: int):
        group = self._zarr("a")
        chunks = [1, *tail]
        for axis in (spatial_axis, spatial_axis + 1):
            chunks[axis + 1] = min(self.chunk, tail[axis])
        if spatial_axis == 1:
            chunks[1] = 1
        if name in group:
            array = group[name]
            if tuple(array.shape[1:]) != tail:
                raise ValueError(f"derived array '{name}' has shape {array.shape}, expected (F, {tail})")
            if array.shape[0] <= frame_index:
                array.resize((frame_index + 1, *tail))
            return array
        fill = 0 if dtype == "uint8" else float("nan")
        from zarr.codecs import BloscCodec

        return group.create_array(
            name,
            compressors=[BloscCodec(cname="lz4", clevel=1, shuffle="shuffle")],
            shape=(frame_index + 1, *tail),
            chunks=tuple(chunks),
            dtype=dtype,
            fill_value=fill,
        )

    def _write_spectral(self, frame_index: int, stacks: dict) -> None:
        reference = self.spectral_reference
        cameras = [c.id for c in self.rig.polarimetric_cameras() if c.sensor == "color-polarization"]
        merged, valid = merge_six_channels(
            {cam: stacks[cam].intensities for cam in cameras},
            self.rig,
            reference,
            plane_distance_mm=self.plane_distance_mm,
            masks={cam: stacks[cam].valid for cam in cameras},
        )
        shape = merged.shape[1:3]
        self._ensure("spectral/stacks", frame_index, merged.shape, "float32", 1)[frame_index] = merged
        self._ensure("spectral/valid", frame_index, shape, "uint8", 0)[frame_index] = valid.astype(np.uint8)

    def _write_derived(
        self, frame_index: int, camera: Camera, raw: np.ndarray, method: DemosaicMethod
    ) -> PolarizationStack:
        stack = demosaic_camera(raw, camera, method=method)
        image_tail = stack.intensities.shape[1:]
        stacks = self._ensure(f"stacks/{camera.id}", frame_index, (4, *image_tail), "float32", 1)
        stacks[frame_index] = stack.intensities
        mask = stack.saturated.astype(np.uint8) | (stack.defects.astype(np.uint8) << 1)
        self._ensure(f"masks/{camera.id}", frame_index, mask.shape, "uint8", 0)[frame_index] = mask
        return stack

    def _write_manifest(self, *, complete: bool) -> dict:
        self._manifest = write_manifest(self.root, self.rig, self.sequence, complete=complete)
        return self._manifest
