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
``dynamic RESULT DIR_DYNAMIC`` fits each imported frame (:mod:`polarface.pipeline.dynamic.imported`).
The import streams one view at a time (8 EXR images in memory) and resumes view by view.

Inputs first (:func:`check_session`): the layout, the text files (errors name the file and the line) and
every EXR's header and offset table (size, channels, not truncated; :mod:`polarface.capture.authors_checks`)
are checked before anything is written. ``imported.json`` is then written first with ``complete: false``
and the session's fingerprint (``inputs``: its text files' SHA-1 and every EXR's size), and again with
``complete: true``, the summary and the chunk inventory of every unwrap store (``stores``) when the import
is done. A rerun into the folder therefore knows what it holds: the same session resumes (a finished import
is returned as it is); another one is refused, naming what differs (:func:`check_import_folder`), unless
the command's ``--force`` replaces the folder. An EXR that fails to decode halfway (its structure intact, its
pixels not) stops the import with :class:`ImportStoppedError`: the views written so far are a clean resumable
state (replace the file and rerun). :func:`read_imported` compares every unwrap store with its inventory,
so that a chunk deleted or changed after the import is refused (naming the store, the array and the view)
instead of being read as zarr's fill value.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from polarface.capture.authors_checks import (
    check_session_files,
    session_differences,
    session_fingerprint,
    store_inventory,
)
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
from polarface.capture.rig import Rig
from polarface.geometry.mesh import save_obj
from polarface.geometry.poses import invert_rigid, save_poses
from polarface.io import read_exr, read_json_object, record_path, resolve_recorded_path, write_json_atomic
from polarface.pipeline.inputs.frames import parse_frame_selection
from polarface.pipeline.inputs.imported import (
    IMPORTED_FORMAT,
    IMPORTED_JSON,
    IMPORTED_VERSION,
    imported_stores_problem,
    is_imported_session,
    read_imported,
)
from polarface.texture import build_views
from polarface.texture.texture_maps import (
    grid_mesh,
    texel_geometry_from_maps,
    texture_view_samples,
    write_texture_unwrap,
)

__all__ = [
    "ImportPlan", "ImportStoppedError", "check_import_folder", "check_imported_inputs", "check_session",
    "copy_unwrap_store", "import_authors", "prepare_imported",
]

class ImportStoppedError(ValueError):
    """An import that failed after it began writing (an EXR whose pixels do not decode): what it imported is
    kept as a resumable state (module docstring)."""


@dataclasses.dataclass(frozen=True, eq=False)
class ImportPlan:
    """An authors' session checked by :func:`check_session`: nothing has been written.

    Attributes:
        session: the scanned module folder. rig: its rig. gains: the white balance per camera.
        icp: static sessions: ``(F, 4, 4)`` frame -> reference, else None.
        resolution: the texture's ``(rows, cols)``. fingerprint: what identifies the session's content
            (:func:`polarface.capture.authors_checks.session_fingerprint`).
    """

    session: AuthorsSession
    rig: Rig
    gains: dict[int, np.ndarray]
    icp: np.ndarray | None
    resolution: tuple[int, int]
    fingerprint: dict[str, Any]

    @property
    def kind(self) -> str:
        return "dynamic" if self.session.dynamic else "static"


def check_session(session_dir: str | Path) -> ImportPlan:
    """Check everything an import of ``session_dir`` reads before it writes anything (module docstring).

    Raises:
        FileNotFoundError: a missing folder or file. ValueError: a partial download, a text file with a bad
            line (naming the file and the line), an EXR that is truncated, lacks its channels or has another
            size than the texture (naming it).
    """
    session = scan_session(session_dir)
    root = session.root
    rig = authors_rig(read_colmap_cameras(root / "cameras.txt"), read_colmap_images(root / "images.txt"),
                      str(root))
    gains = read_white_balance(root / "white_balance.txt")
    icp = None if session.dynamic else read_icp_poses(root / "icp-pose", session.frame_count)
    resolution = check_session_files(session)
    return ImportPlan(session, rig, gains, icp, resolution, session_fingerprint(session))


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


def _import_static(plan: ImportPlan, out: Path, progress: bool) -> dict[str, Any]:
    session = plan.session
    poses = np.stack([invert_rigid(m) for m in plan.icp])  # frame -> reference inverted: model -> world
    geometry = _geometry(session.texture_dir / "vertex.exr", session.texture_dir / "normal.exr")
    frames = list(range(session.frame_count))
    views = build_views(plan.rig, frames, poses, 0)
    reader = _view_reader(session, views, plan.gains, geometry)
    write_texture_unwrap(out / "unwrap.zarr", geometry, views, reader, progress=progress)
    save_obj(out / "mesh.obj", grid_mesh(geometry))
    save_poses(out / "poses.json", poses)
    return {"texture_resolution": list(geometry.resolution), "views": len(views)}


def _import_dynamic(plan: ImportPlan, out: Path, progress: bool) -> dict[str, Any]:
    session = plan.session
    identity = np.eye(4)
    for frame, (vertex, normal) in enumerate(session.tracked_paths):
        folder = out / "frames" / f"{frame:04d}"
        if (folder / "mesh.obj").is_file() and (folder / "unwrap.zarr").is_dir():
            continue
        geometry = _geometry(vertex, normal)
        views = build_views(plan.rig, [frame], identity[None], 0)
        folder.mkdir(parents=True, exist_ok=True)
        reader = _view_reader(session, views, plan.gains, geometry)
        write_texture_unwrap(folder / "unwrap.zarr", geometry, views, reader, progress=progress,
                             desc=f"import frame {frame}")
        save_obj(folder / "mesh.obj", grid_mesh(geometry))
    return {"texture_resolution": list(plan.resolution), "views": 2 * session.frame_count}


def _store_names(plan: ImportPlan) -> list[str]:
    """The unwrap stores of an import, relative to its folder."""
    if plan.session.dynamic:
        return [f"frames/{frame:04d}/unwrap.zarr" for frame in range(plan.session.frame_count)]
    return ["unwrap.zarr"]


def _written_files(plan: ImportPlan, out: Path) -> set[str]:
    """The session's EXRs (relative to it) that an import in ``out`` has written something from: the texture
    geometry of every store begun, the images of every view written."""
    from polarface.texture import UnwrapStore

    session = plan.session
    root = session.root
    written: set[str] = set()
    for index, name in enumerate(_store_names(plan)):
        store, partial = out / name, out / f"{name}.partial"
        if not (store.is_dir() or partial.is_dir()):
            continue
        geometry = session.tracked_paths[index] if session.dynamic else \
            (session.texture_dir / "vertex.exr", session.texture_dir / "normal.exr")  # fmt: skip
        written |= {p.relative_to(root).as_posix() for p in geometry}
        try:
            unwrap = UnwrapStore.open(store if store.is_dir() else partial)
            views = unwrap.views
            done = range(len(views)) if store.is_dir() else unwrap.done()
        except (ValueError, OSError, KeyError):  # left unreadable by a killed run: rewritten from scratch
            continue
        for view in (views[i] for i in done):
            camera = int(view.camera_id.removeprefix("cam"))
            for angle in AUTHORS_ANGLES:
                paths = session.observation_paths.get((angle, camera, view.frame), ())
                written |= {p.relative_to(root).as_posix() for p in paths}
    return written


_IMPORT_ENTRIES = ("rig.json", "unwrap.zarr", "unwrap.zarr.partial", "mesh.obj", "poses.json", "frames")


def check_import_folder(plan: ImportPlan, out: str | Path) -> dict[str, Any] | None:
    """The record of the import folder ``out`` when it may be continued with ``plan``'s session (None: no
    import there yet).

    Raises:
        ValueError: ``out`` holds an import of another session (another kind, frame list, text file, or an
            EXR it has already imported that now differs; named), or import files without a record.
    """
    out = Path(out)
    file = out / IMPORTED_JSON
    if not file.is_file():
        if any((out / name).exists() for name in _IMPORT_ENTRIES):
            raise ValueError(f"'{out}' holds an unfinished import that records no session (polarface before "
                             "issue 47); pass --force to import again or choose another --out")
        return None
    record = read_json_object(file)
    if record.get("format") != IMPORTED_FORMAT:
        raise ValueError(f"'{file}' is not an authors' import record (format {record.get('format')!r})")
    problems = []
    if record.get("kind") != plan.kind:
        problems.append(f"it holds a {record.get('kind')} session, not a {plan.kind} one")
    if list(record.get("frames", [])) != list(plan.session.frame_names):
        problems.append(f"its frames are {_frame_span(record.get('frames', []))}, the session's "
                        f"{_frame_span(plan.session.frame_names)}")
    inputs = record.get("inputs")
    if isinstance(inputs, dict):
        problems += session_differences(inputs, plan.fingerprint, _written_files(plan, out))
    else:  # a record of polarface before issue 47: the session's place is all it tells
        recorded = resolve_recorded_path(out, record.get("session"))
        if recorded is None or Path(os.path.abspath(recorded)) != Path(os.path.abspath(plan.session.root)):
            problems.append(f"it was imported from '{record.get('session')}'")
    if problems:
        more = f" (and {len(problems) - 3} more)" if len(problems) > 3 else ""
        raise ValueError(f"'{out}' holds an import of another session than '{plan.session.root}': "
                         f"{'; '.join(problems[:3])}{more}; pass --force to replace it or choose another "
                         "--out")
    return record


def _frame_span(frames) -> str:
    frames = list(frames)
    return f"{len(frames)} ({frames[0]}..{frames[-1]})" if frames else "none"


def import_authors(session_dir: str | Path | ImportPlan, out: str | Path, *,
                   progress: bool = True) -> dict[str, Any]:
    """Import an authors' module folder into the imported session folder ``out`` (module docstring).

    Args:
        session_dir: the module folder (``5_Static/90``, ``6_Dynamic_1/90``, or their parent), or the
            :class:`ImportPlan` of :func:`check_session`.
        out: the imported session folder (created; the caller applies the output-folder policy). A
            rerun into the same folder resumes at the first view (or dynamic frame) not written; a finished
            import of the same session is returned as it is.

    Returns:
        ``imported.json``'s content.

    Raises:
        FileNotFoundError: a missing folder, angle folder, visibility map or camera file, naming it.
        ValueError: inconsistent frame lists, unreadable or truncated files, nothing seen, or ``out``
            holding an import of another session (all before anything is written).
        ImportStoppedError: an EXR whose pixels fail to decode once writing began (the views written are
            kept).
    """
    started = time.perf_counter()
    plan = session_dir if isinstance(session_dir, ImportPlan) else check_session(session_dir)
    session = plan.session
    out = Path(out)
    existing = check_import_folder(plan, out)
    if existing is not None and existing.get("complete") is True:
        problem = imported_stores_problem(out, existing)
        if problem is not None:
            raise ValueError(f"imported session '{out}': {problem}; pass --force to import it again")
        return existing
    record = {
        "format": IMPORTED_FORMAT,
        "version": IMPORTED_VERSION,
        "kind": plan.kind,
        "session": record_path(out, session.root),
        "frames": list(session.frame_names),
        "cameras": [f"cam{c}" for c in AUTHORS_CAMERAS],
        "white_balance": {f"cam{c}": [float(v) for v in g] for c, g in plan.gains.items()},
        "inputs": plan.fingerprint,
        "complete": False,
    }
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / IMPORTED_JSON, record)  # first: a rerun knows which session this folder holds
    plan.rig.save(out / "rig.json")
    try:
        summary = (_import_dynamic if session.dynamic else _import_static)(plan, out, progress)
    except ValueError as exc:
        raise ImportStoppedError(str(exc)) from exc
    stores = {name: store_inventory(out / name) for name in _store_names(plan)}
    record = {**record, **summary, "stores": stores, "seconds": round(time.perf_counter() - started, 3),
              "complete": True}
    write_json_atomic(out / IMPORTED_JSON, record)
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
    :func:`polarface.texture.views.build_views` does), its rig, mesh and poses, and the result.json header."""
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
    poses = shutil.copyfile(Path(imported) / "poses.json", folder.poses_path)  # the RESULT needs no input
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
        "capture": record_path(folder.root, imported),
        "imported": record["session"],
        "mesh": record_path(folder.root, Path(imported) / "mesh.obj"),
        "poses": record_path(folder.root, poses),
        "poses_source": record_path(folder.root, Path(imported) / "poses.json"),
        "geometry": None,
        "reference_frame": 0,
        "excluded_frames": [],
        "timings": {"prepare_s": time.perf_counter() - started},
    }


def check_imported_inputs(static: Path, dynamic: Path | None, frames: str | None) -> None:
    """Refuse, before anything is written, a reconstruction mixing an imported session with a capture
    store, an unfinished import, or a dynamic import whose texture differs from the static one's."""

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
