"""Re-rendering of one view in texture space from parameter maps (residuals, held-out evaluation, the
report's DoP/AoLP validation).

Maps follow ``SIM/ground_truth/maps`` conventions: ``eta, alpha_s, alpha_ss, rho_s, rho_ss,
displacement_mm`` as ``(Ht, Wt)`` float32 and ``rho_sss_bar`` as ``(Ht, Wt, 6)``.
"""

from __future__ import annotations

import numpy as np
import torch

from polarface.geometry.heights import normals_from_heights
from polarface.inverse.polarimetric.config import PARAMETER_NAMES
from polarface.inverse.polarimetric.model import render_samples
from polarface.inverse.polarimetric.problem import build_patch_samples
from polarface.texture import UnwrapStore

__all__ = ["render_view_texture", "shading_normals"]


def shading_normals(unwrap: UnwrapStore, displacement_mm: np.ndarray) -> np.ndarray:
    """``(Ht, Wt, 3)`` float32 unit normals (model frame) of the base mesh displaced by
    ``displacement_mm`` ``(Ht, Wt)`` (mm)."""
    geometry = unwrap.geometry()
    if displacement_mm.shape != geometry.mask.shape:
        raise ValueError(
            f"argument 'displacement_mm' must have shape {geometry.mask.shape}; got {displacement_mm.shape}"
        )
    t = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float64))  # noqa: E731
    with torch.no_grad():
        normal = normals_from_heights(
            t(displacement_mm),
            t(geometry.tangent_u),
            t(geometry.tangent_v),
            t(geometry.normal),
            t(geometry.texel_size_u),
            t(geometry.texel_size_v),
            torch.from_numpy(geometry.mask),
        )
    return normal.numpy().astype(np.float32)


def render_view_texture(
    unwrap: UnwrapStore,
    maps: dict[str, np.ndarray],
    view_index: int,
    *,
    normal: np.ndarray | None = None,
    patch: int = 128,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observed and re-rendered observations of one view on the texture.

    Args:
        unwrap: the unwrapped capture; maps: parameter maps (module docstring); view_index: view to render;
        normal: optional precomputed :func:`shading_normals`; patch: texels per side processed at once.

    Returns:
        ``observed (Ht, Wt, 3, 3)``, ``predicted (Ht, Wt, 3, 3)`` (``[I_sss, I_zeta, I_s]`` x the view's
        channels; zero where not visible) and ``valid (Ht, Wt)`` bool.
    """
    views = unwrap.views
    if not 0 <= view_index < len(views):
        raise ValueError(f"argument 'view_index' must be in [0, {len(views)}); got {view_index}")
    for name in PARAMETER_NAMES:
        if name not in maps:
            raise ValueError(f"argument 'maps' lacks '{name}'")
    height, width = unwrap.resolution
    normal = shading_normals(unwrap, maps["displacement_mm"]) if normal is None else normal
    observed = np.zeros((height, width, 3, 3), np.float32)
    predicted = np.zeros_like(observed)
    valid = np.zeros((height, width), bool)
    for rows, cols in unwrap.patches(patch):
        batch, geometry = build_patch_samples(unwrap, rows, cols, [view_index], views, dtype=torch.float64)
        if batch is None:
            continue
        w = geometry.mask.shape[1]
        texel = batch.texel.numpy()
        r, c = texel // w + rows.start, texel % w + cols.start
        t = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float64))  # noqa: E731
        with torch.no_grad():
            prediction = render_samples(
                batch,
                t(normal[r, c]),
                t(np.maximum(maps["eta"][r, c], 1.0 + 1e-6)),
                t(np.maximum(maps["alpha_s"][r, c], 1e-3)),
                t(np.maximum(maps["alpha_ss"][r, c], 1e-3)),
                t(maps["rho_s"][r, c]),
                t(maps["rho_ss"][r, c]),
                t(np.take_along_axis(maps["rho_sss_bar"][r, c], batch.channels.numpy(), axis=1)),
            )
        predicted[r, c] = torch.stack([prediction.i_sss, prediction.i_zeta, prediction.i_s], dim=1).numpy()
        observed[r, c] = batch.observed.numpy()
        valid[r, c] = True
    return observed, predicted, valid
