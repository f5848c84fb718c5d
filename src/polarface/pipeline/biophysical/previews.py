"""Previews of the biophysical stage: chromophore colour maps, the four-map panel, sRGB, residuals.

Files (under ``RESULT/previews``): ``c_m.png`` ... (colour maps with scale bars, ranges from
:data:`polarface.results.CHROMOPHORE_PREVIEWS`), ``chromophores.png`` (the four maps' previews side by
side in one panel, like the paper's teaser), ``subsurface_srgb.png`` (sRGB under D65),
``rho_sss_bar_residual.png`` and ``in_gamut.png``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from polarface.inverse.biophysical import PARAMETER_ORDER, per_texel_relative_residual
from polarface.io import colormap_png, read_png, write_png
from polarface.results import CHROMOPHORE_PREVIEWS, ResultFolder

__all__ = ["write_previews", "write_residual_previews"]


def _write_panel(path: Path, previews: list[Path]) -> None:
    """The four chromophore previews (equal-sized colour maps with scale bars) side by side in one PNG,
    atomically: the panel is composed from their pixels, not drawn again."""
    images = [read_png(preview)[..., :3] for preview in previews]
    write_png(path, np.concatenate(images, axis=1), bit_depth=8)


def write_previews(
    root: str | Path,
    parameters: np.ndarray,
    mask: np.ndarray,
    spectral: np.ndarray,
    wavelengths_nm: np.ndarray,
) -> list[Path]:
    """Colour-mapped previews with scale bars and an sRGB preview of the spectral subsurface albedo.

    Args:
        root: RESULT folder (previews go to ``root/previews``).
        parameters: ``(H, W, 4)`` maps in ``PARAMETER_ORDER``; mask ``(H, W)`` bool.
        spectral: ``(L, H, W)`` subsurface albedo; wavelengths_nm ``(L,)``.
    """
    from polarface.skin.spectral import spectrum_to_srgb

    folder = ResultFolder(root)
    written = []
    for i, name in enumerate(PARAMETER_ORDER):
        label, low, high, cmap = CHROMOPHORE_PREVIEWS[name]
        written.append(
            colormap_png(
                folder.preview_path(name),
                parameters[..., i],
                vmin=low,
                vmax=high,
                cmap=cmap,
                mask=mask,
                title=label,
                colorbar=True,
            )
        )
    _write_panel(folder.preview_path("chromophores"), written)
    written.append(folder.preview_path("chromophores"))
    _, srgb = spectrum_to_srgb(np.moveaxis(spectral, 0, -1).astype(np.float64), wavelengths_nm)
    srgb = np.where(mask[..., None], srgb, 0.0)
    written.append(write_png(folder.preview_path("subsurface_srgb"), srgb, bit_depth=8))
    return written


def write_residual_previews(
    folder: ResultFolder, rendered: np.ndarray, in_gamut: np.ndarray, mask: np.ndarray, observed: np.ndarray
) -> None:
    """``previews/rho_sss_bar_residual.png`` (relative residual, clipped at 10 %) and
    ``previews/in_gamut.png`` (grey: input inside the skin gamut, red: outside, black: no texel).

    Args:
        rendered, observed: ``(H, W, 6)`` re-rendered and input rho_sss_bar; in_gamut, mask ``(H, W)`` bool.
    """
    residual = per_texel_relative_residual(rendered, observed, mask)
    colormap_png(
        folder.preview_path("rho_sss_bar_residual"),
        residual,
        vmin=0.0,
        vmax=0.1,
        cmap="magma",
        mask=mask,
        title="re-render relative residual (clipped at 10 %)",
        colorbar=True,
    )
    inside = in_gamut & mask
    preview = np.zeros((*mask.shape, 3), np.uint8)
    preview[inside] = (150, 150, 150)
    preview[mask & ~inside] = (230, 30, 30)
    write_png(folder.preview_path("in_gamut"), preview)
