"""The inputs of a reconstruction, resolved and checked before anything is written: the capture store
(or a simulation folder's ``SIM/static``), its geometry (given, a GEOM folder, a simulation's ground
truth, or none: the stereo geometry stage) and the texture resolution (:func:`resolve_reconstruct_inputs`).
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

from polarface.io.storage import PathOrUrl, StoragePath
from polarface.pipeline.inputs.folders import InputFolder, read_input_folder
from polarface.pipeline.inputs.imported import read_imported

__all__ = [
    "MIN_TEXTURE_RESOLUTION",
    "ReconstructInputs",
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
    capture's stereo pairs (into ``RESULT/geometry``); ``geometry_folder`` is the GEOM folder of a
    ``polarface geometry`` run when one was given.
    """

    capture: StoragePath
    mesh_path: Path | None
    poses_path: Path | None
    texture_resolution: int
    geometry_folder: Path | None = None


def _resolve_geometry(geometry: PathOrUrl | None, mesh: PathOrUrl | None,
                      poses: PathOrUrl | None) -> tuple[Path | None, Path | None, Path | None]:
    """``(mesh, poses, GEOM folder)``; ``(None, None, None)`` selects the stereo geometry stage."""
    if mesh is not None or poses is not None:
        if mesh is None or poses is None:
            raise ValueError("arguments '--mesh' and '--poses' must be given together")
        if geometry is not None:
            raise ValueError("argument '--geometry' cannot be combined with '--mesh'/'--poses'")
        return Path(mesh), Path(poses), None
    if geometry is None:
        return None, None, None
    folder = read_input_folder(geometry, ("geometry", "ground_truth"), argument="--geometry")
    return folder.mesh_path, folder.poses_path, folder.root if folder.kind == "geometry" else None


def resolve_reconstruct_inputs(
    capture: PathOrUrl,
    *,
    geometry: PathOrUrl | None = None,
    mesh: PathOrUrl | None = None,
    poses: PathOrUrl | None = None,
    texture_resolution: int | None = None,
) -> ReconstructInputs:
    """Resolve a capture store, simulation folder or imported session and its geometry
    (:func:`~polarface.pipeline.inputs.folders.read_input_folder`).

    ``capture`` is a capture store, a simulation folder (then ``SIM/static`` is used and the texture
    resolution defaults to the simulation's; else 512) or an imported authors' session (its own geometry
    and texture resolution). Without ``geometry``, ``mesh`` and ``poses`` the geometry stage reconstructs
    them from the capture's stereo pairs (also for a simulation: its ground truth is used only by
    ``evaluate``, or when passed as ``geometry=SIM/ground_truth``); ``geometry`` is a GEOM folder of
    ``polarface geometry`` or a simulation's ground-truth folder.

    Raises:
        FileNotFoundError: the capture or mesh does not exist. ValueError: not a capture store, no
        geometry, ``mesh`` without ``poses`` (or the reverse), or the poses file does not exist.
    """
    if texture_resolution is not None:
        check_texture_resolution(texture_resolution)
    folder = read_input_folder(capture, ("capture", "imported", "simulation"), argument="CAPTURE")
    if folder.kind == "imported":
        return _imported_inputs(folder, geometry, mesh, poses)
    if folder.static is None:
        raise ValueError(f"argument 'CAPTURE': simulation folder '{folder.root}' holds no static capture "
                         "store")
    mesh_path, poses_path, geometry_folder = _resolve_geometry(geometry, mesh, poses)
    if mesh_path is not None and not mesh_path.is_file():
        raise FileNotFoundError(f"mesh '{mesh_path}' does not exist")
    if poses_path is not None and not poses_path.is_file():
        raise ValueError(f"the capture has no poses: '{poses_path}' does not exist (pass '--poses')")
    resolution = texture_resolution or folder.texture_resolution or 512
    return ReconstructInputs(folder.static, mesh_path, poses_path, int(resolution), geometry_folder)


def _imported_inputs(folder: InputFolder, *given) -> ReconstructInputs:
    """The inputs of an imported authors' session (``polarface import-authors``; its own mesh, poses and
    texture resolution: docs/authors_dataset.md)."""
    if any(value is not None for value in given):
        raise ValueError(f"'{folder.root}' is an imported session with its own geometry: drop '--geometry', "
                         "'--mesh' and '--poses'")
    read_imported(folder.root, "static")  # finished, static, its stores intact
    return ReconstructInputs(folder.root, folder.mesh_path, folder.poses_path, int(folder.texture_resolution),
                             None)
