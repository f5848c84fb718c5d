"""Spectral grid, the rig's six-channel spectral calibration, and spectral -> sRGB previews.

The rig (paper Sec. 4, Fig. responsefunction) films through Dolby/Infitec 3D-glasses filters: camera
1 behind the eye that passes the *upper* half of each of the B, G, R bands, camera 2 behind the eye
that passes the *lower* halves, giving six channels. A :class:`SpectralCalibration` stores, on a
wavelength grid (nm), each channel's relative response (camera sensitivity x filter) and the LED's
relative spectral power; :meth:`SpectralCalibration.integrate` maps spectral reflectance ``(..., L)``
to the six channels ``(..., 6)`` with weights ``response x LED``, each row normalised to sum 1 on the
grid (a perfect white reflector gives exactly 1 per channel).

The default (:func:`default_spectral_calibration`) is a documented stand-in, replaceable by measured
curves: CIE LED-B5 (CIE 015:2018, CCT about 6600 K) for the paper's 6500 K Cree LED, the NPL-measured
Nikon D5100 RGB sensitivity (Darrodi et al. 2015) for the Sony IMX250MYR, and smooth comb filters for
the Dolby glasses: **no measured Dolby/Infitec transmission data exists in this project**; the bands
below are a model (logistic edges, 5 nm, peak transmission 0.9):

* upper eye (camera 1): B 455-495, G 540-590, R 615-720 nm;
* lower eye (camera 2): B 400-455, G 495-540, R 575-620 nm (overlapping around 575-620 nm).

Grid responses are box averages of 1 nm curves over each grid point's bin (edges halfway between
grid points). Bundled data: ``polarface/data/spectra`` (see its README).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from importlib import resources
from typing import Any

import numpy as np
import torch

from polarface._validation import as_float_tensor, check_last_dim, check_range
from polarface.skin.chromophores import interpolate_table

__all__ = [
    "CHANNEL_NAMES",
    "DEFAULT_WAVELENGTHS_NM",
    "DOLBY_LOWER_BANDS_NM",
    "DOLBY_UPPER_BANDS_NM",
    "FINE_WAVELENGTHS_NM",
    "SpectralCalibration",
    "bin_average",
    "bin_edges",
    "channel_responses",
    "cie_illuminant",
    "default_spectral_calibration",
    "default_wavelengths",
    "load_spectral_table",
    "rig_spectral_parts",
    "spectrum_to_srgb",
]

#: Default spectral grid of the paper: 15 wavelengths, 420..700 nm in 20 nm steps.
DEFAULT_WAVELENGTHS_NM: tuple[float, ...] = tuple(float(w) for w in range(420, 701, 20))
#: Default channel order: camera 1 (upper half bands) R, G, B, then camera 2 (lower halves) R, G, B.
CHANNEL_NAMES: tuple[str, ...] = (
    "red_upper",
    "green_upper",
    "blue_upper",
    "red_lower",
    "green_lower",
    "blue_lower",
)
#: Modelled Dolby/Infitec pass bands (nm) of the two eyes, (B, G, R) each.
DOLBY_UPPER_BANDS_NM = ((455.0, 495.0), (540.0, 590.0), (615.0, 720.0))
DOLBY_LOWER_BANDS_NM = ((400.0, 455.0), (495.0, 540.0), (575.0, 620.0))
_EDGE_WIDTH_NM = 5.0
_PEAK_TRANSMISSION = 0.9
#: XYZ -> linear sRGB (IEC 61966-2-1, D65 white).
_XYZ_TO_SRGB = ((3.2406, -1.5372, -0.4986), (-0.9689, 1.8758, 0.0415), (0.0557, -0.2040, 1.0570))


def default_wavelengths(
    dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> torch.Tensor:
    """``(15,)`` tensor of :data:`DEFAULT_WAVELENGTHS_NM` in nm."""
    return torch.tensor(DEFAULT_WAVELENGTHS_NM, dtype=dtype, device=device)


@functools.lru_cache(maxsize=8)
def load_spectral_table(filename: str) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Read a bundled CSV of ``polarface/data/spectra``: (wavelengths nm, {column: values})."""
    path = resources.files("polarface") / "data" / "spectra" / filename
    with path.open("r", encoding="utf-8") as handle:
        header = handle.readline().strip().split(",")
        data = np.loadtxt(handle, delimiter=",", ndmin=2)
    return data[:, 0].copy(), {name: data[:, i + 1].copy() for i, name in enumerate(header[1:])}


def bin_edges(grid: np.ndarray) -> np.ndarray:
    """``(L + 1,)`` edges of the bins of a grid's wavelengths: half way between neighbours, the ends as far
    out as the first and last half steps."""
    mids = 0.5 * (grid[1:] + grid[:-1])
    first = grid[0] - (mids[0] - grid[0]) if grid.size > 1 else grid[0] - 0.5
    last = grid[-1] + (grid[-1] - mids[-1]) if grid.size > 1 else grid[-1] + 0.5
    return np.concatenate([[first], mids, [last]])


def bin_average(table_nm: np.ndarray, values: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Average of a tabulated curve (linear interpolation, zero outside) over each grid bin."""
    edges = bin_edges(grid)
    fine = np.arange(edges[0], edges[-1] + 1e-9, 0.5)
    curve = np.interp(fine, table_nm, values, left=0.0, right=0.0)
    index = np.clip(np.searchsorted(edges, fine, side="right") - 1, 0, grid.size - 1)
    sums = np.bincount(index, weights=curve, minlength=grid.size)
    counts = np.bincount(index, minlength=grid.size)
    return sums / np.maximum(counts, 1)


def cie_illuminant(name: str, wavelengths_nm: Sequence[float] | np.ndarray) -> np.ndarray:
    """Relative SPD of a bundled CIE illuminant (``"D65"``, ``"LED-B5"``, ... ``"LED-V2"``) on a grid (nm).

    Returns ``(L,)`` float64, bin-averaged on the grid and scaled to a maximum of 1.
    """
    grid = np.asarray(wavelengths_nm, dtype=np.float64)
    if name == "D65":
        table_nm, columns = load_spectral_table("cie_d65_relative_spd.csv")
    else:
        table_nm, columns = load_spectral_table("cie_2018_led_illuminants_relative_spd.csv")
    if name not in columns:
        known = ["D65", *load_spectral_table("cie_2018_led_illuminants_relative_spd.csv")[1]]
        raise ValueError(f"unknown illuminant '{name}'; bundled: {', '.join(known)}")
    if grid.min() < table_nm[0] or grid.max() > table_nm[-1]:
        raise ValueError(
            f"wavelengths_nm must lie in {table_nm[0]:g}-{table_nm[-1]:g} nm for illuminant {name}"
        )
    spd = bin_average(table_nm, columns[name], grid)
    return spd / spd.max()


@dataclasses.dataclass(frozen=True)
class SpectralCalibration:
    """The rig's spectral calibration: six channel responses and the LED spectrum on a grid.

    Attributes:
        wavelengths_nm: ``(L,)`` increasing wavelengths, nm (float64 tensor).
        channel_names: six channel names (camera 1 upper halves R, G, B; camera 2 lower halves).
        channel_responses: ``(6, L)`` relative responses (camera sensitivity x Dolby filter), >= 0.
        led_spd: ``(L,)`` relative spectral power of the LED, >= 0.
    """

    wavelengths_nm: torch.Tensor
    channel_names: tuple[str, ...]
    channel_responses: torch.Tensor
    led_spd: torch.Tensor

    def __post_init__(self) -> None:
        wl = as_float_tensor(self.wavelengths_nm, "wavelengths_nm", dtype=torch.float64)
        responses = as_float_tensor(self.channel_responses, "channel_responses", dtype=torch.float64)
        led = as_float_tensor(self.led_spd, "led_spd", dtype=torch.float64)
        names = tuple(str(n) for n in self.channel_names)
        if wl.ndim != 1 or wl.numel() < 2 or bool((wl[1:] <= wl[:-1]).any()):
            raise ValueError("'wavelengths_nm' must be a strictly increasing 1-D grid of >= 2 values")
        if len(names) != 6 or len(set(names)) != 6:
            raise ValueError(f"'channel_names' must be 6 distinct names; got {names}")
        if tuple(responses.shape) != (6, wl.numel()):
            raise ValueError(f"'channel_responses' must be (6, {wl.numel()}); got {tuple(responses.shape)}")
        if tuple(led.shape) != (wl.numel(),):
            raise ValueError(f"'led_spd' must be ({wl.numel()},); got {tuple(led.shape)}")
        check_range(responses, "channel_responses", 0.0)
        check_range(led, "led_spd", 0.0)
        if bool(((responses * led).sum(-1) <= 0).any()):
            raise ValueError("every channel needs a positive response x LED somewhere on the grid")
        object.__setattr__(self, "wavelengths_nm", wl)
        object.__setattr__(self, "channel_responses", responses)
        object.__setattr__(self, "led_spd", led)
        object.__setattr__(self, "channel_names", names)

    @property
    def weights(self) -> torch.Tensor:
        """``(6, L)`` integration weights ``response x LED``, each row summing to 1."""
        raw = self.channel_responses * self.led_spd
        return raw / raw.sum(-1, keepdim=True)

    def integrate(self, spectrum: Any) -> Any:
        """Camera-channel values ``(..., 6)`` of spectral reflectance ``(..., L)`` on this grid.

        Torch in (any float dtype/device, differentiable) -> torch out; numpy in -> numpy out.
        A reflectance of 1 at every wavelength gives exactly 1 in every channel.
        """
        is_torch = isinstance(spectrum, torch.Tensor)
        values = as_float_tensor(spectrum, "spectrum")
        check_last_dim(values, "spectrum", self.wavelengths_nm.numel())
        result = values @ self.weights.to(dtype=values.dtype, device=values.device).T
        return result if is_torch else result.numpy()

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form (lists of floats)."""
        return {
            "wavelengths_nm": self.wavelengths_nm.tolist(),
            "channel_names": list(self.channel_names),
            "channel_responses": self.channel_responses.tolist(),
            "led_spd": self.led_spd.tolist(),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SpectralCalibration:
        """Inverse of :meth:`to_dict`; raises ``ValueError`` naming a missing or bad field."""
        missing = [
            k for k in ("wavelengths_nm", "channel_names", "channel_responses", "led_spd") if k not in data
        ]
        if missing:
            raise ValueError(f"spectral calibration is missing field(s): {', '.join(missing)}")
        return cls(
            wavelengths_nm=data["wavelengths_nm"],
            channel_names=tuple(data["channel_names"]),
            channel_responses=data["channel_responses"],
            led_spd=data["led_spd"],
        )

    def resampled(self, wavelengths_nm: Any) -> SpectralCalibration:
        """The calibration linearly interpolated onto another grid inside this one's range (nm)."""
        grid = as_float_tensor(wavelengths_nm, "wavelengths_nm", dtype=torch.float64)
        table = self.wavelengths_nm.numpy()
        responses = interpolate_table(grid, table, self.channel_responses.T.numpy()).T
        led = interpolate_table(grid, table, self.led_spd.numpy())
        return SpectralCalibration(grid, self.channel_names, responses.contiguous(), led)


def _comb_filter(fine_nm: np.ndarray, bands: Sequence[tuple[float, float]]) -> np.ndarray:
    transmission = np.zeros_like(fine_nm)
    for low, high in bands:
        rise = 1.0 / (1.0 + np.exp(-(fine_nm - low) / _EDGE_WIDTH_NM * 4.0))
        fall = 1.0 / (1.0 + np.exp((fine_nm - high) / _EDGE_WIDTH_NM * 4.0))
        transmission = np.maximum(transmission, rise * fall)
    return _PEAK_TRANSMISSION * transmission


#: The 1-nm grid of :func:`rig_spectral_parts` (nm).
FINE_WAVELENGTHS_NM = np.arange(380.0, 780.0 + 1e-9, 1.0)


def rig_spectral_parts(
    camera_shift_nm: Sequence[float] = (0.0, 0.0, 0.0), filter_shift_nm: Sequence[float] = (0.0, 0.0)
) -> tuple[np.ndarray, np.ndarray]:
    """The parts of the default rig's channels on :data:`FINE_WAVELENGTHS_NM` (``(F,)``, 1 nm): the
    camera's R, G, B sensitivity (Nikon D5100) and the two Dolby filters' transmittance (upper eye,
    lower eye), each shifted by its ``camera_shift_nm`` (R, G, B) or ``filter_shift_nm`` (upper, lower)
    towards longer wavelengths (a simulated rig that differs from its nominal one,
    :mod:`polarface.simulate.rig_perturbation`). Returns ``(camera (3, F), filters (2, F))`` float64."""
    fine = FINE_WAVELENGTHS_NM
    cam_nm, cam = load_spectral_table("camera_sensitivity_nikon_d5100_npl.csv")
    camera = np.stack([np.interp(fine - float(shift), cam_nm, cam[colour])
                       for colour, shift in zip(("red", "green", "blue"), camera_shift_nm, strict=True)])
    filters = np.stack([_comb_filter(fine - float(shift), bands) for bands, shift in
                        zip((DOLBY_UPPER_BANDS_NM, DOLBY_LOWER_BANDS_NM), filter_shift_nm, strict=True)])
    return camera, filters


def channel_responses(camera: np.ndarray, filters: np.ndarray, fine_nm: np.ndarray,
                      wavelengths_nm: Sequence[float] | np.ndarray) -> np.ndarray:
    """The six channel responses ``(6, L)`` on ``wavelengths_nm`` (channel order :data:`CHANNEL_NAMES`)
    from a camera's ``(3, F)`` R, G, B sensitivity and the ``(2, F)`` upper and lower filters on
    ``fine_nm``: each product averaged over each grid wavelength's bin, scaled to a maximum of 1."""
    grid = np.asarray(wavelengths_nm, dtype=np.float64)
    responses = np.stack([bin_average(fine_nm, camera[colour] * filters[eye], grid)
                          for eye in (0, 1) for colour in (0, 1, 2)])
    return responses / responses.max()


def default_spectral_calibration(
    wavelengths_nm: Sequence[float] | np.ndarray = DEFAULT_WAVELENGTHS_NM,
) -> SpectralCalibration:
    """The documented default calibration (module docstring) on ``wavelengths_nm`` (380-780 nm).

    Channels: camera 1 = Nikon D5100 R, G, B x upper-eye comb; camera 2 = R, G, B x lower-eye comb
    (:func:`rig_spectral_parts`, :func:`channel_responses`). LED: CIE LED-B5. Responses are scaled to a
    maximum of 1.
    """
    grid = np.asarray(wavelengths_nm, dtype=np.float64)
    if grid.ndim != 1 or grid.min() < 380 or grid.max() > 780:
        raise ValueError("wavelengths_nm must be a 1-D grid inside 380-780 nm (bundled camera data range)")
    camera, filters = rig_spectral_parts()
    return SpectralCalibration(
        torch.from_numpy(grid.copy()),
        CHANNEL_NAMES,
        torch.from_numpy(channel_responses(camera, filters, FINE_WAVELENGTHS_NM, grid)),
        torch.from_numpy(cie_illuminant("LED-B5", grid)),
    )


def spectrum_to_srgb(spectrum: Any, wavelengths_nm: Any, illuminant: str | Any = "D65") -> tuple[Any, Any]:
    """sRGB preview of spectral reflectance via the CIE 1931 2-degree observer.

    ``XYZ = sum S I cmf / sum I y_bar`` (a perfect white reflector has Y = 1), then the IEC 61966-2-1
    matrix to linear sRGB (no chromatic adaptation: a non-D65 illuminant tints the white), then the
    sRGB transfer curve on values clipped to [0, 1].

    Args:
        spectrum: ``(..., L)`` reflectance on ``wavelengths_nm``.
        wavelengths_nm: ``(L,)`` grid in nm inside 360-780.
        illuminant: a bundled CIE illuminant name (``"D65"``, ``"LED-B5"``, ...) or an ``(L,)`` SPD.

    Returns:
        ``(linear_srgb, encoded_srgb)``, each ``(..., 3)``; torch in -> torch out, else numpy.
    """
    is_torch = isinstance(spectrum, torch.Tensor)
    values = as_float_tensor(spectrum, "spectrum")
    grid = as_float_tensor(wavelengths_nm, "wavelengths_nm", dtype=torch.float64).cpu().numpy()
    if grid.ndim != 1:
        raise ValueError("argument 'wavelengths_nm' must be 1-D")
    check_last_dim(values, "spectrum", grid.size)
    if isinstance(illuminant, str):
        spd = cie_illuminant(illuminant, grid)
    else:
        spd = as_float_tensor(illuminant, "illuminant", dtype=torch.float64).cpu().numpy()
        if spd.shape != grid.shape:
            raise ValueError(f"'illuminant' must have shape {grid.shape}; got {spd.shape}")
        check_range(torch.from_numpy(spd), "illuminant", 0.0)
    cmf_nm, cmf = load_spectral_table("cie_1931_2deg_cmf.csv")
    if grid.min() < cmf_nm[0] or grid.max() > cmf_nm[-1]:
        raise ValueError(f"wavelengths_nm must lie in {cmf_nm[0]:g}-{cmf_nm[-1]:g} nm for the CIE 1931 CMFs")
    xyz_bar = np.stack([bin_average(cmf_nm, cmf[k], grid) for k in ("x_bar", "y_bar", "z_bar")])  # (3, L)
    weights = xyz_bar * spd / float((xyz_bar[1] * spd).sum())
    matrix = np.asarray(_XYZ_TO_SRGB) @ weights  # (3, L)
    linear = values @ torch.as_tensor(matrix.T, dtype=values.dtype, device=values.device)
    clipped = linear.clamp(0.0, 1.0)
    encoded = torch.where(
        clipped <= 0.0031308, 12.92 * clipped, 1.055 * clipped.clamp_min(1e-12) ** (1.0 / 2.4) - 0.055
    )
    if is_torch:
        return linear, encoded
    return linear.numpy(), encoded.numpy()
