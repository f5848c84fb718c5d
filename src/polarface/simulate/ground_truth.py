"""Ground-truth appearance maps of the simulated head, on the asset's UV atlas.

Every map is a plausible, spatially varying texture ``(H, W)`` (or ``(H, W, 6)``) float32:

* ``displacement_mm`` — the scan's displacement map, zero-median, in mm (pores, wrinkles);
* ``rho_s`` — specular albedo from the scan's specular map, raised in oily regions;
* ``eta`` — 1.38-1.48, higher on the oilier forehead and nose (paper Sec. 6, "Polarimetric
  reflectance": more oil and moisture on forehead and nose than on cheeks and lips);
* ``alpha_s`` 0.30-0.65 (shinier where oily), ``alpha_ss`` 0.90-1.00, ``rho_ss``;
* chromophores ``c_m``, ``beta_m``, ``c_h_in``, ``c_h_out`` derived from the scan's albedo map
  *through the skin model*: per texel, the melanin and outer-haemoglobin multipliers whose modelled
  colour (two-layer diffusion total -> CIE 1931 -> linear sRGB) best matches the albedo texel's
  colour relative to the median skin colour. Freckles and brows (darker, browner) get melanin,
  cheeks and lips (redder) haemoglobin. The skin-type preset sets the means (forehead values on
  the forehead, cheek values on the cheeks, blended elsewhere), so one asset yields types I-VI;
* ``rho_sss_bar`` — the six-channel subsurface albedo: the two-layer total ``R_bar`` integrated
  into the rig's six spectral channels (``docs/conventions.md``, "Radiometry of the pBSSRDF").

All randomness (the low-frequency variation of beta_m, c_h_in, alpha_ss, rho_ss) comes from one
seeded numpy Generator: the same seed gives the same maps.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
import torch
from scipy import ndimage

from polarface.results import CHROMOPHORE_MAPS, POLARIMETRIC_MAPS
from polarface.simulate.presets import SkinTypePreset

__all__ = [
    "SCALAR_MAPS",
    "AppearanceMaps",
    "blood_flow_factor",
    "build_appearance_maps",
    "chromophore_maps",
    "chromophore_multipliers_from_albedo",
    "facial_region_weights",
    "smooth_random_field",
]

#: Names of the scalar maps, in the order they are saved.
SCALAR_MAPS = (*POLARIMETRIC_MAPS, *CHROMOPHORE_MAPS)


@dataclasses.dataclass(frozen=True, eq=False)
class AppearanceMaps:
    """Ground-truth parameter maps on the UV atlas (texture layout of ``polarface.geometry.uv_raster``).

    Attributes:
        eta, alpha_s, alpha_ss, rho_s, rho_ss: ``(H, W)`` float32 polarimetric parameters.
        displacement_mm: ``(H, W)`` float32 displacement H along the base normal, mm.
        c_m, beta_m, c_h_in, c_h_out: ``(H, W)`` float32 biophysical volume fractions.
        rho_sss_bar: ``(H, W, 6)`` float32 six-channel subsurface albedo (local, before blur).
        mask: ``(H, W)`` bool, texels covered by the UV atlas.
    """

    eta: np.ndarray
    alpha_s: np.ndarray
    alpha_ss: np.ndarray
    rho_s: np.ndarray
    rho_ss: np.ndarray
    displacement_mm: np.ndarray
    c_m: np.ndarray
    beta_m: np.ndarray
    c_h_in: np.ndarray
    c_h_out: np.ndarray
    rho_sss_bar: np.ndarray
    mask: np.ndarray

    def scalar_maps(self) -> dict[str, np.ndarray]:
        """The ten scalar maps by name (``SCALAR_MAPS`` order)."""
        return {name: getattr(self, name) for name in SCALAR_MAPS}

    def replace(self, **changes: np.ndarray) -> AppearanceMaps:
        """A copy with some maps replaced (used for the per-frame blood-flow maps)."""
        return dataclasses.replace(self, **changes)


def chromophore_maps(maps: AppearanceMaps) -> dict[str, np.ndarray]:
    """The four chromophore maps ``(Ht, Wt)`` of ``maps``: ``c_m``, ``beta_m``, ``c_h_in``, ``c_h_out``."""
    return {"c_m": maps.c_m, "beta_m": maps.beta_m, "c_h_in": maps.c_h_in, "c_h_out": maps.c_h_out}


def smooth_random_field(
    shape: tuple[int, int], correlation_texels: float, rng: np.random.Generator
) -> np.ndarray:
    """Zero-mean, unit-std Gaussian random field with the given correlation length, float32 ``shape``."""
    noise = rng.standard_normal(shape)
    field = ndimage.gaussian_filter(noise, sigma=correlation_texels, mode="wrap")
    field -= field.mean()
    std = field.std()
    return (field / std if std > 0 else field).astype(np.float32)


def facial_region_weights(
    positions: np.ndarray, mask: np.ndarray, landmarks: dict[str, np.ndarray]
) -> dict[str, np.ndarray]:
    """Soft weights in [0, 1] of facial regions per texel, from rest-pose positions (mm).

    Regions are smooth 3D Gaussian blobs around the asset's landmarks
    (``polarface.geometry.head_asset.LANDMARKS_XY_MM``, model frame: mm, +y up, face towards +z):

    * ``forehead`` (40 x 22 x 25 mm blob at the ``forehead`` landmark, lowered 10 mm),
    * ``nose`` (12 x 22 x 25 mm along the midline above ``nose_tip``),
    * ``cheeks`` (20 x 18 x 25 mm at ``cheek_left`` and ``cheek_right``),
    * ``lips`` (22 x 8 x 15 mm at ``mouth_center``),
    * ``oily`` = the T-zone (forehead + nose), used for eta, alpha_s and rho_s.

    Args:
        positions: ``(H, W, 3)`` rest-pose texel positions in mm.
        mask: ``(H, W)`` bool valid texels.
        landmarks: name -> ``(3,)`` rest-pose position in mm; needs ``forehead``, ``nose_tip``,
            ``cheek_left``, ``cheek_right``, ``mouth_center``.
    """
    missing = {"forehead", "nose_tip", "cheek_left", "cheek_right", "mouth_center"} - set(landmarks)
    if missing:
        raise ValueError(f"argument 'landmarks' lacks {sorted(missing)}")
    safe = np.where(mask[..., None], positions, 0.0)

    def blob(centre: np.ndarray, sigma_mm: tuple[float, float, float]) -> np.ndarray:
        d2 = (((safe - np.asarray(centre)) / np.asarray(sigma_mm)) ** 2).sum(axis=-1)
        return np.where(mask, np.exp(-0.5 * d2), 0.0).astype(np.float32)

    forehead_centre = np.asarray(landmarks["forehead"]) + np.array([0.0, -10.0, 0.0])
    nose_centre = np.asarray(landmarks["nose_tip"]) + np.array([0.0, 15.0, -5.0])
    forehead = blob(forehead_centre, (40.0, 22.0, 25.0))
    nose = blob(nose_centre, (12.0, 22.0, 25.0))
    cheeks = np.maximum(
        blob(landmarks["cheek_left"], (20.0, 18.0, 25.0)), blob(landmarks["cheek_right"], (20.0, 18.0, 25.0))
    )
    lips = blob(landmarks["mouth_center"], (22.0, 8.0, 15.0))
    oily = np.clip(forehead + nose, 0.0, 1.0)
    return {"forehead": forehead, "nose": nose, "cheeks": cheeks, "lips": lips, "oily": oily}


def _srgb_linear_of_chromophores(
    c_m: torch.Tensor, beta_m: torch.Tensor, c_h_in: torch.Tensor, c_h_out: torch.Tensor
) -> torch.Tensor:
    """Linear sRGB ``(..., 3)`` of the two-layer diffusion total under the rig's LED."""
    from polarface.skin import spectral
    from polarface.skin.layers import subsurface_albedo

    wavelengths = torch.as_tensor(spectral.DEFAULT_WAVELENGTHS_NM, dtype=c_m.dtype)
    r_bar = subsurface_albedo(c_m, beta_m, c_h_in, c_h_out, wavelengths)
    return spectral.spectrum_to_srgb(r_bar, wavelengths)[0]


def _nearest_table_entry(table: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """A function mapping points ``(n, 3)`` float64 to the index ``(n,)`` int64 of their nearest row of
    ``table`` ``(T, 3)`` (Euclidean), the first of equal rows: a k-d tree over the distinct rows.

    The table repeats rows where its chromophores are clamped; among those the first index is the one
    an ``argmin`` over all rows gives, so the multipliers do not depend on how ties are broken. (It
    replaced ``torch.cdist`` + ``argmin``, whose distances go through a matrix product: on the demo's
    240 k and the tiny preset's 60 k texels both pick the same entries, 2.4 s -> 0.26 s, measured.)
    """
    from scipy.spatial import cKDTree

    _, first = np.unique(table, axis=0, return_index=True)
    first = np.sort(first)
    tree = cKDTree(table[first])
    return lambda points: first[tree.query(points)[1]].astype(np.int64)


def chromophore_multipliers_from_albedo(
    albedo_linear: np.ndarray,
    mask: np.ndarray,
    base: tuple[float, float, float, float],
    *,
    log_range: float = 2.0,
    lut_steps: int = 41,
    chunk: int = 65536,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-texel log-multipliers of melanin and outer haemoglobin explaining the albedo's colour.

    Through the skin model: a table of modelled colours ``g(a, b) = log rgb(C_m e^a, C_h_out e^b) -
    log rgb(C_m, C_h_out)`` (two-layer diffusion total -> CIE 1931 -> linear sRGB) over a
    ``lut_steps`` x ``lut_steps`` grid of ``a, b`` in ``[-log_range, log_range]`` at the ``base``
    parameters; each texel's colour relative to the median colour, ``f = log albedo - log median``,
    is matched to its nearest table entry and refined by one linearised least-squares step with the
    table's finite-difference Jacobian (continuous values, no banding).

    Args:
        albedo_linear: ``(H, W, 3)`` linear RGB albedo texture (any scale: only ratios matter).
        mask: ``(H, W)`` bool texels to solve; others get 0.
        base: scalar ``(c_m, beta_m, c_h_in, c_h_out)`` around which the multipliers act.
        log_range: bound on the natural-log multipliers.
        lut_steps: table resolution per axis.
        chunk: texels per block of the least-squares step (memory bound).

    Returns:
        ``(a, b)``: ``(H, W)`` float32 natural-log multipliers of ``c_m`` and ``c_h_out``.
    """
    grid = torch.linspace(-log_range, log_range, lut_steps, dtype=torch.float64)
    aa, bb = torch.meshgrid(grid, grid, indexing="ij")
    c_m, beta_m, c_h_in, c_h_out = (torch.tensor(float(v), dtype=torch.float64) for v in base)
    # Keep every table entry physical: C_m <= 0.5 and C_m + C_h_out < 1 (volume fractions).
    lut_c_m = (c_m * torch.exp(aa.reshape(-1))).clamp(max=0.5)
    lut_c_h_out = torch.minimum((c_h_out * torch.exp(bb.reshape(-1))).clamp(max=0.32), 0.999 - lut_c_m)
    rgb = _srgb_linear_of_chromophores(
        lut_c_m, beta_m.expand(aa.numel()), c_h_in.expand(aa.numel()), lut_c_h_out
    )
    table = torch.log(rgb.clamp_min(1e-8)).reshape(lut_steps, lut_steps, 3)
    centre = lut_steps // 2
    table = table - table[centre, centre]
    step = float(grid[1] - grid[0])
    # Finite-difference Jacobian of the table along a and b (central inside, one-sided at the rim).
    jac_a = torch.gradient(table, spacing=step, dim=0)[0]
    jac_b = torch.gradient(table, spacing=step, dim=1)[0]
    nearest_entry = _nearest_table_entry(table.reshape(-1, 3).numpy())

    rgb_texels = np.clip(albedo_linear[mask].astype(np.float64), 1e-4, None)
    target = torch.from_numpy(np.log(rgb_texels) - np.log(np.median(rgb_texels, axis=0)))
    params = torch.empty(target.shape[0], 2, dtype=torch.float64)
    for start in range(0, target.shape[0], chunk):
        block = target[start : start + chunk]
        nearest = torch.from_numpy(nearest_entry(block.numpy()))
        ia, ib = nearest // lut_steps, nearest % lut_steps
        jac = torch.stack([jac_a[ia, ib], jac_b[ia, ib]], dim=-1)  # (n, 3, 2)
        residual = (block - table[ia, ib]).unsqueeze(-1)
        normal = jac.transpose(1, 2) @ jac + 1e-9 * torch.eye(2, dtype=torch.float64)
        delta = torch.linalg.solve(normal, jac.transpose(1, 2) @ residual).squeeze(-1)
        delta = delta.clamp(-step, step)  # stay within the neighbouring cells
        params[start : start + chunk, 0] = grid[ia] + delta[:, 0]
        params[start : start + chunk, 1] = grid[ib] + delta[:, 1]
    params = params.clamp(-log_range, log_range)
    a = np.zeros(mask.shape, np.float32)
    b = np.zeros(mask.shape, np.float32)
    a[mask] = params[:, 0].numpy()
    b[mask] = params[:, 1].numpy()
    return a, b


def _regional_chromophore_means(
    regions: dict[str, np.ndarray], skin_type: SkinTypePreset
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(c_m, beta_m, c_h_in, c_h_out)`` float64 ``(H, W)`` base maps: forehead values on the forehead,
    cheek values on cheeks and lips, their mean elsewhere (blended by the region weights)."""
    forehead_values = np.array([skin_type.c_m, skin_type.beta_m, skin_type.c_h_in, skin_type.c_h_out])
    cheek_values = np.array(skin_type.cheek) if any(skin_type.cheek) else forehead_values
    w_forehead = regions["forehead"] + regions["nose"]
    w_cheek = np.maximum(regions["cheeks"], regions["lips"])
    total = w_forehead + w_cheek + 0.3
    blend = (
        w_forehead[..., None] * forehead_values
        + w_cheek[..., None] * cheek_values
        + 0.3 * 0.5 * (forehead_values + cheek_values)
    ) / total[..., None]
    return tuple(blend[..., i].astype(np.float64) for i in range(4))  # type: ignore[return-value]


def _six_channel_albedo(
    c_m: np.ndarray,
    beta_m: np.ndarray,
    c_h_in: np.ndarray,
    c_h_out: np.ndarray,
    mask: np.ndarray,
    calibration,
) -> np.ndarray:
    """``(H, W, 6)`` float32 subsurface albedo rho_sss_bar of the chromophore maps (0 outside ``mask``)."""
    from polarface.skin import spectral
    from polarface.skin.layers import subsurface_albedo

    wavelengths = torch.as_tensor(spectral.DEFAULT_WAVELENGTHS_NM, dtype=torch.float64)
    r_bar = subsurface_albedo(
        torch.from_numpy(c_m[mask]),
        torch.from_numpy(beta_m[mask]),
        torch.from_numpy(c_h_in[mask]),
        torch.from_numpy(c_h_out[mask]),
        wavelengths,
    )
    rho_sss_bar = np.zeros((*mask.shape, 6), np.float32)
    rho_sss_bar[mask] = calibration.integrate(r_bar).numpy()
    return rho_sss_bar


def build_appearance_maps(
    *,
    albedo_linear: np.ndarray,
    specular: np.ndarray,
    displacement_mm: np.ndarray,
    positions: np.ndarray,
    mask: np.ndarray,
    landmarks: dict[str, np.ndarray],
    skin_type: SkinTypePreset,
    calibration,  # polarface.skin.spectral.SpectralCalibration
    seed: int = 0,
) -> AppearanceMaps:
    """Build every ground-truth map for one skin type.

    Args:
        albedo_linear: ``(H, W, 3)`` linear RGB albedo of the scan.
        specular: ``(H, W)`` specular map of the scan in [0, 1].
        displacement_mm: ``(H, W)`` displacement of the scan in mm (high-passed detail).
        positions: ``(H, W, 3)`` rest-pose texel positions, mm (for the regions).
        mask: ``(H, W)`` bool texels covered by the atlas.
        landmarks: name -> ``(3,)`` rest-pose landmark positions (see :func:`facial_region_weights`).
        skin_type: the preset giving the chromophore means.
        calibration: the rig's ``SpectralCalibration`` (rho_sss_bar channels).
        seed: seed of the low-frequency variations.

    Returns:
        :class:`AppearanceMaps` with zeros outside ``mask`` (and eta = 1.4 there, so it stays valid).
    """
    shape = mask.shape
    rng = np.random.default_rng(seed)
    regions = facial_region_weights(positions, mask, landmarks)
    oily = regions["oily"]
    base_c_m, base_beta_m, base_c_h_in, base_c_h_out = _regional_chromophore_means(regions, skin_type)
    # Low-frequency variations (correlation ~1/16 of the atlas).
    corr = shape[0] / 16.0
    beta_m = np.clip(base_beta_m + 0.015 * smooth_random_field(shape, corr, rng), 0.0, 1.0)
    c_h_in = np.clip(base_c_h_in * (1.0 + 0.15 * smooth_random_field(shape, corr, rng)), 1e-3, 0.3)
    log_m, log_h = chromophore_multipliers_from_albedo(
        albedo_linear,
        mask,
        (
            float(np.median(base_c_m[mask])),
            float(np.median(beta_m[mask])),
            float(np.median(base_c_h_in[mask])),
            float(np.median(base_c_h_out[mask])),
        ),
    )
    c_m = np.clip(base_c_m * np.exp(log_m), 1e-3, 0.5)
    c_h_out = np.clip(base_c_h_out * np.exp(log_h), 1e-3, 0.3)
    # Lips are redder than the albedo texture alone explains (no melanin change).
    c_h_out = np.clip(c_h_out * (1.0 + 0.6 * regions["lips"]), 1e-3, 0.3)
    c_h_out = np.minimum(c_h_out, 0.999 - c_m)  # volume fractions: C_m + C_h_out < 1

    spec = np.clip(specular.astype(np.float64), 0.0, 1.0)
    spec_norm = spec / max(float(np.percentile(spec[mask], 95)), 1e-6)
    eta = 1.395 + 0.08 * oily + 0.008 * smooth_random_field(shape, corr, rng)
    eta = np.clip(eta, 1.38, 1.48)
    alpha_s = np.clip(0.62 - 0.30 * oily + 0.02 * smooth_random_field(shape, corr, rng), 0.30, 0.65)
    alpha_ss = np.clip(0.95 + 0.02 * smooth_random_field(shape, corr, rng), 0.90, 1.0)
    rho_s = np.clip(0.35 + 0.45 * np.clip(spec_norm, 0.0, 1.2) + 0.2 * oily, 0.05, 1.0)
    rho_ss = np.clip(0.25 + 0.05 * smooth_random_field(shape, corr, rng), 0.1, 0.4)
    displacement_mm = displacement_mm.astype(np.float64) - float(np.median(displacement_mm[mask]))

    rho_sss_bar = _six_channel_albedo(c_m, beta_m, c_h_in, c_h_out, mask, calibration)

    def finish(values: np.ndarray, outside: float = 0.0) -> np.ndarray:
        return np.where(mask, values, outside).astype(np.float32)

    return AppearanceMaps(
        eta=finish(eta, 1.4),
        alpha_s=finish(alpha_s, 0.5),
        alpha_ss=finish(alpha_ss, 0.95),
        rho_s=finish(rho_s),
        rho_ss=finish(rho_ss),
        displacement_mm=finish(displacement_mm),
        c_m=finish(c_m),
        beta_m=finish(beta_m),
        c_h_in=finish(c_h_in),
        c_h_out=finish(c_h_out),
        rho_sss_bar=rho_sss_bar,
        mask=mask.copy(),
    )


def blood_flow_factor(time_s: np.ndarray | float, recovery_s: float = 2.0) -> np.ndarray:
    """Fraction of outer haemoglobin restored ``t`` seconds after releasing the pressure.

    ``1 - exp(-t / tau)`` with ``tau = recovery_s / 3`` (95 % restored after ``recovery_s``; the paper
    shows blood re-entering the pressed region within about two seconds, Fig. "blood flow").
    """
    tau = recovery_s / 3.0
    return 1.0 - np.exp(-np.asarray(time_s, dtype=np.float64) / tau)
