"""Two-layer biophysical skin model: layer optical properties and composed diffusion totals.

Paper Sec. 3.2 (Eq. epi_ab) and supplement "Human Skin Rendering with Subsurface Scattering" /
"Optimization of Biophysically-based Parameters Details". Parameters are volume fractions (maps,
broadcast over texels): melanin ``c_m``, eumelanin share of melanin ``beta_m``, haemoglobin of the
inner (dermis) and outer (epidermis + upper dermis) layer ``c_h_in``, ``c_h_out``; oxy fraction
``gamma`` (0.75). Spectral axis last: outputs ``(..., L)`` for parameters ``(...)`` and wavelengths
``(L,)`` in nm.

    sigma_a_out = C_m (beta_m s_em + (1 - beta_m) s_pm) + C_h_out (gamma s_oxy + (1 - gamma) s_deoxy)
                  + (1 - C_m - C_h_out) s_base
    sigma_a_in  = C_h_in (gamma s_oxy + (1 - gamma) s_deoxy) + (1 - C_h_in) s_base
    sigma_s'_out = 14.74 l^-0.22 + 2.2e11 l^-4,  sigma_s'_in = 0.5 sigma_s'_out

The outer layer (0.25 mm, relative index 1.4 under air, index-matched below) gives R_out^f, T_out^f,
R_out^b, T_out^b by the multipole; the semi-infinite inner layer (index-matched) R_in^f by the dipole.
The composed total (the geometric series of the supplement):

    R_bar = R_out^f + T_out^f R_in (1 - R_out^b R_in)^-1 T_out^b.

``R_bar`` is a diffusion total: it excludes the specular reflection and the entry Fresnel loss
(``docs/conventions.md``, "Radiometry of the pBSSRDF"); integrating it into camera channels with
``SpectralCalibration.integrate`` gives ``rho_sss_bar``.

Note (documented limitation): at 0.25 mm the outer layer is only 1-3 transport mean free paths thick
across 420-700 nm, where the multipole's transmittance is rough (see ``multipole`` and the oracle
tests); this is the paper's model and is kept.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import torch

from polarface._validation import array_api, broadcast_named, broadcast_shape, check_range
from polarface.skin.chromophores import (
    sigma_a_baseline,
    sigma_a_deoxy_haemoglobin,
    sigma_a_eumelanin,
    sigma_a_oxy_haemoglobin,
    sigma_a_pheomelanin,
    sigma_s_prime_outer,
)
from polarface.skin.multipole import DEFAULT_N_POLES, slab_totals_unchecked

__all__ = [
    "CHROMOPHORE_NAMES",
    "PARAMETER_RANGES",
    "LayerOptics",
    "LayerTotals",
    "SkinLayerConstants",
    "chromophore_spectra",
    "compose_total_reflectance",
    "layer_optics",
    "layer_optics_unchecked",
    "layer_totals",
    "layer_totals_unchecked",
    "subsurface_albedo",
    "subsurface_albedo_unchecked",
]


@dataclasses.dataclass(frozen=True)
class SkinLayerConstants:
    """Fixed constants of the two-layer skin model (literature defaults, cited per attribute).

    Attributes:
        outer_thickness_mm: outer-layer thickness, mm (0.25; Donner & Jensen 2006/2008).
        eta_skin: relative refractive index of skin under air inside the multipole (1.4).
        eta_interlayer: relative index between the layers (1.0: index-matched).
        gamma: oxy-haemoglobin fraction of haemoglobin (0.75; paper, Donner 2008, Jimenez 2010).
        inner_scattering_ratio: inner reduced scattering / outer (0.5).
        n_poles: multipole pairs per side for the outer layer.
    """

    outer_thickness_mm: float = 0.25
    eta_skin: float = 1.4
    eta_interlayer: float = 1.0
    gamma: float = 0.75
    inner_scattering_ratio: float = 0.5
    n_poles: int = DEFAULT_N_POLES

    def __post_init__(self) -> None:
        if not (self.outer_thickness_mm > 0 and math.isfinite(self.outer_thickness_mm)):
            raise ValueError(f"outer_thickness_mm must be finite and > 0; got {self.outer_thickness_mm}")
        if not self.eta_skin > 0 or not self.eta_interlayer > 0:
            raise ValueError("eta_skin and eta_interlayer must be > 0")
        if not 0.0 <= self.gamma <= 1.0:
            raise ValueError(f"gamma must lie in [0, 1]; got {self.gamma}")
        if not self.inner_scattering_ratio > 0:
            raise ValueError(f"inner_scattering_ratio must be > 0; got {self.inner_scattering_ratio}")


#: Physical ranges of the biophysical parameters (volume fractions), used by fits and validation.
#: Melanin up to 0.5 and haemoglobin up to 0.32 contain the literature ranges (Donner & Jensen
#: 2006, Jimenez 2010) and the paper's estimates (supplement Table tb:res_params).
#: The two-layer model's chromophore parameters (volume fractions), in the order every stage uses.
CHROMOPHORE_NAMES = ("c_m", "beta_m", "c_h_in", "c_h_out")

PARAMETER_RANGES: dict[str, tuple[float, float]] = {
    "c_m": (0.0, 0.5),
    "beta_m": (0.0, 1.0),
    "c_h_in": (0.0, 0.32),
    "c_h_out": (0.0, 0.32),
}


class LayerOptics(NamedTuple):
    """Optical coefficients per wavelength, each ``(..., L)`` in mm^-1."""

    sigma_a_out: torch.Tensor
    sigma_a_in: torch.Tensor
    sigma_s_prime_out: torch.Tensor
    sigma_s_prime_in: torch.Tensor


class LayerTotals(NamedTuple):
    """Diffusion totals per texel and wavelength, each ``(..., L)``, dimensionless."""

    r_out_f: torch.Tensor
    t_out_f: torch.Tensor
    r_out_b: torch.Tensor
    t_out_b: torch.Tensor
    r_in_f: torch.Tensor


def _check_parameters(c_m, beta_m, c_h_in, c_h_out) -> list[torch.Tensor]:
    for name, value in (("c_m", c_m), ("beta_m", beta_m), ("c_h_in", c_h_in), ("c_h_out", c_h_out)):
        check_range(value, name, 0.0, 1.0)
    c_m, beta_m, c_h_in, c_h_out = broadcast_named(
        ("c_m", c_m), ("beta_m", beta_m), ("c_h_in", c_h_in), ("c_h_out", c_h_out)
    )
    check_range(c_m + c_h_out, "c_m + c_h_out", 0.0, 1.0)
    return [c_m, beta_m, c_h_in, c_h_out]


@array_api("c_m", "beta_m", "c_h_in", "c_h_out", "wavelengths_nm")
def layer_optics(
    c_m: torch.Tensor,
    beta_m: torch.Tensor,
    c_h_in: torch.Tensor,
    c_h_out: torch.Tensor,
    wavelengths_nm: torch.Tensor,
    constants: SkinLayerConstants = SkinLayerConstants(),
) -> LayerOptics:
    """Absorption and reduced scattering of both layers (paper Eq. epi_ab), mm^-1.

    Args:
        c_m: ``(...)`` melanin volume fraction in [0, 1].
        beta_m: ``(...)`` eumelanin fraction of melanin in [0, 1].
        c_h_in: ``(...)`` haemoglobin (whole blood) volume fraction of the inner layer in [0, 1].
        c_h_out: ``(...)`` haemoglobin volume fraction of the outer layer; ``c_m + c_h_out <= 1``.
        wavelengths_nm: ``(L,)`` wavelengths in nm (250-1000, the haemoglobin table's range).
        constants: :class:`SkinLayerConstants` (gamma, inner scattering ratio).

    Returns:
        :class:`LayerOptics` of ``(..., L)`` tensors in mm^-1.
    """
    if wavelengths_nm.ndim != 1:
        raise ValueError(
            f"argument 'wavelengths_nm' must be 1-D (L,); got shape {tuple(wavelengths_nm.shape)}"
        )
    c_m, beta_m, c_h_in, c_h_out = _check_parameters(c_m, beta_m, c_h_in, c_h_out)
    return layer_optics_unchecked(c_m, beta_m, c_h_in, c_h_out, wavelengths_nm, constants)


def layer_optics_unchecked(c_m, beta_m, c_h_in, c_h_out, wavelengths_nm, constants) -> LayerOptics:
    """Unchecked core of :func:`layer_optics` (tensors in, validated by the caller): :class:`LayerOptics` of
    ``(..., L)`` tensors in mm^-1."""
    c_m, beta_m, c_h_in, c_h_out = (p[..., None] for p in (c_m, beta_m, c_h_in, c_h_out))
    spectra = chromophore_spectra(wavelengths_nm, constants.gamma)
    melanin = beta_m * spectra["eumelanin"] + (1 - beta_m) * spectra["pheomelanin"]
    base = spectra["baseline"]
    sigma_a_out = c_m * melanin + c_h_out * spectra["blood"] + (1 - c_m - c_h_out) * base
    sigma_a_in = c_h_in * spectra["blood"] + (1 - c_h_in) * base
    scattering_out = spectra["scattering"].expand_as(sigma_a_out)
    return LayerOptics(
        sigma_a_out, sigma_a_in, scattering_out, constants.inner_scattering_ratio * scattering_out
    )


def chromophore_spectra(wavelengths_nm: torch.Tensor, gamma: float) -> dict[str, torch.Tensor]:
    """The spectra of Eq. epi_ab at ``wavelengths_nm`` ``(L,)`` (nm), each ``(L,)`` in mm^-1: ``blood`` (oxy
    fraction ``gamma``), ``baseline``, ``eumelanin``, ``pheomelanin`` absorption and the outer layer's
    reduced ``scattering``."""
    blood = gamma * sigma_a_oxy_haemoglobin(wavelengths_nm) + (1 - gamma) * sigma_a_deoxy_haemoglobin(
        wavelengths_nm
    )
    return {
        "blood": blood,
        "baseline": sigma_a_baseline(wavelengths_nm),
        "eumelanin": sigma_a_eumelanin(wavelengths_nm),
        "pheomelanin": sigma_a_pheomelanin(wavelengths_nm),
        "scattering": sigma_s_prime_outer(wavelengths_nm),
    }


@array_api("sigma_a_out", "sigma_a_in", "sigma_s_prime_out", "sigma_s_prime_in")
def layer_totals(
    sigma_a_out: torch.Tensor,
    sigma_a_in: torch.Tensor,
    sigma_s_prime_out: torch.Tensor,
    sigma_s_prime_in: torch.Tensor,
    constants: SkinLayerConstants = SkinLayerConstants(),
) -> LayerTotals:
    """Diffusion totals of the two layers from their coefficients (any matching shapes, mm^-1 in).

    Outer layer: multipole slab of ``constants.outer_thickness_mm`` with ``eta_skin`` on top and
    ``eta_interlayer`` below; backward totals swap the surfaces. Inner layer: dipole, semi-infinite,
    relative index ``eta_interlayer``.

    Returns:
        :class:`LayerTotals` (``r_out_f, t_out_f, r_out_b, t_out_b, r_in_f``), broadcast shape,
        dimensionless.
    """
    for name, value in (
        ("sigma_a_out", sigma_a_out),
        ("sigma_a_in", sigma_a_in),
    ):
        check_range(value, name, 0.0)
    for name, value in (("sigma_s_prime_out", sigma_s_prime_out), ("sigma_s_prime_in", sigma_s_prime_in)):
        check_range(value, name, 0.0, low_inclusive=False)
    return layer_totals_unchecked(sigma_a_out, sigma_a_in, sigma_s_prime_out, sigma_s_prime_in, constants)


#: Elements per block of :func:`layer_totals_unchecked` (a multiple of every SIMD width): each of the
#: multipole's ~150 elementwise steps then runs on a block that stays in the core's cache (0.5 MB in
#: float64) instead of streaming the whole array through memory once per step.
_TOTALS_BLOCK = 65536


def layer_totals_unchecked(
    sigma_a_out, sigma_a_in, sigma_s_prime_out, sigma_s_prime_in, constants
) -> LayerTotals:
    """Unchecked core of :func:`layer_totals` (broadcasting tensors, mm^-1; :class:`LayerTotals` of their
    broadcast shape).

    Large inputs go through in blocks of :data:`_TOTALS_BLOCK` elements of their broadcast shape: every
    step is elementwise, so the values are the same (test), and 240 k texels x 15 wavelengths take
    about half the time (measured, 1 and 2 threads).
    """
    inputs = (sigma_a_out, sigma_a_in, sigma_s_prime_out, sigma_s_prime_in)
    shape = broadcast_shape(*(t.shape for t in inputs))
    count = math.prod(shape)
    if count <= 2 * _TOTALS_BLOCK:
        return _layer_totals_block(*inputs, constants)
    flat = [t.expand(shape).reshape(-1) for t in inputs]
    blocks = [
        _layer_totals_block(*(f[start : start + _TOTALS_BLOCK] for f in flat), constants)
        for start in range(0, count, _TOTALS_BLOCK)
    ]
    return LayerTotals(*(torch.cat(parts).reshape(shape) for parts in zip(*blocks, strict=True)))


def _layer_totals_block(
    sigma_a_out, sigma_a_in, sigma_s_prime_out, sigma_s_prime_in, constants
) -> LayerTotals:
    """:func:`layer_totals_unchecked` of one block (the multipole and dipole totals, elementwise)."""

    def scalar(value: float) -> torch.Tensor:
        return torch.tensor(value, dtype=sigma_a_out.dtype, device=sigma_a_out.device)

    d, eta_top, eta_mid = (
        scalar(constants.outer_thickness_mm),
        scalar(constants.eta_skin),
        scalar(constants.eta_interlayer),
    )
    n = constants.n_poles
    r_out_f, t_out_f = slab_totals_unchecked(sigma_a_out, sigma_s_prime_out, d, eta_top, eta_mid, n)
    r_out_b, t_out_b = slab_totals_unchecked(sigma_a_out, sigma_s_prime_out, d, eta_mid, eta_top, n)
    r_in_f, _ = slab_totals_unchecked(sigma_a_in, sigma_s_prime_in, scalar(math.inf), eta_mid, eta_mid, 0)
    return LayerTotals(r_out_f, t_out_f, r_out_b, t_out_b, r_in_f)


def _compose(r_out_f, t_out_f, r_out_b, t_out_b, r_in_f) -> torch.Tensor:
    return r_out_f + t_out_f * r_in_f * t_out_b / (1.0 - r_out_b * r_in_f)


@array_api("r_out_f", "t_out_f", "r_out_b", "t_out_b", "r_in_f")
def compose_total_reflectance(
    r_out_f: torch.Tensor,
    t_out_f: torch.Tensor,
    r_out_b: torch.Tensor,
    t_out_b: torch.Tensor,
    r_in_f: torch.Tensor,
) -> torch.Tensor:
    """``R_bar = R_out^f + T_out^f R_in (1 - R_out^b R_in)^-1 T_out^b`` (sum of inter-reflections).

    All arguments broadcast, dimensionless. ``R_out^b R_in`` must be < 1 (else ``ValueError``).
    """
    loop_gain = r_out_b * r_in_f
    check_range(loop_gain, "r_out_b * r_in_f", high=1.0, high_inclusive=False)
    return r_out_f + t_out_f * r_in_f * t_out_b / (1.0 - loop_gain)


@array_api("c_m", "beta_m", "c_h_in", "c_h_out", "wavelengths_nm")
def subsurface_albedo(
    c_m: torch.Tensor,
    beta_m: torch.Tensor,
    c_h_in: torch.Tensor,
    c_h_out: torch.Tensor,
    wavelengths_nm: torch.Tensor,
    constants: SkinLayerConstants = SkinLayerConstants(),
) -> torch.Tensor:
    """Spectral total diffuse reflectance ``R_bar`` of the two-layer skin, ``(..., L)``, dimensionless.

    Args and ranges as in :func:`layer_optics`. Differentiable in the four parameters.
    ``SpectralCalibration.integrate(subsurface_albedo(...))`` gives the 6-channel ``rho_sss_bar``.
    """
    if wavelengths_nm.ndim != 1:
        raise ValueError(
            f"argument 'wavelengths_nm' must be 1-D (L,); got shape {tuple(wavelengths_nm.shape)}"
        )
    c_m, beta_m, c_h_in, c_h_out = _check_parameters(c_m, beta_m, c_h_in, c_h_out)
    return subsurface_albedo_unchecked(c_m, beta_m, c_h_in, c_h_out, wavelengths_nm, constants)


def subsurface_albedo_unchecked(c_m, beta_m, c_h_in, c_h_out, wavelengths_nm, constants) -> torch.Tensor:
    """Unchecked core of :func:`subsurface_albedo` (for inner loops of fits)."""
    optics = layer_optics_unchecked(c_m, beta_m, c_h_in, c_h_out, wavelengths_nm, constants)
    return _compose(*layer_totals_unchecked(*optics, constants))
