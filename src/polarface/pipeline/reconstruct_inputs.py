"""The inputs of a reconstruction, resolved and checked before anything is written: the capture store
(or a simulation folder's ``SIM/static``), its geometry (given, a GEOM folder, a simulation's ground
truth, or none: the stereo geometry stage) and the texture resolution (:func:`resolve_reconstruct_inputs`);
a finished capture whose derived store reads (:func:`check_capture_manifest`, :func:`check_derived_store`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path

from polarface.io.storage import StoragePath, open_zarr_group, storage_path

__all__ = [
    "MIN_TEXTURE_RESOLUTION",
    "ReconstructInputs",
    "check_capture_manifest",
    "check_derived_store",
    "check_texture_resolution",
    "max_texture_resolution",
    "resolve_reconstruct_inputs",
]

#: The smallest texture side the cylindrical atlas accepts, texels.
MIN_TEXTURE_RESOLUTION = 8
#: Working memory per texel of the whole-texture stages, bytes: the atlas rasterisation and the texel
#: geometry of the prepare stage (positions, normals, tangent frames, texel sizes in float64), the RESULT's
#: ~25 float32 maps and their previews, with room for the copies a stage makes. An estimate with a
#: margin, used only to refuse a texture that cannot fit at once instead of after minutes of work.
_BYTES_PER_TEXEL = 400
#: The largest side ever accepted (8x the paper's 2048), whatever the memory.
_MAX_TEXTURE_RESOLUTION = 16384


def max_texture_resolution(memory_bytes: int | None = None) -> int:
    """The largest texture side whose whole-texture stages fit in ``memory_bytes`` (default: this machine's
    physical memory), at most 16384."""
    if memory_bytes is None:
        try:
            memory_bytes = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):  # not a POSIX system: no bound but the fixed one
            return _MAX_TEXTURE_RESOLUTION
    return int(min(_MAX_TEXTURE_RESOLUTION, math.isqrt(max(int(memory_bytes) // _BYTES_PER_TEXEL, 0))))


def check_texture_resolution(value: object, option: str = "--texture-resolution") -> int:
    """``value`` as a texture side in texels; ValueError naming ``option`` unless it is an integer in
    [:data:`MIN_TEXTURE_RESOLUTION`, :func:`max_texture_resolution`] (a texture that cannot fit in this
    machine's memory is refused at once)."""
    upper = max_texture_resolution()
    integer = isinstance(value, int) and not isinstance(value, bool)
    if not integer or not MIN_TEXTURE_RESOLUTION <= value <= upper:
        gigabytes = value * value * _BYTES_PER_TEXEL / 1e9 if integer and value > upper else None
        needed = f" ({value}x{value} texels would need about {gigabytes:.3g} GB)" if gigabytes else ""
        raise ValueError(
            f"argument '{option}' must be an integer in [{MIN_TEXTURE_RESOLUTION}, {upper}] on this machine"
            f"{needed}; got {value!r}"
        )
    return value


@dataclasses.dataclass(frozen=True)
class ReconstructInputs:
    """Resolved inputs: the capture store, the geometry and the texture resolution.

    ``mesh_path`` and ``poses_path`` are None when the geometry stage reconstructs them from the
    capture's stereo pairs (into ``RESULT/geometry``); ``geometry_dir`` is the GEOM folder of a
    ``polarface geometry`` run when one was given.
    """

    capture: StoragePath
    mesh_path: Path | None
    poses_path: Path | None
    texture_resolution: int
    geometry_dir: Path | None = None


def _resolve_geometry(geometry: Path | None, mesh: Path | None,
                      poses: Path | None) -> tuple[Path | None, Path | None, Path | None]:
    """``(mesh, poses, GEOM folder)``; ``(None, None, None)`` selects the stereo geometry stage."""
    if mesh is not None or poses is not None:
        if mesh is None or poses is None:
            raise ValueError("arguments '--mesh' and '--poses' must be given together")
        if geometry is not None:
            raise ValueError("argument '--geometry' cannot be combined with '--mesh'/'--poses'")
        return Path(mesh), Path(poses), None
    if geometry is None:
        return None, None, None
    geometry = Path(geometry)
    if (geometry / "geometry.json").is_file():  # a GEOM folder of `polarface geometry`
        return geometry / "mesh.obj", geometry / "poses.json", geometry
    if (geometry / "mesh_rest.obj").is_file():  # the simulator's ground-truth layout
        return geometry / "mesh_rest.obj", geometry / "static" / "poses.json", None
    raise FileNotFoundError(
        f"'--geometry {geometry}' holds neither geometry.json (a GEOM folder) nor mesh_rest.obj "
        "(a simulation's ground_truth folder)"
    )


def resolve_reconstruct_inputs(
    capture: str | Path,
    *,
    geometry: str | Path | None = None,
    mesh: str | Path | None = None,
    poses: str | Path | None = None,
    texture_resolution: int | None = None,
) -> ReconstructInputs:
    """Resolve a capture store or simulation folder and its geometry.

    ``capture`` is a capture store or a simulation folder (then ``SIM/static`` is used and the texture
    resolution defaults to the simulation's; else 512). Without ``geometry``, ``mesh`` and ``poses`` the
    geometry stage reconstructs them from the capture's stereo pairs (also for a simulation: its
    ground truth is used only by ``evaluate``, or when passed as ``geometry=SIM/ground_truth``).

    Raises:
        FileNotFoundError: the capture or mesh does not exist. ValueError: not a capture store, no
        geometry, ``mesh`` without ``poses`` (or the reverse), or the poses file does not exist.
    """
    if texture_resolution is not None:
        check_texture_resolution(texture_resolution)
    capture = storage_path(capture)
    if not capture.exists():
        raise FileNotFoundError(f"capture '{capture}' does not exist")
    if isinstance(capture, Path) and (capture / "imported.json").is_file():
        return _imported_inputs(capture, geometry, mesh, poses)
    sim_root = None
    if (capture / "static" / "manifest.json").exists():
        sim_root, capture = capture, capture / "static"
    if not (capture / "manifest.json").exists():
        raise ValueError(f"'{capture}' is not a capture store (no manifest.json)")
    mesh_path, poses_path, geometry_dir = _resolve_geometry(
        Path(geometry) if geometry is not None else None, mesh, poses
    )
    if mesh_path is not None and not mesh_path.is_file():
        raise FileNotFoundError(f"mesh '{mesh_path}' does not exist")
    if poses_path is not None and not poses_path.is_file():
        raise ValueError(f"the capture has no poses: '{poses_path}' does not exist (pass '--poses')")
    resolution = texture_resolution
    if resolution is None:
        resolution = 512
        summary = (sim_root / "simulation.json") if sim_root is not None else None
        if summary is not None and summary.exists():
            resolution = int(json.loads(summary.read_text())["preset"]["texture_resolution"])
    return ReconstructInputs(capture, mesh_path, poses_path, int(resolution), geometry_dir)


def _imported_inputs(folder: Path, *given) -> ReconstructInputs:
    """The inputs of an imported authors' session (``polarface import-authors``; its own mesh, poses and
    texture resolution: docs/authors_dataset.md)."""
    from polarface.pipeline.import_authors import read_imported

    if any(value is not None for value in given):
        raise ValueError(f"'{folder}' is an imported session with its own geometry: drop '--geometry', "
                         "'--mesh' and '--poses'")
    record = read_imported(folder, "static")
    return ReconstructInputs(folder, folder / "mesh.obj", folder / "poses.json",
                             int(record["texture_resolution"][0]), None)


def check_capture_manifest(store) -> None:
    """The capture's ``manifest.json`` describes a finished capture whose frame count is its frame list's."""
    path = store.root / "manifest.json"
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


def check_derived_store(store) -> None:
    """Read ``derived.zarr``'s metadata and the first chunk of each of its arrays (corrupt metadata or
    chunks fail here, naming the store, before any output is written)."""
    path = store.root / "derived.zarr"
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
