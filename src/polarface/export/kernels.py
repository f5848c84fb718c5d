"""Diffusion-kernel export (``polarface export --format kernels``): sum-of-Gaussians profiles per cluster.

For real-time separable subsurface scattering (``docs/export.md``, section "Diffusion kernels"). The
masked texels are clustered by their chromophores (k-means on z-scored ``c_m, beta_m, c_h_in, c_h_out``,
deterministic seed); for each cluster centre and each camera channel the total diffuse reflectance
profile ``R_c(r)`` (mm^-2) is the one polarface's renderer applies to homogeneous skin of those
chromophores (:func:`polarface.skin.render_layered_subsurface`, one blurred inter-reflection as the
renderer and the biophysical fine stage use it): with the layer totals ``R_f, T_f, R_b, T_b, R_in`` of
:func:`polarface.skin.layer_totals` and the fine stage's normalised layer shapes ``G_X`` of
``maps/sog.json``,

    R_l(r) = R_f G_Rf(r) + T_f R_in T_b / (1 - R_b R_in) (G_Tb * G_Rin * G_Tf)(r)

per wavelength ``l`` (``*``: 2-D convolution; Gaussians convolve by adding variances), integrated into
channels with the rig's white-normalised weights (``SpectralCalibration.weights``). This composite
(``exact_*`` in the NPZ: every variance ``v_a + v_b + v_c`` of the triple products) is then fitted onto
the fine stage's nine variances ``4^j (0.01 mm)^2`` with :func:`polarface.skin.fit_sog` and rescaled so
that the weights sum to the exact total albedo (energy kept; the fit's relative error is recorded).

Files in the format's folder: ``kernels.json`` (``KERNELS_FORMAT``) and ``kernels.npz``; read both back
with :func:`load_kernels`.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from polarface.export.formats import ExportOptions
from polarface.export.source import ExportSource
from polarface.io import atomic_path, record_path, write_json_atomic
from polarface.results import layout
from polarface.skin.layers import CHROMOPHORE_NAMES, SkinLayerConstants

__all__ = [
    "KERNELS_FORMAT",
    "KERNELS_VERSION",
    "DiffusionKernels",
    "cluster_chromophores",
    "composite_profile_weights",
    "load_kernels",
    "write_kernels",
]

KERNELS_FORMAT = "polarface-kernels"
KERNELS_VERSION = 1
KERNELS_JSON = "kernels.json"
KERNELS_NPZ = "kernels.npz"
_RGB_NAMES = ("red", "green", "blue")
_MODEL = (
    "R_c(r) = sum_k weights[c][k] * exp(-r^2 / (2 variances_mm2[k])) / (2 pi variances_mm2[k]); r in mm, "
    "R in mm^-2 (radiant exitance per unit incident power), sum_k weights[c][k] = total diffuse albedo of "
    "channel c (no Fresnel factors, as rho_sss_bar)"
)


@dataclasses.dataclass(frozen=True, eq=False)
class DiffusionKernels:
    """The exported kernels (:func:`load_kernels`).

    Attributes:
        channel_names: the ``C`` = 6 camera channels.
        variances_mm2: ``(N,)`` float64 variances of the Gaussians, mm^2.
        weights: ``(K, C, N)`` float64 weights per cluster and channel (dimensionless).
        weights_rgb: ``(K, 3, N)`` weights of linear RGB (mean of each colour's two half bands).
        centres: ``(K, 4)`` chromophores of the cluster centres (``chromophore_names`` order).
        texel_counts: ``(K,)`` masked texels per cluster.
        cluster_map: ``(H, W)`` int16 cluster of every texel (RESULT texture layout), -1 outside the mask.
        chromophore_names: ``("c_m", "beta_m", "c_h_in", "c_h_out")``.
    """

    channel_names: tuple[str, ...]
    variances_mm2: np.ndarray
    weights: np.ndarray
    weights_rgb: np.ndarray
    centres: np.ndarray
    texel_counts: np.ndarray
    cluster_map: np.ndarray
    chromophore_names: tuple[str, ...] = CHROMOPHORE_NAMES

    @property
    def albedo(self) -> np.ndarray:
        """``(K, C)`` total diffuse albedo per cluster and channel (sum of the weights)."""
        return self.weights.sum(-1)

    def profile(self, cluster: int, r_mm: np.ndarray, rgb: bool = False) -> np.ndarray:
        """``(C, R)`` (``(3, R)`` with ``rgb``) profile ``R(r)`` in mm^-2 of ``cluster`` at radii ``r_mm``."""
        weights = (self.weights_rgb if rgb else self.weights)[cluster]
        r = np.asarray(r_mm, dtype=np.float64)
        v = self.variances_mm2[:, None]
        return weights @ (np.exp(-(r[None] ** 2) / (2.0 * v)) / (2.0 * math.pi * v))


def cluster_chromophores(values: np.ndarray, clusters: int, seed: int = 0, iterations: int = 50,
                         sample: int = 20000) -> tuple[np.ndarray, np.ndarray]:
    """k-means of ``values`` ``(M, D)`` (z-scored per column; k-means++ start from ``seed``; Lloyd steps
    until the labels settle or ``iterations``; centres found on a ``sample`` of the rows drawn with
    ``seed``, then every row gets its nearest centre). Empty clusters are dropped.

    Returns:
        ``(labels (M,) int64 in [0, K'), centres (K', D))`` with ``K' <= clusters``; centres are the
        members' means in the units of ``values``, ordered by decreasing member count.
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 2 or len(values) == 0:
        raise ValueError(f"argument 'values' must be a non-empty (M, D) array; got {values.shape}")
    if int(clusters) < 1:
        raise ValueError(f"argument 'clusters' must be >= 1; got {clusters}")
    spread = values.std(axis=0)
    features = (values - values.mean(axis=0)) / np.where(spread > 0, spread, 1.0)
    rng = np.random.default_rng(seed)
    rows = features[np.sort(rng.choice(len(features), sample, replace=False))] if len(features) > sample \
        else features
    centres = rows[[int(rng.integers(len(rows)))]]
    while len(centres) < min(int(clusters), len(rows)):  # k-means++ seeding
        nearest = _squared_distances(rows, centres).min(axis=1).clip(min=0.0)
        if nearest.sum() <= 0:
            break
        centres = np.vstack([centres, rows[rng.choice(len(rows), p=nearest / nearest.sum())]])
    labels = np.full(len(rows), -1)
    for _ in range(iterations):
        new = _squared_distances(rows, centres).argmin(axis=1)
        if np.array_equal(new, labels):
            break
        labels = new
        counts = np.bincount(labels, minlength=len(centres))
        sums = np.stack([np.bincount(labels, column, minlength=len(centres)) for column in rows.T], 1)
        centres = np.where(counts[:, None] > 0, sums / np.maximum(counts, 1)[:, None], centres)
    labels = _squared_distances(features, centres).argmin(axis=1)
    sizes = np.bincount(labels, minlength=len(centres))
    order = [k for k in np.argsort(-sizes, kind="stable") if sizes[k] > 0]
    remap = np.full(len(centres), -1)
    remap[order] = np.arange(len(order))
    labels = remap[labels]
    return labels, np.stack([values[labels == k].mean(0) for k in range(len(order))])


def _squared_distances(points: np.ndarray, centres: np.ndarray) -> np.ndarray:
    return (points**2).sum(1)[:, None] - 2.0 * points @ centres.T + (centres**2).sum(1)[None]


def composite_profile_weights(centre: np.ndarray, shapes, wavelengths_nm: np.ndarray,
                              channel_weights: np.ndarray, variances_mm2: np.ndarray,
                              constants: SkinLayerConstants = SkinLayerConstants()  # noqa: B008
                              ) -> tuple[np.ndarray, np.ndarray]:
    """The renderer's exact homogeneous profile of chromophores ``centre`` ``(4,)`` as a SoG per channel.

    Args:
        shapes: :class:`polarface.skin.ProfileShapes` of ``(L, J)`` normalised weights (``sog.json``).
        wavelengths_nm: ``(L,)`` grid of ``shapes``; channel_weights: ``(C, L)`` integration weights.
        variances_mm2: ``(J,)`` variances of ``shapes``.

    Returns:
        ``(variances (M,) mm^2, weights (C, M))``: every single variance (the ``R_f`` lobe) and every
        sum of three (the inner path), duplicates merged; ``weights.sum(-1)`` is the local
        ``sum_l W_cl R_bar_l`` exactly.
    """
    import torch

    from polarface.skin.layers import layer_optics, layer_totals

    params = [torch.tensor([float(c)], dtype=torch.float64) for c in centre]
    grid = torch.as_tensor(np.asarray(wavelengths_nm, dtype=np.float64))
    totals = [t[0].numpy() for t in layer_totals(*layer_optics(*params, grid, constants), constants)]
    r_f, t_f, r_b, t_b, r_in = totals  # each (L,)
    inner = t_f * r_in * t_b / (1.0 - r_b * r_in)
    a, x, y, z = (np.asarray(getattr(shapes, k), dtype=np.float64) for k in ("r_out_f", "t_out_f",
                                                                            "r_in_f", "t_out_b"))
    v = np.asarray(variances_mm2, dtype=np.float64)
    triple = np.einsum("la,lb,lc->labc", x, y, z).reshape(len(grid), -1) * inner[:, None]
    triple_v = (v[:, None, None] + v[None, :, None] + v[None, None, :]).reshape(-1)
    all_v = np.concatenate([v, triple_v])
    all_w = np.concatenate([a * r_f[:, None], triple], axis=1)  # (L, J + J^3)
    merged, index = np.unique(np.round(all_v, 12), return_inverse=True)
    spectral = np.zeros((len(grid), len(merged)))
    np.add.at(spectral.T, index, all_w.T)
    return merged, np.asarray(channel_weights, dtype=np.float64) @ spectral


def _ladder_fit(exact_v: np.ndarray, exact_w: np.ndarray, ladder_v: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Weights ``(..., J)`` on ``ladder_v`` fitted to composite profiles ``exact_w`` ``(..., M)`` on
    ``exact_v`` (:func:`polarface.skin.fit_sog`), rescaled to the exact totals; their relative errors."""
    import torch

    from polarface.skin.sog import default_radial_grid, fit_sog, sog_profile

    r = default_radial_grid()
    exact = sog_profile(torch.from_numpy(exact_w), r, torch.from_numpy(exact_v))
    fitted = fit_sog(r, exact, torch.from_numpy(ladder_v)).weights.numpy()
    sums = fitted.sum(-1, keepdims=True)
    weights = fitted * exact_w.sum(-1, keepdims=True) / np.where(sums > 0, sums, 1.0)
    rescaled = sog_profile(torch.from_numpy(weights), r, torch.from_numpy(ladder_v))
    step = r[1:] - r[:-1]
    measure = torch.zeros_like(r)
    measure[1:] += 0.5 * step
    measure[:-1] += 0.5 * step
    measure = measure * r  # r dr, the fit's own objective
    error = torch.sqrt((((rescaled - exact) ** 2) * measure).sum(-1) / ((exact**2) * measure).sum(-1))
    return weights, error.numpy()


def _checked_sog(source: ExportSource) -> tuple[Any, np.ndarray, np.ndarray]:
    """``(shapes, wavelengths (L,), variances (J,))`` of ``maps/sog.json``; ValueError naming it."""
    from polarface.results.appearance import sog_shapes

    path = source.map_file("sog")
    payload = source.sog
    try:
        shapes = sog_shapes(payload)
        wavelengths = np.asarray(payload["wavelengths_nm"], dtype=np.float64)
        variances = np.asarray(payload["variances_mm2"], dtype=np.float64)
        layers = [np.asarray(getattr(shapes, k)) for k in layout.SOG_LAYERS]
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as exc:
        raise ValueError(f"'{path}' is not a valid {layout.SOG_FORMAT} file ({exc!r})") from None
    expected = (len(wavelengths), len(variances))
    bad = [k for k, w in zip(layout.SOG_LAYERS, layers, strict=True)
           if w.shape != expected or not np.isfinite(w).all() or (w < 0).any()]
    if bad or not (variances > 0).all() or len(variances) == 0:
        raise ValueError(
            f"'{path}': layers {bad or list(layout.SOG_LAYERS)} must be finite non-negative "
            f"(len(wavelengths_nm), len(variances_mm2)) = {expected} arrays and variances_mm2 > 0"
        )
    return shapes, wavelengths, variances


def write_kernels(source: ExportSource, out: Path, options: ExportOptions) -> dict[str, Any]:
    """Write ``kernels.json`` and ``kernels.npz`` of the static result into the folder ``out``.

    Returns:
        ``files``, ``clusters``, ``texels``, the worst ladder fit error and ``lost``.

    Raises:
        ValueError: an empty mask, a malformed ``maps/sog.json`` or a rig without spectral calibration
            (naming the file).
    """
    mask = source.mask
    if not mask.any():
        raise ValueError(f"'{source.map_file(layout.MASK)}' has no valid texel; no kernel to export")
    rig = source.rig
    if rig.spectral is None:
        raise ValueError(f"'{source.folder.rig_path}' has no spectral calibration (needed for channels)")
    shapes, wavelengths, ladder = _checked_sog(source)
    calibration = rig.spectral.to_calibration().resampled(wavelengths)
    channel_weights = calibration.weights.numpy()
    chromophores = np.stack([source.scalar_map(name)[mask] for name in CHROMOPHORE_NAMES], -1)
    labels, centres = cluster_chromophores(chromophores, options.kernel_clusters, seed=0)
    exact = [composite_profile_weights(c, shapes, wavelengths, channel_weights, ladder) for c in centres]
    exact_v = exact[0][0]
    exact_w = np.stack([w for _, w in exact])
    weights, errors = _ladder_fit(exact_v, exact_w, ladder)
    rgb_rows = [[cam.colour_channels[c] for c in "RGB"] for cam in rig.polarimetric_cameras()[:2]]
    weights_rgb = 0.5 * (weights[:, rgb_rows[0]] + weights[:, rgb_rows[1]])
    cluster_map = np.full(mask.shape, -1, dtype=np.int16)
    cluster_map[mask] = labels
    counts = np.bincount(labels, minlength=len(centres))
    names = list(source.channel_names)
    out = Path(out)
    with atomic_path(out / KERNELS_NPZ) as tmp, open(tmp, "wb") as handle:
        np.savez_compressed(
            handle, weights=weights, weights_rgb=weights_rgb, variances_mm2=ladder, centres=centres,
            texel_counts=counts, cluster_map=cluster_map, exact_variances_mm2=exact_v,
            exact_weights=exact_w, fit_relative_error=errors, channel_names=np.array(names),
            chromophore_names=np.array(CHROMOPHORE_NAMES),
        )
    clusters = [
        {
            "index": k,
            "texels": int(counts[k]),
            "centre": dict(zip(CHROMOPHORE_NAMES, centres[k].tolist(), strict=True)),
            "albedo": dict(zip(names, weights[k].sum(-1).tolist(), strict=True)),
            "weights": dict(zip(names, weights[k].tolist(), strict=True)),
            "weights_rgb": dict(zip(_RGB_NAMES, weights_rgb[k].tolist(), strict=True)),
            "fit_relative_error": dict(zip(names, errors[k].tolist(), strict=True)),
        }
        for k in range(len(centres))
    ]
    write_json_atomic(out / KERNELS_JSON, {
        "format": KERNELS_FORMAT,
        "version": KERNELS_VERSION,
        "model": _MODEL,
        "units": {"r": "mm", "variances_mm2": "mm^2", "profile": "mm^-2", "weights": "dimensionless",
                  "centre": "volume fractions"},
        "channel_names": names,
        "rgb_names": list(_RGB_NAMES),
        "chromophore_names": list(CHROMOPHORE_NAMES),
        "variances_mm2": ladder.tolist(),
        "clustering": {"method": "k-means on z-scored chromophores", "requested": options.kernel_clusters,
                       "clusters": len(centres), "seed": 0, "texels": int(mask.sum())},
        "source": {"sog": record_path(out, source.map_file("sog")), "wavelengths_nm": wavelengths.tolist(),
                   "blurred_interreflections": 1, "constants": dataclasses.asdict(SkinLayerConstants())},
        "npz": KERNELS_NPZ,
        "clusters": clusters,
    })
    return {
        "files": [KERNELS_JSON, KERNELS_NPZ],
        "clusters": len(centres),
        "texels": int(mask.sum()),
        "max_fit_relative_error": float(errors.max()),
        "lost": ["per-texel chromophores: one kernel per cluster (cluster_map says which)",
                 "layered transport: the two layers' blurs collapse into one radial profile per channel"],
    }


def load_kernels(path: str | Path) -> DiffusionKernels:
    """Read an exported kernels folder (or its ``kernels.npz`` / ``kernels.json``).

    Raises:
        FileNotFoundError: no ``kernels.npz`` / ``kernels.json`` there. ValueError: not a
            ``polarface-kernels`` file of a known version (naming it).
    """
    path = Path(path)
    folder = path if path.is_dir() else path.parent
    json_path, npz_path = folder / KERNELS_JSON, folder / KERNELS_NPZ
    for required in (json_path, npz_path):
        if not required.is_file():
            raise FileNotFoundError(f"'{required}' does not exist (export with --format kernels)")
    header = json.loads(json_path.read_text(encoding="utf-8"))
    if header.get("format") != KERNELS_FORMAT or header.get("version") != KERNELS_VERSION:
        raise ValueError(f"'{json_path}' is not a {KERNELS_FORMAT} version {KERNELS_VERSION} file")
    with np.load(npz_path, allow_pickle=False) as data:
        return DiffusionKernels(
            channel_names=tuple(str(n) for n in data["channel_names"]),
            variances_mm2=data["variances_mm2"],
            weights=data["weights"],
            weights_rgb=data["weights_rgb"],
            centres=data["centres"],
            texel_counts=data["texel_counts"],
            cluster_map=data["cluster_map"],
            chromophore_names=tuple(str(n) for n in data["chromophore_names"]),
        )
