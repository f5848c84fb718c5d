"""What an exporter reads from a RESULT folder: maps (checked, named when missing), mesh, rig, frames.

Every exporter goes through :class:`ExportSource`, so a RESULT that lacks a map a format needs is refused
with one error naming the missing file before anything is written (:meth:`ExportSource.require`), and one
whose map, mesh, rig or ``sog.json`` cannot be read (truncated, NaN in ``rig.json``, corrupt JSON) with
one error naming that file, also before anything is written (:meth:`ExportSource.load`: what it reads
stays cached for the writers).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from polarface.io.named_reads import named_read
from polarface.io.storage import PathOrUrl
from polarface.results import ResultFolder, layout

__all__ = ["ExportSource", "MissingMapError"]


class MissingMapError(FileNotFoundError):
    """A RESULT lacks a map (or file) that an export format needs; the message names the file and format."""


@dataclasses.dataclass(frozen=True, eq=False)
class ExportSource:
    """A RESULT folder as the exporters read it (maps cached once read).

    Attributes:
        folder: the RESULT (or, from :meth:`frame`, one ``frames/NNNN`` folder of it).
        frames: the dynamic frames to export (indices of ``frames/NNNN`` holding maps), ascending; empty
            for a static result or a per-frame source.
    """

    folder: ResultFolder
    frames: tuple[int, ...] = ()

    @classmethod
    def open(cls, result: PathOrUrl | ResultFolder, frames: Sequence[int] | None = None) -> ExportSource:
        """The RESULT at ``result`` with the dynamic ``frames`` (default: every frame whose folder holds
        ``maps/mask.png``).

        Raises:
            FileNotFoundError: the folder or its ``result.json`` does not exist.
            ValueError: a requested frame has no folder with maps (naming it).
        """
        folder = result if isinstance(result, ResultFolder) else ResultFolder(result)
        if not (folder.root / layout.RESULT_JSON).is_file():
            raise FileNotFoundError(f"'{folder.root}' is not a RESULT folder (no {layout.RESULT_JSON})")
        present = [f for f in folder.frame_indices() if folder.frame(f).has_map(layout.MASK, ".png")]
        if frames is None:
            chosen = present
        else:
            missing = sorted(set(frames) - set(present))
            if missing:
                raise ValueError(
                    f"argument 'frames': {missing} have no maps under '{folder.root / layout.FRAMES_DIR}' "
                    f"(frames with maps: {present})"
                )
            chosen = sorted(set(frames))
        return cls(folder, tuple(chosen))

    @functools.cache  # noqa: B019 (one source per export: the formats share each frame's reads)
    def frame(self, index: int) -> ExportSource:
        """The source of one dynamic frame (``frames/NNNN``: its maps and tracked ``mesh.obj``), the same
        object on every call, so its maps and mesh are read once for all formats."""
        return ExportSource(self.folder.frame(index))

    # ---- checks ------------------------------------------------------------------------------
    def map_file(self, name: str) -> Any:
        """The file of map ``name`` (``maps/<name>.exr``; the mask and other PNGs ``maps/<name>.png``;
        ``sog`` is ``maps/sog.json``)."""
        if name == layout.MASK or name == layout.IN_GAMUT:
            return self.folder.map_path(name, ".png")
        if name == "sog":
            return self.folder.map_path(name, ".json")
        return self.folder.map_path(name)

    def require(self, names: Iterable[str], format_name: str, *, frames: bool = True) -> None:
        """Refuse, naming every missing file, a source without the maps ``names`` (and ``mesh.obj`` and
        ``rig.json``) that ``format_name`` needs; with ``frames``, the same for each of :attr:`frames`.

        Raises:
            MissingMapError: a map or file is missing.
        """
        names = tuple(names)
        sources = [self, *(self.frame(f) for f in self.frames if frames)]
        missing = []
        for source in sources:
            files = [source.map_file(n) for n in names]
            files += [source.folder.mesh_path, source.folder.rig_path]
            missing += [str(p) for p in files if not p.is_file()]
        if missing:
            listed = ", ".join(f"'{p}'" for p in dict.fromkeys(missing))
            raise MissingMapError(
                f"export format '{format_name}' needs {listed}, which the RESULT '{self.folder.root}' lacks "
                "(run the stage that writes it first: docs/result_folder.md)"
            )

    def load(self, names: Iterable[str], *, frames: bool = True) -> None:
        """Read (and cache) the maps ``names``, the mesh and the rig of this source and, with ``frames``,
        of each of :attr:`frames`, so that a file that cannot be read fails before the writers start.

        Raises:
            ValueError, OSError: a file cannot be read (naming it).
        """
        names = tuple(names)
        for source in [self, *(self.frame(f) for f in self.frames if frames)]:
            source.rig  # noqa: B018 - read for the check, cached for the writers
            source.mesh  # noqa: B018
            for name in names:
                if name in (layout.MASK, layout.IN_GAMUT):
                    named_read(source.map_file(name), lambda s=source, n=name: s.folder.read_mask(name=n))
                elif name == "sog":
                    source.sog  # noqa: B018
                elif name == layout.RHO_SSS_BAR:
                    source.channel_map(name)
                else:
                    source.scalar_map(name)

    # ---- data --------------------------------------------------------------------------------
    @functools.cached_property
    def channel_names(self) -> list[str]:
        """The six spectral channel names (``result.json`` of the sequence)."""
        root = self.folder.sequence or self.folder
        return root.channel_names()

    @functools.cache  # noqa: B019 (one source per export; the cache lives as long as it)
    def scalar_map(self, name: str) -> np.ndarray:
        """``maps/<name>.exr`` channel ``Y``: ``(H, W)`` float32."""
        return self.folder.read_scalar_map(name)

    @functools.cache  # noqa: B019
    def channel_map(self, name: str) -> np.ndarray:
        """``maps/<name>.exr``: ``(H, W, 6)`` float32, channels in :attr:`channel_names` order."""
        return self.folder.read_channel_map(name, self.channel_names)

    @functools.cached_property
    def mask(self) -> np.ndarray:
        """``(H, W)`` bool valid texels (``maps/mask.png``)."""
        return self.folder.read_mask()

    @functools.cached_property
    def mesh(self):
        """:class:`polarface.geometry.TriangleMesh` of ``mesh.obj`` (model frame, mm, UVs; a frame's own
        tracked mesh for a per-frame source). Raises ValueError naming the file when it cannot be read."""
        return self.folder.read_mesh()

    @functools.cached_property
    def rig(self):
        """:class:`polarface.capture.Rig` of ``rig.json``."""
        return named_read(self.folder.rig_path, self.folder.read_rig)

    @functools.cached_property
    def sog(self) -> dict[str, Any] | None:
        """``maps/sog.json`` (the biophysical stage's sum-of-Gaussians shapes) or None."""
        return named_read(self.map_file("sog"), self.folder.read_sog)

    def timestamp_s(self, frame: int) -> float:
        """The capture time of dynamic ``frame`` (s; ``stages.dynamic.timestamps_s``), else the frame index
        at 30 frames per second."""
        record = self.folder.stage_record("dynamic") if self.folder.sequence is None else {}
        stamps = record.get("timestamps_s") or {}
        return float(stamps.get(str(frame), frame / 30.0))
