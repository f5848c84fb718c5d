"""Texture-space subsurface transport of the renderer (paper supplement Eq. simple_sss).

Per frame:

1. **Entry** at every texel ``x_i`` of the posed head: for each LED module, a shadow ray from the
   texel decides visibility, and :func:`polarface.optics.subsurface_entry_flux` gives the flux
   entering the skin (entry Fresnel transmission with its polarization dependence, times the shading
   ``I_L (n . w_i) / Gamma^2``). The flux is spectrally flat (white-normalised LED), so it is one
   scalar map ``E``.
2. **Diffusion** on the 15-wavelength grid with the heterogeneous two-layer model
   (:func:`polarface.skin.heterogeneous.render_layered_subsurface`): per-texel layer totals from the
   chromophore maps, fixed normalised sum-of-Gaussians shapes per layer and wavelength fitted at the
   median texel, separable blurs honouring the texel size in mm (median size times a per-texel
   stretch from the UV parameterisation).
3. **Channels**: the exitance spectra are integrated into the six camera channels with the rig's
   spectral calibration (white-normalised: a unit exitance at every wavelength gives 1).

The exit Fresnel transmission and its polarization are applied per camera pixel
(:mod:`polarface.render.shading`). Light does not cross UV seams (a documented limitation of
texture-space diffusion; the seams of the bundled head lie behind the ears and under the chin).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from polarface.geometry.raycast import RayCaster
from polarface.geometry.uv_raster import UVRaster
from polarface.optics.image_formation import subsurface_entry_flux
from polarface.render.shading import lit_above_horizon, module_intensities
from polarface.skin.heterogeneous import ProfileShapes, fit_layer_shapes, render_layered_subsurface
from polarface.skin.layers import (
    CHROMOPHORE_NAMES,
    LayerTotals,
    SkinLayerConstants,
    layer_optics,
    layer_totals,
)

__all__ = ["SubsurfaceModel", "entering_flux", "texture_space_exitance", "visible_entry_flux"]


@dataclasses.dataclass(frozen=True, eq=False)
class SubsurfaceModel:
    """Per-texel layer totals and the fixed SoG shapes of one set of chromophore maps.

    Attributes:
        wavelengths_nm: ``(L,)`` float64 grid.
        totals: :class:`LayerTotals`, each ``(L, Ht, Wt)`` float32 (zero outside the atlas).
        shapes: :class:`ProfileShapes` with ``(L, J)`` normalised weights (median texel).
        texel_size_mm: the median texel size of the rest-pose raster, mm.
        stretch: ``(Ht, Wt, 2)`` per-texel size / median size along u (x) and v (y), or None: blur
            with the median texel size everywhere (FFT path, ~20x faster; ignores atlas distortion).
        mask: ``(Ht, Wt)`` float32 0/1 atlas coverage.
    """

    wavelengths_nm: torch.Tensor
    totals: LayerTotals
    shapes: ProfileShapes
    texel_size_mm: float
    stretch: torch.Tensor | None
    mask: torch.Tensor

    def totals_local_r_bar(self) -> torch.Tensor:
        """``(L, Ht, Wt)`` composed two-layer total ``R_bar`` per texel (the blur-free model)."""
        return _local_r_bar(self.totals)

    @classmethod
    def build(
        cls,
        chromophores: dict[str, np.ndarray],
        raster: UVRaster,
        wavelengths_nm: torch.Tensor,
        constants: SkinLayerConstants = SkinLayerConstants(),  # noqa: B008 - frozen dataclass
        shapes: ProfileShapes | None = None,
        *,
        per_texel_stretch: bool = False,
    ) -> SubsurfaceModel:
        """Layer totals from ``chromophores`` (``c_m``, ``beta_m``, ``c_h_in``, ``c_h_out`` maps).

        ``shapes`` default: fitted to the layer profiles at the median parameters of the atlas.
        ``per_texel_stretch`` blurs with each texel's own size (slow tap loop) instead of the median.
        """
        mask = raster.mask
        params = [
            torch.from_numpy(np.asarray(chromophores[k][mask], np.float64))
            for k in CHROMOPHORE_NAMES
        ]
        optics = layer_optics(*params, wavelengths_nm, constants)
        per_texel = layer_totals(*optics, constants)  # each (N, L)
        height, width = mask.shape
        totals = []
        for value in per_texel:
            full = torch.zeros(wavelengths_nm.numel(), height, width, dtype=torch.float32)
            full[:, torch.from_numpy(mask)] = value.T.float()
            totals.append(full)
        if shapes is None:
            median = [p.median().reshape(1) for p in params]
            shapes = fit_layer_shapes(layer_optics(*median, wavelengths_nm, constants), constants)
            shapes = ProfileShapes(*(w[0] for w in shapes[:5]), relative_error=shapes.relative_error)
        sizes = np.stack([raster.texel_size_u, raster.texel_size_v], axis=-1)
        texel_size = float(np.median(sizes[mask]))
        stretch = np.where(mask[..., None], np.clip(sizes / texel_size, 0.05, 20.0), 1.0)
        return cls(
            wavelengths_nm=wavelengths_nm,
            totals=LayerTotals(*totals),
            shapes=shapes,
            texel_size_mm=texel_size,
            stretch=torch.from_numpy(stretch.astype(np.float32)) if per_texel_stretch else None,
            mask=torch.from_numpy(mask.astype(np.float32)),
        )

    def updated(
        self,
        chromophores: dict[str, np.ndarray],
        texels: np.ndarray,
        constants: SkinLayerConstants = SkinLayerConstants(),  # noqa: B008 - frozen dataclass
    ) -> SubsurfaceModel:
        """This model with the layer totals of the ``texels`` ``(Ht, Wt)`` bool (inside the atlas)
        recomputed from ``chromophores`` (maps as in :meth:`build`); every other texel keeps its totals.

        The totals are per texel, so where ``chromophores`` equal the maps this model was built from the
        result is the model :meth:`build` makes of ``chromophores`` with this model's shapes, raster and
        stretch (bit for bit), at the cost of ``texels`` only (a dynamic frame changes a few percent).
        """
        texels = np.asarray(texels, bool)
        if not texels.any():
            return self
        params = [
            torch.from_numpy(np.asarray(chromophores[k][texels], np.float64)) for k in CHROMOPHORE_NAMES
        ]
        per_texel = layer_totals(*layer_optics(*params, self.wavelengths_nm, constants), constants)
        where = torch.from_numpy(texels)
        totals = []
        for full, value in zip(self.totals, per_texel, strict=True):
            full = full.clone()
            full[:, where] = value.T.float()
            totals.append(full)
        return dataclasses.replace(self, totals=LayerTotals(*totals))


def _local_r_bar(totals: LayerTotals) -> torch.Tensor:
    r_out_f, t_out_f, r_out_b, t_out_b, r_in_f = totals
    return r_out_f + t_out_f * r_in_f * t_out_b / (1.0 - r_out_b * r_in_f)


def entering_flux(
    caster: RayCaster,
    raster: UVRaster,
    shading_normal: np.ndarray,
    eta: np.ndarray,
    light_positions: np.ndarray,
    light_intensity: float | np.ndarray,
    camera_up: np.ndarray,
    chunk: int = 262144,
) -> np.ndarray:
    """``(Ht, Wt)`` float32 flux entering the skin per texel, summed over visible LED modules.

    Args:
        caster: ray caster of the posed mesh ``raster`` was repositioned onto.
        raster: posed raster (positions mm, geometric frame).
        shading_normal: ``(Ht, Wt, 3)`` world unit normals including the displacement detail.
        eta: ``(Ht, Wt)`` refractive index map.
        light_positions: ``(K, 3)`` mm; light_intensity: radiant intensity of every module, or ``(K,)``
            one per module (:func:`~polarface.render.shading.module_intensities`).
        camera_up: ``(3,)`` up vector defining the lights' polarization frame.
    """
    mask = raster.mask
    out = np.zeros(mask.shape, np.float32)
    points = raster.position[mask].astype(np.float64)
    normals = shading_normal[mask].astype(np.float64)
    geometric = raster.normal[mask].astype(np.float64)
    etas = np.maximum(eta[mask].astype(np.float64), 1.0 + 1e-6)
    lights = np.asarray(light_positions, np.float64)
    flux = np.zeros(points.shape[0])
    up = torch.from_numpy(np.asarray(camera_up, np.float64))
    intensity = module_intensities(light_intensity, lights.shape[0])
    for start in range(0, points.shape[0], chunk):
        stop = min(start + chunk, points.shape[0])
        visible = lit_above_horizon(
            caster, points[start:stop], geometric[start:stop], normals[start:stop], lights
        )  # (n, K)
        phi = visible_entry_flux(
            torch.from_numpy(normals[start:stop]),
            torch.from_numpy(points[start:stop]),
            up,
            lights,
            intensity,
            torch.from_numpy(etas[start:stop])[:, None],
            visible,
        )
        flux[start:stop] = phi[:, 0].numpy()
    out[mask] = flux
    return out


def visible_entry_flux(
    normal: torch.Tensor,
    position: torch.Tensor,
    up: torch.Tensor,
    light_positions: np.ndarray,
    light_intensity: torch.Tensor,
    eta: torch.Tensor,
    visible: np.ndarray,
) -> torch.Tensor:
    """``(N, C)`` flux entering the skin at ``N`` points, summed over the LED modules each point sees.

    :func:`polarface.optics.subsurface_entry_flux` of every module ``k`` over the points whose shadow
    ray to it is free (``visible[:, k]``); shadowed modules add nothing.

    Args:
        normal: ``(N, 3)`` unit shading normals; position: ``(N, 3)`` mm (one frame, float64 or 32).
        up: ``(3,)`` or ``(N, 3)`` up vector of the lights' polarizer frame.
        light_positions: ``(K, 3)`` mm (numpy). light_intensity: ``(K, C)`` radiant intensity per channel.
        eta: ``(N, 1)`` or ``(N, C)`` refractive index > 1. visible: ``(N, K)`` bool.
    """
    flux = torch.zeros(normal.shape[0], light_intensity.shape[-1], dtype=position.dtype)
    lights = torch.from_numpy(np.asarray(light_positions)).to(position.dtype)
    for k in range(lights.shape[0]):
        lit = torch.from_numpy(np.asarray(visible[:, k], bool))
        if not bool(lit.any()):
            continue
        flux[lit] += subsurface_entry_flux(
            normal[lit],
            position[lit],
            up if up.ndim == 1 else up[lit],
            lights[k : k + 1],
            light_intensity[k : k + 1],
            eta[lit],
        )
    return flux


def texture_space_exitance(
    flux: np.ndarray, model: SubsurfaceModel, calibration, *, blur: bool = True
) -> np.ndarray:
    """``(Ht, Wt, 6)`` float32 diffused exitance per camera channel (before the exit Fresnel factor).

    Args:
        flux: ``(Ht, Wt)`` entering flux (:func:`entering_flux`).
        model: layer totals and shapes.
        calibration: the rig's ``SpectralCalibration`` on ``model.wavelengths_nm``.
        blur: False replaces the diffusion by its local total (``R_bar E``; for tests of the
            blur-free model).
    """
    energy = torch.from_numpy(flux.astype(np.float32))[None].expand(model.wavelengths_nm.numel(), -1, -1)
    if blur:
        spectral = render_layered_subsurface(
            energy,
            tuple(model.totals),
            model.shapes,
            model.texel_size_mm,
            stretch=model.stretch,
            mask=model.mask,
        )
    else:
        spectral = model.totals_local_r_bar() * energy
    channels = calibration.integrate(spectral.permute(1, 2, 0).double())
    return channels.clamp_min(0.0).float().numpy()  # FFT blurs ring at ~1e-8 around dark texels
