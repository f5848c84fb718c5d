"""The export formats, one registry (in the manner of colour-science's ``*_METHODS``).

Each :class:`ExportFormat` names the maps it needs (checked by :meth:`ExportSource.require` before
anything is written) and its writer, imported only when the format is used (Mitsuba, USD and glTF
writers pull in nothing heavy at ``import polarface``). What each format maps onto what, and what is
lost: ``docs/export.md``.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from polarface.export.source import ExportSource
from polarface.results import layout

__all__ = ["EXPORT_FORMATS", "ExportFormat", "ExportOptions", "export_format"]

_POLARIMETRIC = (*layout.POLARIMETRIC_MAPS, layout.RHO_SSS_BAR, layout.MASK)


@dataclasses.dataclass(frozen=True)
class ExportOptions:
    """Settings of ``polarface export`` (defaults: every format's documented default).

    Attributes:
        formats: format names of :data:`EXPORT_FORMATS`, written in this order.
        frames: dynamic frame selection (``"0-4,7"``; None: every frame with maps).
        kernel_clusters: texel clusters (k-means on the chromophores) of the ``kernels`` format.
    """

    formats: tuple[str, ...] = ("mitsuba", "gltf", "usd", "kernels")
    frames: str | None = None
    kernel_clusters: int = 8

    def __post_init__(self) -> None:
        if not self.formats:
            raise ValueError("argument 'formats': give at least one format")
        unknown = [f for f in self.formats if f not in EXPORT_FORMATS]
        if unknown:
            raise ValueError(f"argument 'formats': unknown {unknown}; choose from {sorted(EXPORT_FORMATS)}")
        if int(self.kernel_clusters) < 1:
            raise ValueError(f"argument 'kernel_clusters' must be >= 1; got {self.kernel_clusters}")


@dataclasses.dataclass(frozen=True)
class ExportFormat:
    """One export format.

    Attributes:
        name: the ``--format`` name; also the sub-folder of the export folder it writes.
        description: one line for ``--help`` and ``export.json``.
        maps: the RESULT maps it needs (``maps/<name>.exr``; ``mask`` is ``maps/mask.png``, ``sog`` is
            ``maps/sog.json``), for the static result and for every exported dynamic frame when
            ``frames`` is set.
        frames: whether it exports the dynamic frames too (their maps are then required as well; every
            writer gets the same source, whose ``frames`` a static format ignores).
        writer: ``"module:function"``; the function is ``(source, out, options) -> record`` where ``out``
            is the format's (empty, local) folder and ``record`` a JSON-able dict with ``files`` (paths
            relative to ``out``) and any notes.
    """

    name: str
    description: str
    maps: tuple[str, ...]
    frames: bool
    writer: str

    def load_writer(self) -> Callable[[ExportSource, Path, ExportOptions], dict[str, Any]]:
        """The writer function (imported now)."""
        module, function = self.writer.split(":")
        return getattr(importlib.import_module(module), function)


#: Export formats by name, in the order ``polarface export`` writes them.
EXPORT_FORMATS: dict[str, ExportFormat] = {
    "mitsuba": ExportFormat(
        "mitsuba",
        "Mitsuba 3 scene (XML + PLY + EXR textures) of the static result with the rig's cameras and "
        "polarized lights",
        _POLARIMETRIC,
        frames=False,
        writer="polarface.export.mitsuba:write_mitsuba_scene",
    ),
    "gltf": ExportFormat(
        "gltf",
        "glTF 2.0 binary (.glb) of the static result with a PBR material (KHR_materials_specular, "
        "KHR_materials_ior) and an offline 3D viewer page",
        ("eta", "alpha_s", "rho_s", "displacement_mm", layout.RHO_SSS_BAR, layout.MASK),
        frames=False,
        writer="polarface.export.gltf:write_gltf",
    ),
    "usd": ExportFormat(
        "usd",
        "USD stage of the static result and the dynamic sequence (time-sampled points, UVs, "
        "UsdPreviewSurface, per-frame textures)",
        (*_POLARIMETRIC, "c_h_out"),
        frames=True,
        writer="polarface.export.usd:write_usd",
    ),
    "kernels": ExportFormat(
        "kernels",
        "sum-of-Gaussians diffusion kernels per texel cluster and channel (JSON + NPZ) for real-time "
        "separable subsurface scattering",
        (*layout.CHROMOPHORE_MAPS, layout.MASK, "sog"),
        frames=False,
        writer="polarface.export.kernels:write_kernels",
    ),
    "authors-layout": ExportFormat(
        "authors-layout",
        "the RESULT's unwrapped observations and geometry in the layout of the authors' face sessions "
        "(texture-space EXR per polarizer angle and camera, COLMAP cameras, ICP poses); not a default format",
        (),
        frames=True,
        writer="polarface.export.authors_layout:write_authors_layout",
    ),
}


def export_format(name: str) -> ExportFormat:
    """The format ``name`` of :data:`EXPORT_FORMATS`.

    Raises:
        ValueError: an unknown name (listing the known ones).
    """
    if name not in EXPORT_FORMATS:
        raise ValueError(f"unknown export format '{name}'; choose from {sorted(EXPORT_FORMATS)}")
    return EXPORT_FORMATS[name]
