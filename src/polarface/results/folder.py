"""``ResultFolder``: the one reader and writer of a RESULT folder (layout: ``docs/result_folder.md``).

Every stage, the evaluation, the report and the renderer go through this class: it knows where each
map lives (names in :mod:`polarface.results.layout`), reads and writes maps atomically through
:mod:`polarface.io`, and owns ``result.json`` (format keys, stage records). A dynamic sequence keeps
one sub-folder per frame (``frames/NNNN/``), reached with :meth:`ResultFolder.frame`, which has the
same API; shared inputs (``rig.json``, ``mesh.obj``) are read from the sequence root.

The root is a local path or an fsspec URL (``file://``, ``memory://``, ``s3://bucket/key``;
:func:`polarface.io.storage.storage_path`). Every path property is then a
:class:`~polarface.io.storage.UrlPath` and every write goes through :mod:`polarface.io`, which puts each
finished file whole under its key (the writers stage it in a local temporary file), so readers on
other machines never see half a map.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from polarface.io import (
    atomic_path,
    colormap_png,
    read_exr,
    read_json_object,
    read_png,
    write_exr,
    write_json_atomic,
    write_png,
)
from polarface.io.storage import PathOrUrl, StoragePath, local_copy, storage_path
from polarface.results import layout
from polarface.results.header import check_result_header

__all__ = ["ResultFolder"]


def _check_polarimetric_maps(maps: Mapping[str, np.ndarray], mask: np.ndarray) -> None:
    required = (*layout.POLARIMETRIC_MAPS, layout.RHO_SSS_BAR)
    missing = [name for name in required if name not in maps]
    if missing:
        raise ValueError(f"argument 'maps' lacks {missing}; the polarimetric stage writes {list(required)}")
    wrong = {n: np.shape(maps[n]) for n in required if np.shape(maps[n])[:2] != np.shape(mask)}
    if wrong:
        raise ValueError(f"argument 'maps': shapes {wrong} do not match the mask's {np.shape(mask)}")


def _under_root(name: str) -> property:
    """A read-only property of a :class:`ResultFolder`: the path ``root / name``."""
    return property(lambda folder: folder.root / name, doc=f"``root / {name!r}``")


class ResultFolder:
    """A RESULT folder rooted at ``root`` (need not exist yet; writers create sub-folders).

    Args:
        root: the folder (``RESULT`` or, for a frame, ``RESULT/frames/NNNN``): a local path or a URL.
        sequence: the enclosing RESULT of a per-frame folder (None for a top-level one).

    Raises:
        ValueError: ``root`` is a URL of an unknown protocol or one whose package is missing.
    """

    def __init__(self, root: PathOrUrl, *, sequence: ResultFolder | None = None) -> None:
        self.root: StoragePath = storage_path(root)
        self.sequence = sequence

    def __repr__(self) -> str:
        return f"ResultFolder('{self.root}')"

    # ---- paths -------------------------------------------------------------------------------
    maps_dir = _under_root(layout.MAPS_DIR)
    previews_dir = _under_root(layout.PREVIEWS_DIR)
    checkpoints_dir = _under_root(layout.CHECKPOINTS_DIR)
    exports_dir = _under_root(layout.EXPORTS_DIR)
    geometry_dir = _under_root(layout.GEOMETRY_DIR)
    tracking_dir = _under_root(layout.TRACKING_DIR)
    result_json_path = _under_root(layout.RESULT_JSON)
    unwrap_path = _under_root(layout.UNWRAP_STORE)
    report_path = _under_root(layout.REPORT_HTML)
    #: ``poses.json``: the copy of given poses (a RESULT of stereo geometry has ``geometry/poses.json``).
    poses_path = _under_root(layout.POSES_JSON)

    @property
    def rig_path(self) -> StoragePath:
        """``rig.json`` of the sequence root (a frame folder shares its sequence's rig)."""
        return (self.sequence or self).root / layout.RIG_JSON

    @property
    def mesh_path(self) -> StoragePath:
        """``mesh.obj``: the frame's own mesh when it has one, else the sequence's rest mesh."""
        own = self.root / layout.MESH_OBJ
        return own if self.sequence is None or own.is_file() else self.sequence.root / layout.MESH_OBJ

    def map_path(self, name: str, suffix: str = ".exr") -> StoragePath:
        """``maps/<name><suffix>``."""
        return self.maps_dir / f"{name}{suffix}"

    def preview_path(self, name: str) -> StoragePath:
        """``previews/<name>.png``."""
        return self.previews_dir / f"{name}.png"

    def has_map(self, name: str, suffix: str = ".exr") -> bool:
        return self.map_path(name, suffix).is_file()

    # ---- result.json -------------------------------------------------------------------------
    def read_result(self) -> dict[str, Any]:
        """``result.json`` as a dict (empty when the file does not exist yet).

        Raises:
            ValueError: the file is not valid JSON or not an object, or a format key (``format``,
                ``version``, ``channel_names``, ``texture_resolution``, ``stages``) is malformed
                (naming the file and the key).
        """
        path = self.result_json_path
        if not path.exists():
            return {}
        data = read_json_object(path)
        check_result_header(path, data)
        return data

    def update_result(
        self,
        values: Mapping[str, Any] | None = None,
        *,
        defaults: Mapping[str, Any] | None = None,
        stage: str | None = None,
        record: Mapping[str, Any] | None = None,
    ) -> dict[str, Any]:
        """Read, update and atomically rewrite ``result.json``; returns the new content.

        Args:
            values: top-level keys set (overwritten).
            defaults: top-level keys set only where missing.
            stage: a stage name; ``record`` replaces ``stages[stage]`` (``stages`` is always present).
        """
        data = self.read_result()
        data.update(values or {})
        for key, value in (defaults or {}).items():
            data.setdefault(key, value)
        stages = data.setdefault("stages", {})
        if stage is not None:
            stages[stage] = dict(record or {})
        write_json_atomic(self.result_json_path, data)
        return data

    def write_result_header(self, channel_names: Sequence[str], texture_resolution: Sequence[int],
                            texel_size_mm: float) -> dict[str, Any]:
        """Set ``format``, ``version``, ``channel_names``, ``texture_resolution`` and ``texel_size_mm``."""
        return self.update_result(
            {
                "format": layout.RESULT_FORMAT,
                "version": layout.RESULT_VERSION,
                "channel_names": list(channel_names),
                "texture_resolution": list(texture_resolution),
                "texel_size_mm": texel_size_mm,
            }
        )

    def stage_record(self, stage: str) -> dict[str, Any]:
        """``stages[stage]`` of ``result.json`` (empty when the stage has not run)."""
        return self.read_result().get("stages", {}).get(stage, {})

    def stage_complete(self, stage: str) -> bool:
        """Whether ``result.json`` records ``stage`` as complete."""
        return bool(self.stage_record(stage).get("complete", False))

    def record_stage(self, stage: str, record: Mapping[str, Any]) -> dict[str, Any]:
        """Store ``record`` with ``complete: true`` as ``stages[stage]``."""
        return self.update_result(stage=stage, record={**record, "complete": True})

    def channel_names(self) -> list[str]:
        """``result.json``'s ``channel_names`` (``channel0``... when it records none)."""
        return self.read_result().get("channel_names") or layout.default_channel_names()

    # ---- maps --------------------------------------------------------------------------------
    def read_scalar_map(self, name: str) -> np.ndarray:
        """``maps/<name>.exr`` channel ``Y`` as ``(H, W)`` float32.

        Raises:
            FileNotFoundError: the map does not exist. ValueError: it has no ``Y`` channel.
        """
        path = self.map_path(name)
        if not path.is_file():
            raise FileNotFoundError(f"'{path}' does not exist (run the reconstruction stages first)")
        channels = read_exr(path)
        if "Y" not in channels:
            raise ValueError(f"'{path}' has no channel 'Y' (channels {sorted(channels)})")
        return channels["Y"]

    def write_scalar_map(self, name: str, values: np.ndarray) -> StoragePath:
        """Write ``(H, W)`` ``values`` as ``maps/<name>.exr`` channel ``Y`` (float32)."""
        return write_exr(self.map_path(name), {"Y": values})

    def read_channel_map(self, name: str, channel_names: Sequence[str], *, strict: bool = True) -> np.ndarray:
        """``maps/<name>.exr`` as ``(H, W, C)`` float32, channels in ``channel_names`` order.

        With ``strict=False`` a file lacking one of the names is read in sorted channel order.

        Raises:
            FileNotFoundError: the map does not exist. ValueError (strict): a channel is missing.
        """
        path = self.map_path(name)
        if not path.is_file():
            raise FileNotFoundError(f"'{path}' does not exist (run the polarimetric stage first)")
        channels = read_exr(path)
        names = list(channel_names)
        missing = [n for n in names if n not in channels]
        if missing and strict:
            raise ValueError(f"'{path}' lacks channel(s) {missing} of the rig's calibration {names}")
        if missing or not names:
            names = sorted(channels)
        return np.stack([channels[n] for n in names], axis=-1)

    def write_channel_map(self, name: str, values: np.ndarray, channel_names: Sequence[str]) -> StoragePath:
        """Write ``(H, W, C)`` ``values`` as ``maps/<name>.exr`` with one named channel per slice."""
        return write_exr(self.map_path(name), {n: values[..., i] for i, n in enumerate(channel_names)})

    def read_mask(self, shape: tuple[int, int] | None = None, name: str = layout.MASK) -> np.ndarray:
        """``maps/<name>.png`` as ``(H, W)`` bool (grey > 127, or > 0.5 for a float image).

        Raises:
            FileNotFoundError: the file does not exist. ValueError: its shape is not ``shape``.
        """
        path = self.map_path(name, ".png")
        if not path.is_file():
            raise FileNotFoundError(f"mask '{path}' does not exist")
        mask = read_png(path)
        mask = mask[..., 0] if mask.ndim == 3 else mask
        if shape is not None and mask.shape != tuple(shape):
            raise ValueError(f"mask '{path}' is {mask.shape}, expected {tuple(shape)}")
        return mask > (0.5 if mask.dtype.kind == "f" else 127)

    def write_mask(self, mask: np.ndarray, name: str = layout.MASK) -> StoragePath:
        """Write ``(H, W)`` bool ``mask`` as ``maps/<name>.png`` (8-bit, 255 = True)."""
        return write_png(self.map_path(name, ".png"), mask.astype(np.uint8) * 255)

    def read_maps(self, channel_names: Sequence[str] | None = None) -> dict[str, np.ndarray]:
        """The polarimetric maps present in ``maps/`` as float64.

        Returns:
            ``POLARIMETRIC_MAPS`` ``(H, W)``, ``rho_sss_bar`` ``(H, W, C)`` (``channel_names`` order, or
            sorted channel names when the file lacks one) and ``mask`` ``(H, W)`` bool; absent files are
            left out.
        """
        out: dict[str, np.ndarray] = {}
        for name in layout.POLARIMETRIC_MAPS:
            if self.has_map(name):
                out[name] = np.asarray(read_exr(self.map_path(name))["Y"], dtype=np.float64)
        if self.has_map(layout.RHO_SSS_BAR):
            rho = self.read_channel_map(layout.RHO_SSS_BAR, channel_names or [], strict=False)
            out[layout.RHO_SSS_BAR] = rho.astype(np.float64)
        if self.has_map(layout.MASK, ".png"):
            out[layout.MASK] = self.read_mask()
        return out

    def write_polarimetric_maps(
        self,
        maps: Mapping[str, np.ndarray],
        mask: np.ndarray,
        diagnostics: Mapping[str, np.ndarray] | None = None,
    ) -> None:
        """Write the polarimetric stage's maps, mask and previews (see ``docs/result_folder.md``).

        Args:
            maps: ``POLARIMETRIC_MAPS`` ``(H, W)`` and ``rho_sss_bar`` ``(H, W, 6)`` (result.json's
                channel order).
            mask: ``(H, W)`` bool valid texels.
            diagnostics: ``(H, W)`` maps named in ``DIAGNOSTIC_MAPS`` (e.g. ``view_count``, fitting views
                per texel), or None.

        Raises:
            ValueError: a map is missing, a diagnostic map is not registered, or a shape does not match
                the mask (nothing is written).
        """
        _check_polarimetric_maps(maps, mask)
        diagnostics = dict(diagnostics or {})
        for name, values in diagnostics.items():
            if name not in layout.DIAGNOSTIC_MAPS:
                known = sorted(layout.DIAGNOSTIC_MAPS)
                raise ValueError(f"diagnostic map '{name}' is not registered in DIAGNOSTIC_MAPS {known}")
            if np.shape(values) != mask.shape:
                shape = np.shape(values)
                raise ValueError(f"diagnostic map '{name}' has shape {shape}; expected {mask.shape}")
        for name in layout.POLARIMETRIC_MAPS:
            self.write_scalar_map(name, maps[name].astype(np.float32))
            self._write_map_preview(name, maps[name], mask)
        rho = maps[layout.RHO_SSS_BAR].astype(np.float32)
        self.write_channel_map(layout.RHO_SSS_BAR, rho, self.channel_names())
        self.write_mask(mask)
        for name, values in diagnostics.items():
            self._write_diagnostic_map(name, np.asarray(values), mask)
        upper = rho[..., :3] if rho.shape[-1] >= 3 else np.repeat(rho[..., :1], 3, -1)
        scale = max(float(np.percentile(upper[mask], 99.5)) if mask.any() else 1.0, 1e-6)
        preview = np.clip(upper / scale, 0, 1)
        shown = np.where(mask[..., None], preview, 0.0).astype(np.float64)
        write_png(self.preview_path("rho_sss_bar_rgb"), shown)

    def _write_diagnostic_map(self, name: str, values: np.ndarray, mask: np.ndarray) -> None:
        """``maps/<name>.exr`` and its preview, scaled from the entry's ``vmin`` to the map's maximum."""
        spec = layout.DIAGNOSTIC_MAPS[name]
        self.write_scalar_map(name, values.astype(np.float32))
        shown = values > 0 if spec.shown == "positive" else mask
        colormap_png(
            self.preview_path(name),
            np.where(shown, values, np.nan).astype(np.float64),
            vmin=spec.vmin,
            vmax=float(max(values.max(), spec.vmin + 1)),
            mask=shown,
            title=spec.title,
            colorbar=True,
        )

    def _write_map_preview(self, name: str, values: np.ndarray, mask: np.ndarray) -> None:
        """Colour-mapped preview over the 1st..99th percentile of the masked values."""
        inside = values[mask]
        vmin, vmax = (
            (float(np.percentile(inside, 1)), float(np.percentile(inside, 99))) if inside.size else (0, 1)
        )
        colormap_png(
            self.preview_path(name),
            np.where(mask, values, np.nan),
            vmin=vmin,
            vmax=vmax if vmax > vmin else vmin + 1e-6,
            mask=mask,
            title=name,
            colorbar=True,
        )

    # ---- other artifacts ---------------------------------------------------------------------
    @property
    def loss_curve_path(self) -> StoragePath:
        return self.checkpoints_dir / "loss_curve.npy"

    def write_loss_curve(self, curve: Sequence[float]) -> StoragePath:
        """``checkpoints/loss_curve.npy``: mean total loss per iteration (float64), atomically."""
        with atomic_path(self.loss_curve_path) as tmp:
            np.save(tmp, np.asarray(curve))
        return self.loss_curve_path

    def read_loss_curve(self) -> np.ndarray | None:
        """The loss curve, or None when it was not written."""
        if not self.loss_curve_path.exists():
            return None
        with local_copy(self.loss_curve_path) as local:
            return np.load(local)

    def read_sog(self) -> dict[str, Any] | None:
        """``maps/sog.json`` as a dict, or None when absent.

        Raises:
            ValueError: the file is not valid JSON or not an object (naming the file).
        """
        path = self.map_path("sog", ".json")
        if not path.is_file():
            return None
        return read_json_object(path)

    def write_sog(self, payload: Mapping[str, Any]) -> StoragePath:
        """Write ``maps/sog.json`` (keys in ``docs/result_folder.md``)."""
        return write_json_atomic(self.map_path("sog", ".json"), dict(payload))

    def read_rig(self):
        """The capture rig of ``rig.json`` (:class:`polarface.capture.rig.Rig`)."""
        from polarface.capture.rig import Rig

        return Rig.load(self.rig_path)

    def read_mesh(self):
        """The mesh of :attr:`mesh_path` (model frame, mm, with UVs).

        Raises:
            FileNotFoundError: it does not exist.
        """
        from polarface.geometry.mesh import load_mesh

        if not self.mesh_path.is_file():
            raise FileNotFoundError(f"'{self.mesh_path}' does not exist")
        return load_mesh(self.mesh_path)

    def write_mesh(self, mesh) -> StoragePath:
        """Write ``mesh.obj`` (model frame, mm, UVs)."""
        from polarface.geometry.mesh import save_obj

        return save_obj(self.root / layout.MESH_OBJ, mesh)

    def stereo_geometry(self) -> bool:
        """Whether the mesh came from the stereo geometry stage (``stages.prepare.geometry`` of the
        sequence's ``result.json`` is set): its model frame is then the rig world of the reference frame
        (y down, the face towards -z; ``docs/geometry.md``), not the bundled head's frame."""
        root = self.sequence or self
        return bool(root.stage_record("prepare").get("geometry"))

    def rest_placement(self) -> np.ndarray:
        """``(4, 4)`` float64 model -> rig-world transform at which the RESULT's head faces the polarimetric
        module: identity for stereo geometry (:meth:`stereo_geometry`), else the simulator's rest placement
        of the bundled head (:func:`polarface.geometry.head_asset.head_placement`)."""
        from polarface.geometry.head_asset import head_placement

        return np.eye(4) if self.stereo_geometry() else head_placement()

    # ---- dynamic sequences -------------------------------------------------------------------
    def frame(self, index: int) -> ResultFolder:
        """The per-frame folder ``frames/NNNN`` (same API; rig and rest mesh shared with this one)."""
        if isinstance(index, bool) or not isinstance(index, int | np.integer) or index < 0:
            raise ValueError(f"argument 'index' must be an integer >= 0; got {index!r}")
        if self.sequence is not None:
            raise ValueError(f"'{self.root}' is already a per-frame folder; frames do not nest")
        return ResultFolder(self.root / layout.FRAMES_DIR / f"{int(index):04d}", sequence=self)

    def frame_indices(self) -> list[int]:
        """Indices of the per-frame folders present, ascending."""
        frames = self.root / layout.FRAMES_DIR
        if not frames.is_dir():
            return []
        return sorted(int(p.name) for p in frames.iterdir() if p.is_dir() and p.name.isdigit())
