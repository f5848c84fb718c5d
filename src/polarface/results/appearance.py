"""Everything needed to render a RESULT folder, read through :class:`~polarface.results.ResultFolder`."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from polarface.geometry.head_asset import head_placement
from polarface.io.storage import PathOrUrl, StoragePath, storage_path
from polarface.results import layout
from polarface.results.folder import ResultFolder

__all__ = ["ResultAppearance", "load_sog", "sog_shapes"]


def sog_shapes(payload: Mapping[str, Any]):
    """A ``sog.json`` payload as :class:`polarface.skin.heterogeneous.ProfileShapes` (float64, ``(L, 9)``)."""
    import torch

    from polarface.skin.heterogeneous import ProfileShapes

    layers = payload["layers"]
    return ProfileShapes(*(torch.tensor(layers[k], dtype=torch.float64) for k in layout.SOG_LAYERS))


def load_sog(path: PathOrUrl):
    """Read a ``sog.json`` file (a local path or a URL) back as
    :class:`polarface.skin.heterogeneous.ProfileShapes` (float64)."""
    import json

    return sog_shapes(json.loads(storage_path(path).read_text(encoding="utf-8")))


@dataclasses.dataclass(frozen=True, eq=False)
class ResultAppearance:
    """Everything needed to render a RESULT folder.

    Attributes:
        maps: name -> ``(H, W)`` float32 maps (polarimetric parameters, displacement in mm, chromophores).
        mask: ``(H, W)`` bool valid texels.
        mesh: rest mesh (model frame, mm, UVs).
        rig: the capture rig (cameras, lights, spectral calibration).
        shapes: SoG shapes (:class:`polarface.skin.heterogeneous.ProfileShapes`, ``(L, 9)``) or None
            (then fitted at the median texel).
        placement: ``(4, 4)`` float64 model -> rig-world transform at which the head faces the
            polarimetric module (:meth:`ResultFolder.rest_placement`; the renderer's default pose).
    """

    maps: dict[str, np.ndarray]
    mask: np.ndarray
    mesh: Any
    rig: Any
    shapes: Any
    placement: np.ndarray = dataclasses.field(default_factory=head_placement)

    @classmethod
    def load(cls, result_dir: PathOrUrl | ResultFolder) -> ResultAppearance:
        """Read maps, mask, ``mesh.obj``, ``rig.json`` and ``maps/sog.json`` of a RESULT folder.

        Raises:
            FileNotFoundError: the folder or a map is missing. ValueError: the rig has no spectral
            calibration, a map's shape is not the mask's, or ``maps/sog.json`` is malformed (naming it).
        """
        folder = result_dir if isinstance(result_dir, ResultFolder) else ResultFolder(result_dir)
        if not folder.root.is_dir():
            raise FileNotFoundError(f"result folder '{folder.root}' does not exist")
        rig = folder.read_rig()
        if rig.spectral is None:
            raise ValueError(f"'{folder.rig_path}' has no spectral calibration (needed to render spectra)")
        maps = {
            name: folder.read_scalar_map(name).astype(np.float32)
            for name in (*layout.POLARIMETRIC_MAPS, *layout.CHROMOPHORE_MAPS)
        }
        mask = folder.read_mask()
        for name, values in maps.items():
            if values.shape != mask.shape:
                raise ValueError(
                    f"'{folder.map_path(name)}' is {values.shape}, which does not match the mask "
                    f"'{folder.map_path(layout.MASK, '.png')}' {mask.shape}"
                )
        sog = folder.read_sog()
        shapes = _checked_sog_shapes(sog, folder.map_path("sog", ".json")) if sog is not None else None
        return cls(maps, mask, folder.read_mesh(), rig, shapes, folder.rest_placement())


def _checked_sog_shapes(payload: Any, path: StoragePath):
    """:func:`sog_shapes` of a ``sog.json`` payload; ValueError naming ``path`` when it is malformed."""
    layers = payload.get("layers") if isinstance(payload, dict) else None
    missing = [k for k in layout.SOG_LAYERS if not isinstance(layers, dict) or k not in layers]
    if missing:
        raise ValueError(f"'{path}': 'layers' lacks {missing} (expected {list(layout.SOG_LAYERS)})")
    try:
        shapes = sog_shapes(payload)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"'{path}': 'layers' must hold (L, 9) numeric arrays ({exc})") from None
    for name in layout.SOG_LAYERS:
        values = getattr(shapes, name)
        if values.ndim != 2 or values.shape != shapes.r_out_f.shape or not values.isfinite().all():
            raise ValueError(f"'{path}': layer {name!r} must be a finite (L, 9) array like 'r_out_f'")
    return shapes
