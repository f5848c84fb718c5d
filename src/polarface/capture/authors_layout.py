"""The file layout of the authors' preprocessed face sessions (Ha et al. 2024's dataset release).

What a session folder holds, every fact with where it was read and every assumption, is in
``docs/authors_dataset.md``. In short, a module folder (``5_Static/90`` or ``6_Dynamic_1/90``) holds::

    texture/{0,45,90,135}/exr/img{C}_{F}.exr          texture-space observation, RGB, linear, per camera C
    texture/{0,45,90,135}/exr/visible_img{C}_{F}.exr  its visibility (mean of the channels > 0.5: seen)
    texture/vertex.exr, texture/normal.exr            static: the reference mesh's UV-space position and
                                                      normal maps (ICP reference frame, mm)
    texture/tracked/vertex*.exr, normal*.exr          dynamic: the tracked maps of each frame (world, mm)
    icp-pose/*.txt                                    per frame a 4x4 frame -> reference transform
    cameras.txt, images.txt                           COLMAP text model: intrinsics (OPENCV), world -> camera
    white_balance.txt                                 per camera a row [index, gain_R, gain_G, gain_B]

Cameras 1 and 2 are the polarimetric cameras used by the fit (camera 1: the upper half bands,
spectral channels 0-2; camera 2: the lower ones, 3-5); camera 3, the reference camera, is ignored.
This module scans and checks the layout (:func:`scan_session`) and reads and writes its text files;
:mod:`polarface.capture.authors_rig` turns the cameras into a :class:`polarface.capture.rig.Rig`.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from polarface.io import atomic_path

__all__ = [
    "AUTHORS_ANGLES",
    "AUTHORS_CAMERAS",
    "AuthorsSession",
    "ColmapCamera",
    "read_colmap_cameras",
    "read_colmap_images",
    "read_icp_poses",
    "read_white_balance",
    "scan_session",
    "write_colmap_cameras",
    "write_colmap_images",
]

#: Polarizer angles (degrees) of the ``texture/<angle>/exr`` folders.
AUTHORS_ANGLES = (0, 45, 90, 135)
#: The polarimetric cameras used by the fit (1-based, as in the file names and ``images.txt``).
AUTHORS_CAMERAS = (1, 2)
_IMAGE_NAME = re.compile(r"^(visible_)?img(\d+)_(\d+)\.exr$")


@dataclasses.dataclass(frozen=True)
class ColmapCamera:
    """One camera of ``cameras.txt``: ``width``/``height`` px, ``K`` ``(3, 3)`` px, OpenCV ``distortion``."""

    width: int
    height: int
    K: np.ndarray
    distortion: tuple[float, ...]


@dataclasses.dataclass(frozen=True)
class AuthorsSession:
    """A scanned module folder (checked by :func:`scan_session`).

    Attributes:
        root: the module folder (``.../5_Static/90``).
        dynamic: True when ``texture/tracked`` holds per-frame maps (a dynamic module).
        frame_names: the file frame numbers (strings as written, e.g. ``"0007"``), sorted numerically;
            polarface frame ``k`` is ``frame_names[k]``.
        observation_paths: ``(angle, camera, frame index) -> (image, visibility)`` paths.
        tracked_paths: dynamic only: per frame ``(vertex, normal)`` map paths, else empty.
    """

    root: Path
    dynamic: bool
    frame_names: tuple[str, ...]
    observation_paths: Mapping[tuple[int, int, int], tuple[Path, Path]]
    tracked_paths: tuple[tuple[Path, Path], ...] = ()

    @property
    def texture_dir(self) -> Path:
        return self.root / "texture"

    @property
    def frame_count(self) -> int:
        return len(self.frame_names)


def _module_root(path: Path) -> Path:
    """``path`` itself, or its ``90`` sub-folder when the texture folder lies there."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"authors' session '{path}' does not exist")
    if not (path / "texture").is_dir() and (path / "90" / "texture").is_dir():
        return path / "90"
    return path


def _angle_files(folder: Path) -> dict[int, dict[str, dict[str, Path]]]:
    """``camera -> frame name -> {"image"|"visibility": path}`` of one ``texture/<angle>/exr`` folder."""
    found: dict[int, dict[str, dict[str, Path]]] = {}
    for entry in sorted(folder.iterdir()):
        match = _IMAGE_NAME.match(entry.name)
        if match is None:
            continue
        kind = "visibility" if match.group(1) else "image"
        found.setdefault(int(match.group(2)), {}).setdefault(match.group(3), {})[kind] = entry
    return found


def _tracked_paths(texture: Path, count: int) -> tuple[tuple[Path, Path], ...]:
    folder = texture / "tracked"
    vertex = sorted(folder.glob("vertex*.exr"))
    normal = sorted(folder.glob("normal*.exr"))
    for name, paths in (("vertex", vertex), ("normal", normal)):
        if len(paths) != count:
            raise ValueError(
                f"'{folder}' holds {len(paths)} {name}*.exr maps but the observations have {count} frames "
                "(partial download?)"
            )
    return tuple(zip(vertex, normal, strict=True))


def scan_session(path: str | Path) -> AuthorsSession:
    """Scan and check an authors' module folder (layout in the module docstring).

    Args:
        path: the module folder (``5_Static/90``), or its parent (``5_Static``).

    Raises:
        FileNotFoundError: the folder, an angle folder, a visibility map, a camera file or (static) the
            vertex/normal maps are missing, naming the file. ValueError: the cameras' or angles' frame
            lists differ (a partial download), no frame at all, or the dynamic tracked maps do not
            match the frame count.
    """
    root = _module_root(Path(path))
    texture = root / "texture"
    if not texture.is_dir():
        raise FileNotFoundError(f"'{texture}' does not exist: '{root}' is not an authors' session folder")
    for name in ("cameras.txt", "images.txt", "white_balance.txt"):
        if not (root / name).is_file():
            raise FileNotFoundError(f"'{root / name}' does not exist (partial download?)")
    reference: tuple[str, ...] | None = None
    where = ""
    paths: dict[tuple[int, int, int], tuple[Path, Path]] = {}
    for angle in AUTHORS_ANGLES:
        folder = texture / str(angle) / "exr"
        if not folder.is_dir():
            raise FileNotFoundError(f"angle folder '{folder}' does not exist (partial download?)")
        files = _angle_files(folder)
        for camera in AUTHORS_CAMERAS:
            frames = files.get(camera, {})
            names = tuple(sorted((n for n, kinds in frames.items() if "image" in kinds), key=int))
            if reference is None:
                if not names:
                    raise ValueError(f"'{folder}' holds no img{camera}_*.exr observation")
                reference, where = names, f"{folder}/img{camera}_*.exr"
            if names != reference:
                raise ValueError(
                    f"'{folder}' holds {len(names)} img{camera}_*.exr frames but '{where}' holds "
                    f"{len(reference)}{_first_difference(reference, names)} (partial download?)"
                )
            for index, name in enumerate(names):
                image = frames[name]["image"]
                visibility = frames[name].get("visibility")
                if visibility is None:
                    raise FileNotFoundError(
                        f"visibility map '{folder / ('visible_' + image.name)}' of '{image}' does not exist "
                        "(partial download?)"
                    )
                paths[(angle, camera, index)] = (image, visibility)
    assert reference is not None
    dynamic = (texture / "tracked").is_dir()
    if dynamic:
        tracked = _tracked_paths(texture, len(reference))
    else:
        tracked = ()
        for name in ("vertex.exr", "normal.exr"):
            if not (texture / name).is_file():
                raise FileNotFoundError(f"'{texture / name}' does not exist (partial download?)")
    return AuthorsSession(root, dynamic, reference, paths, tracked)


def _first_difference(expected: Sequence[str], got: Sequence[str]) -> str:
    missing = sorted(set(expected) - set(got), key=int)
    extra = sorted(set(got) - set(expected), key=int)
    if missing:
        return f"; frame {missing[0]} is missing"
    return f"; frame {extra[0]} is extra" if extra else ""


def _data_lines(path: Path) -> list[tuple[int, list[str]]]:
    """``(line number, tokens)`` of every line of ``path`` that is neither empty nor a ``#`` comment."""
    if not path.is_file():
        raise FileNotFoundError(f"'{path}' does not exist")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"'{path}' is not a text file ({exc})") from None
    lines = []
    for number, line in enumerate(text.splitlines(), start=1):
        tokens = line.split()
        if tokens and not tokens[0].startswith("#"):
            lines.append((number, tokens))
    return lines


def _first_line(path: Path, lines: dict[int, int], ident: int, number: int, what: str) -> None:
    """Refuse a second line for one ``ident`` (naming both lines); record the first."""
    if ident in lines:
        raise ValueError(f"'{path}' line {number}: {what} {ident} is listed again (line {lines[ident]})")
    lines[ident] = number


def read_colmap_cameras(path: str | Path) -> dict[int, ColmapCamera]:
    """``cameras.txt`` (COLMAP text: ``ID MODEL W H fx fy cx cy [k1 k2 p1 p2 ...]``): camera id -> camera.

    Raises:
        FileNotFoundError: missing. ValueError: naming the file and the line: a line that is not a
            pinhole/OpenCV camera, a size that is not positive, focal lengths that are not positive and
            finite, a principal point or distortion that is not finite, a camera listed twice.
    """
    path = Path(path)
    cameras: dict[int, ColmapCamera] = {}
    lines: dict[int, int] = {}
    for number, tokens in _data_lines(path):
        where = f"'{path}' line {number}"
        try:
            ident, model, width, height = int(tokens[0]), tokens[1], int(tokens[2]), int(tokens[3])
            params = [float(v) for v in tokens[4:]]
        except (ValueError, IndexError):
            raise ValueError(f"{where}: malformed camera line {' '.join(tokens)!r}; expected "
                             "'ID OPENCV WIDTH HEIGHT fx fy cx cy k1 k2 p1 p2'") from None
        _first_line(path, lines, ident, number, "camera")
        if model == "PINHOLE" and len(params) == 4:
            params += [0.0] * 4
        if model not in ("OPENCV", "PINHOLE") or len(params) != 8:
            raise ValueError(f"{where}: camera {ident} model {model} with {len(params)} parameters; "
                             "expected OPENCV (fx fy cx cy k1 k2 p1 p2)")
        if width <= 0 or height <= 0:
            raise ValueError(f"{where}: camera {ident} size {width} x {height} px must be positive")
        if not np.isfinite(params).all():
            raise ValueError(f"{where}: camera {ident} parameters must be finite; got {params}")
        fx, fy, cx, cy = params[:4]
        if fx <= 0 or fy <= 0:
            raise ValueError(f"{where}: camera {ident} focal lengths fx {fx}, fy {fy} must be positive")
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        cameras[ident] = ColmapCamera(width, height, K, tuple(params[4:]))
    return cameras


def _rotation_from_quaternion(qw: float, qx: float, qy: float, qz: float) -> np.ndarray:
    q = np.array([qw, qx, qy, qz], dtype=np.float64)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _quaternion_from_rotation(rotation: np.ndarray) -> np.ndarray:
    """Unit ``(w, x, y, z)`` of a proper rotation (Shepperd's method: the largest diagonal term first)."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = np.trace(m)
    candidates = [trace, m[0, 0], m[1, 1], m[2, 2]]
    k = int(np.argmax(candidates))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i, j, l = [(0, 1, 2), (1, 2, 0), (2, 0, 1)][k - 1]
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[l, l])
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (m[l, j] - m[j, l]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + l] = (m[l, i] + m[i, l]) / s
    q = np.asarray(q)
    return q / np.linalg.norm(q) * (1.0 if q[0] >= 0 else -1.0)


def read_colmap_images(path: str | Path) -> dict[int, np.ndarray]:
    """``images.txt`` (COLMAP text: ``ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` then a line of 2D points):
    image id -> ``(4, 4)`` float64 world -> camera (OpenCV axes, mm).

    Raises:
        FileNotFoundError: missing. ValueError: naming the file and the line: a malformed image line, a
            quaternion or translation that is not finite, a zero quaternion, an image listed twice.
    """
    path = Path(path)
    images: dict[int, np.ndarray] = {}
    lines: dict[int, int] = {}
    for number, tokens in _data_lines(path):
        image_like = len(tokens) >= 9 and tokens[0].isdigit() and tokens[8].isdigit()
        if len(tokens) % 3 == 0 and not image_like:
            continue  # a POINTS2D line (x y point3d_id triples)
        where = f"'{path}' line {number}"
        try:
            values = np.array([float(v) for v in tokens[1:8]])
            int(tokens[0]), int(tokens[8])
        except (ValueError, IndexError):
            raise ValueError(f"{where}: malformed image line {' '.join(tokens)!r}; expected "
                             "'ID QW QX QY QZ TX TY TZ CAMERA_ID NAME'") from None
        ident = int(tokens[0])
        _first_line(path, lines, ident, number, "image")
        if not np.isfinite(values).all():
            raise ValueError(f"{where}: image {ident} quaternion and translation must be finite; got "
                             f"{values.tolist()}")
        if np.linalg.norm(values[:4]) < 1e-12:
            raise ValueError(f"{where}: image {ident} has the zero quaternion (QW QX QY QZ all 0)")
        pose = np.eye(4)
        pose[:3, :3] = _rotation_from_quaternion(*values[:4])
        pose[:3, 3] = values[4:7]
        images[ident] = pose
    return images


def write_colmap_cameras(path: str | Path, cameras: Mapping[int, ColmapCamera]) -> Path:
    """Write ``cameras.txt`` (OPENCV model) atomically."""
    lines = ["# Camera list with one line of data per camera:",
             "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    for ident, camera in sorted(cameras.items()):
        K = np.asarray(camera.K, dtype=np.float64)
        distortion = (list(camera.distortion) + [0.0] * 4)[:4]
        params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *distortion]
        values = " ".join(repr(float(v)) for v in params)
        lines.append(f"{ident} OPENCV {camera.width} {camera.height} {values}")
    return _write_text(Path(path), lines)


def write_colmap_images(path: str | Path, world_to_camera: Mapping[int, np.ndarray]) -> Path:
    """Write ``images.txt`` (one image per camera, camera id = image id, empty 2D point lines)."""
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for ident, pose in sorted(world_to_camera.items()):
        pose = np.asarray(pose, dtype=np.float64)
        values = [*_quaternion_from_rotation(pose[:3, :3]), *pose[:3, 3]]
        lines.append(f"{ident} " + " ".join(repr(float(v)) for v in values) + f" {ident} cam{ident}.png")
        lines.append("")
    return _write_text(Path(path), lines)


def _write_text(path: Path, lines: Sequence[str]) -> Path:
    with atomic_path(path) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n")
    return path


def read_white_balance(path: str | Path, cameras: Sequence[int] = AUTHORS_CAMERAS) -> dict[int, np.ndarray]:
    """``white_balance.txt``: camera -> ``(3,)`` RGB gains (row ``camera - 1``, columns 1-3).

    Raises:
        FileNotFoundError: missing. ValueError: too few rows/columns or non-finite or negative gains.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"'{path}' does not exist")
    try:
        table = np.atleast_2d(np.loadtxt(path, dtype=np.float64))
    except ValueError as exc:
        raise ValueError(f"'{path}' is not a table of numbers: {exc}") from None
    if table.shape[0] < max(cameras) or table.shape[1] < 4:
        raise ValueError(f"'{path}': need a row [index, R, G, B] per camera {list(cameras)}; "
                         f"got shape {table.shape}")
    gains = {c: table[c - 1, 1:4].copy() for c in cameras}
    for camera, gain in gains.items():
        if not (np.isfinite(gain).all() and (gain > 0).all()):
            raise ValueError(f"'{path}': camera {camera} gains must be finite and positive; got {gain}")
    return gains


def read_icp_poses(folder: str | Path, count: int) -> np.ndarray:
    """The ``icp-pose/*.txt`` matrices (sorted by name) as ``(count, 4, 4)`` float64 frame -> reference.

    Raises:
        FileNotFoundError: the folder is missing. ValueError: not ``count`` files (naming the folder) or a
            file that is not a rigid 4x4 matrix (naming it).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"ICP pose folder '{folder}' does not exist (partial download?)")
    files = sorted(p for p in folder.iterdir() if p.suffix == ".txt")
    if len(files) != count:
        raise ValueError(f"'{folder}' holds {len(files)} pose files but the observations have {count} frames "
                         "(partial download?)")
    poses = []
    for path in files:
        try:
            matrix = np.loadtxt(path, dtype=np.float64).reshape(4, 4)
        except ValueError as exc:
            raise ValueError(f"ICP pose '{path}' is not a 4x4 matrix: {exc}") from None
        rotation = matrix[:3, :3]
        orthonormal = np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-4)
        if not (orthonormal and np.allclose(matrix[3], [0, 0, 0, 1])):
            raise ValueError(f"ICP pose '{path}' is not a rigid transform")
        poses.append(matrix)
    return np.stack(poses)
