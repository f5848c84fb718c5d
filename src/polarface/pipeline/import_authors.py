"""``polarface import-authors``: an authors' preprocessed session (``docs/authors_dataset.md``) turned into
an *imported session* folder that ``polarface reconstruct`` (static) and the dynamic stage run on.

Layout of the imported folder ``DIR``::

    DIR/imported.json   format "polarface-authors-import", version, kind ("static" | "dynamic"),
                        session, frames (file frame numbers), texture_resolution, white_balance,
                        complete (written last: an interrupted import is never taken for a finished one)
    DIR/rig.json        cameras cam1/cam2 from cameras.txt/images.txt, the paper's LED ring
                        (:mod:`polarface.capture.authors_rig`), the default spectral calibration
    static:  DIR/unwrap.zarr    the unwrap store (:mod:`polarface.texture.unwrap_store`), no view held out
             DIR/mesh.obj       the texel-grid mesh of vertex.exr (model frame = the ICP reference frame, mm)
             DIR/poses.json     model -> world per frame: the inverse of each icp-pose matrix
    dynamic: DIR/frames/NNNN/unwrap.zarr, mesh.obj   per frame, its tracked maps (world frame, pose identity)

``reconstruct DIR --out RESULT`` copies the unwrap store, rig and mesh into RESULT (its ``prepare`` stage,
:func:`prepare_imported`; ``--holdout-every`` sets the held-out views there) and fits as usual;
``dynamic RESULT DIR_DYNAMIC`` fits each imported frame (:mod:`polarface.pipeline.dynamic_imported`).
The import streams one view at a time (8 EXR images in memory) and resumes view by view.
"""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from polarface.capture.authors_layout import (
    AUTHORS_ANGLES,
    AUTHORS_CAMERAS,
    AuthorsSession,
    read_colmap_cameras,
    read_colmap_images,
    read_icp_poses,
    read_white_balance,
    scan_session,
)
from polarface.capture.authors_rig import authors_rig
from polarface.geometry.mesh import save_obj
from polarface.geometry.poses import invert_rigid, save_poses
from polarface.io import read_exr, read_json_object, write_json_atomic
from polarface.texture import build_views
from polarface.texture.texture_maps import (
    grid_mesh,
    texel_geometry_from_maps,
    texture_view_samples,
    write_texture_unwrap,
)

__all__ = ["IMPORTED_FORMAT", "IMPORTED_JSON", "import_authors", "is_imported_session", "read_imported"]

IMPORTED_JSON = "imported.json"
IMPORTED_FORMAT = "polarface-authors-import"
IMPORTED_VERSION = 1


def is_imported_session(path: str | Path | None) -> bool:
    """Whether ``path`` is a local imported session folder (holds ``imported.json``); False for None."""
    return isinstance(path, Path | str) and str(path) != "" and (Path(path) / IMPORTED_JSON).is_file()


def read_imported(path: str | Path, kind: str | None = None) -> dict[str, Any]:
    """``imported.json`` of a finished import (of ``kind`` when given).

    Raises:
        FileNotFoundError: no ``imported.json``. ValueError: not finished, another format or kind.
    """
    file = Path(path) / IMPORTED_JSON
    record = read_json_object(file)
    if record.get("format") != IMPORTED_FORMAT:
        raise ValueError(f"'{file}' is not an authors' import record (format {record.get('format')!r})")
    if record.get("complete") is not True:
        raise ValueError(f"'{file}': the import was interrupted; rerun 'polarface import-authors' to finish")
    if kind is not None and record.get("kind") != kind:
        raise ValueError(f"'{path}' is an imported {record.get('kind')} session; a {kind} one is needed here")
    return record


def _rgb(path: Path, shape: tuple[int, int] | None) -> np.ndarray:
    channels = read_exr(path)
    missing = [c for c in "RGB" if c not in channels]
    if missing:
        raise ValueError(f"EXR '{path}' lacks channel(s) {missing} (has {sorted(channels)})")
    image = np.stack([channels[c] for c in "RGB"], axis=-1)
    if shape is not None and image.shape[:2] != shape:
        raise ValueError(f"EXR '{path}' is {image.shape[1]}x{image.shape[0]} texels; the texture is "
                         f"{shape[1]}x{shape[0]}")
    return image


def _visibility(path: Path, shape: tuple[int, int]) -> np.ndarray:
    channels = read_exr(path)
    if not channels:
        raise ValueError(f"visibility map '{path}' has no channel")
    value = np.mean(np.stack(list(channels.values()), axis=-1), axis=-1)
    if value.shape != shape:
        raise ValueError(f"visibility map '{path}' is {value.shape[1]}x{value.shape[0]} texels; the texture "
                         f"is {shape[1]}x{shape[0]}")
    return value


def _view_reader(session: AuthorsSession, views, gains: dict[int, np.ndarray], geometry):
    """view index -> ``(obs, valid)`` read from the view's 4 images and 4 visibility maps."""
    camera_index = {f"cam{c}": c for c in AUTHORS_CAMERAS}

    def read(index: int) -> tuple[np.ndarray, np.ndarray]:
        view = views[index]
        camera = camera_index[view.camera_id]
        paths = [session.observation_paths[(angle, camera, view.frame)] for angle in AUTHORS_ANGLES]
        shape = geometry.resolution
        images = [_rgb(image, shape) for image, _ in paths]
        visibilities = [_visibility(visibility, shape) for _, visibility in paths]
        return texture_view_samples(images, visibilities, gains[camera], geometry.mask)

    return read


def _geometry(position_path: Path, normal_path: Path):
    try:
        return texel_geometry_from_maps(_rgb(position_path, None), _rgb(normal_path, None))
    except ValueError as exc:
        raise ValueError(f"'{position_path}' / '{normal_path}': {exc}") from None


def _import_static(session: AuthorsSession, out: Path, rig, gains, progress: bool) -> dict[str, Any]:
    icp = read_icp_poses(session.root / "icp-pose", session.frame_count)  # checked before any write too
    poses = np.stack([invert_rigid(m) for m in icp])  # frame -> reference inverted: model -> world
    geometry = _geometry(session.texture_dir / "vertex.exr", session.texture_dir / "normal.exr")
    frames = list(range(session.frame_count))
    views = build_views(rig, frames, poses, 0)
    write_texture_unwrap(out / "unwrap.zarr", geometry, views, _view_reader(session, views, gains, geometry),
                         progress=progress)
    save_obj(out / "mesh.obj", grid_mesh(geometry))
    save_poses(out / "poses.json", poses)
    return {"texture_resolution": list(geometry.resolution), "views": len(views)}


def _import_dynamic(session: AuthorsSession, out: Path, rig, gains, progress: bool) -> dict[str, Any]:
    identity = np.eye(4)
    resolution = None
    for frame, (vertex, normal) in enumerate(session.tracked_paths):
        folder = out / "frames" / f"{frame:04d}"
        if (folder / "mesh.obj").is_file() and (folder / "unwrap.zarr").is_dir():
            resolution = resolution or list(read_exr(vertex)["R"].shape)
            continue
        geometry = _geometry(vertex, normal)
        resolution = list(geometry.resolution)
        views = build_views(rig, [frame], identity[None], 0)
        folder.mkdir(parents=True, exist_ok=True)
        reader = _view_reader(session, views, gains, geometry)
        write_texture_unwrap(folder / "unwrap.zarr", geometry, views, reader, progress=progress,
                             desc=f"import frame {frame}")
        save_obj(folder / "mesh.obj", grid_mesh(geometry))
    return {"texture_resolution": resolution, "views": 2 * session.frame_count}


def import_authors(session_dir: str | Path, out: str | Path, *, progress: bool = True) -> dict[str, Any]:
    """Import an authors' module folder into the imported session folder ``out`` (module docstring).

    Args:
        session_dir: the module folder (``5_Static/90``, ``6_Dynamic_1/90``, or their parent).
        out: the imported session folder (created; the caller applies the output-folder policy). A
            rerun into the same folder resumes at the first view (or dynamic frame) not written.

    Returns:
        ``imported.json``'s content.

    Raises:
        FileNotFoundError: a missing folder, angle folder, visibility map or camera file, naming it.
        ValueError: inconsistent frame lists, unreadable files, nothing seen.
    """
    started = time.perf_counter()
    session = scan_session(session_dir)
    out = Path(out)
    root = session.root
    rig = authors_rig(read_colmap_cameras(root / "cameras.txt"), read_colmap_images(root / "images.txt"),
                      str(root))
    gains = read_white_balance(root / "white_balance.txt")
    if not session.dynamic:
        read_icp_poses(root / "icp-pose", session.frame_count)  # a partial download fails before any write
    out.mkdir(parents=True, exist_ok=True)
    record_path = out / IMPORTED_JSON
    if record_path.exists():
        record_path.unlink()  # rewritten last, when the import is complete
    rig.save(out / "rig.json")
    kind = "dynamic" if session.dynamic else "static"
    summary = (_import_dynamic if session.dynamic else _import_static)(session, out, rig, gains, progress)
    record = {
        "format": IMPORTED_FORMAT,
        "version": IMPORTED_VERSION,
        "kind": kind,
        "session": str(root),
        "frames": list(session.frame_names),
        "cameras": [f"cam{c}" for c in AUTHORS_CAMERAS],
        "white_balance": {f"cam{c}": [float(v) for v in g] for c, g in gains.items()},
        **summary,
        "seconds": round(time.perf_counter() - started, 3),
        "complete": True,
    }
    write_json_atomic(record_path, record)
    return record


def _link_or_copy(source: str, target: str) -> None:
    """Hard-link a chunk file (never rewritten: zarr replaces chunks by new files), copy metadata (``*.json``,
    rewritten in place by attribute updates); copy where links are impossible (another file system)."""
    if source.endswith(".json"):
        shutil.copy2(source, target)
        return
    try:
        os.link(source, target)
    except OSError:
        shutil.copy2(source, target)


def copy_unwrap_store(source: Path, target: Path) -> None:
    """Copy an unwrap store (chunks hard-linked where possible) into ``target`` via ``target.partial``."""
    partial = target.with_name(target.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    shutil.copytree(source, partial, copy_function=_link_or_copy)
    shutil.rmtree(target, ignore_errors=True)
    partial.rename(target)


def prepare_imported(imported: Path, folder, holdout_every: int) -> dict[str, Any]:
    """The ``prepare`` stage on an imported static session: its unwrap store copied into the RESULT
    ``folder`` (every ``holdout_every``-th frame's views marked held out, as
    :func:`polarface.texture.views.build_views` does), its rig and mesh, and the result.json header."""
    from polarface.geometry.mesh import load_mesh
    from polarface.results import default_channel_names
    from polarface.texture import UnwrapStore

    started = time.perf_counter()
    record = read_imported(imported, "static")
    target = Path(folder.unwrap_path)
    copy_unwrap_store(Path(imported) / "unwrap.zarr", target)
    store = UnwrapStore.open(target, mode="a")
    views = [
        {**v.to_dict(), "held_out": holdout_every >= 2 and v.frame % holdout_every == holdout_every - 1}
        for v in store.views
    ]
    store.root.attrs["views"] = views
    rig_path = Path(imported) / "rig.json"
    shutil.copyfile(rig_path, folder.rig_path)
    folder.write_mesh(load_mesh(Path(imported) / "mesh.obj"))
    unwrap = UnwrapStore.open(target)
    geometry = unwrap.geometry()
    texel_size = float(np.median(0.5 * (geometry.texel_size_u + geometry.texel_size_v)[geometry.mask]))
    rig = folder.read_rig()
    names = list(rig.spectral.to_calibration().channel_names) if rig.spectral is not None else \
        default_channel_names()  # fmt: skip
    folder.write_result_header(names, unwrap.resolution, texel_size)
    return {
        "views": len(views),
        "held_out_views": [i for i, v in enumerate(views) if v["held_out"]],
        "capture": str(imported),
        "imported": record["session"],
        "mesh": str(Path(imported) / "mesh.obj"),
        "poses": str(Path(imported) / "poses.json"),
        "geometry": None,
        "reference_frame": 0,
        "excluded_frames": [],
        "timings": {"prepare_s": time.perf_counter() - started},
    }


def check_imported_inputs(static: Path, dynamic: Path | None, frames: str | None) -> None:
    """Refuse, before anything is written, a reconstruction mixing an imported session with a capture
    store, an unfinished import, or a dynamic import whose texture differs from the static one's."""
    from polarface.pipeline.dynamic_inputs import parse_frame_selection

    if not is_imported_session(static):
        raise ValueError(f"'--dynamic {dynamic}' is an imported authors' session: the static input must be "
                         "one too ('polarface import-authors 5_Static --out DIR')")
    record = read_imported(static, "static")
    if dynamic is None:
        return
    if not is_imported_session(dynamic):
        raise ValueError(f"'{static}' is an imported authors' session: '--dynamic' must be one too "
                         "('polarface import-authors 6_Dynamic_1 --out DIR')")
    moving = read_imported(dynamic, "dynamic")
    if list(moving["texture_resolution"]) != list(record["texture_resolution"]):
        raise ValueError(f"'{dynamic}' has texture {moving['texture_resolution']} but '{static}' has "
                         f"{record['texture_resolution']}: the dynamic maps must share the static atlas")
    parse_frame_selection(frames, range(len(moving["frames"])))
