"""The biophysical stage on a RESULT folder: read rho_sss_bar, fit, write maps, previews and metrics.

Reads (layout in the task's "Reconstruction result folder"): ``maps/rho_sss_bar.exr`` (six channels
named by the rig's spectral calibration), ``maps/mask.png``, ``mesh.obj`` (rest mesh with UVs, mm)
and ``rig.json`` (spectral calibration required). Writes:

* ``maps/c_m.exr``, ``maps/beta_m.exr``, ``maps/c_h_in.exr``, ``maps/c_h_out.exr`` (channel ``Y``,
  volume fractions);
* ``maps/sog.json``: per-layer normalised sum-of-Gaussians weights per wavelength (``(L, 9)`` each),
  the variances (mm^2), wavelengths (nm) and the median parameters they were fitted at;
* ``maps/subsurface_spectral.exr``: the rendered subsurface albedo at each of the L wavelengths
  (channels ``nm420`` ...), ``maps/rho_sss_bar_rendered.exr``: its six-channel integration;
* ``maps/rho_sss_bar_residual.exr``: per texel ``relative`` (``||rendered - input|| / ||input||``) and
  ``gamut_distance`` (the input's distance to the skin model's gamut), ``maps/in_gamut.png`` (255 where
  the input is inside the gamut, :class:`~polarface.inverse.biophysical.BiophysicalConfig`
  ``gamut_tolerance``) and their previews ``previews/rho_sss_bar_residual.png``, ``previews/in_gamut.png``;
* ``previews/c_m.png`` ... (colour maps with scale bars), ``previews/chromophores.png`` (the four maps
  in one panel, like the paper's teaser), ``previews/subsurface_srgb.png`` (sRGB under D65);
* ``result.json``: ``stages.biophysical`` with timings, the re-render relative RMSE against the input
  over all valid texels (``rho_sss_bar_relative_rmse``) and over the in-gamut ones, the gamut floor
  and the number of out-of-gamut texels.

Texel size and per-texel stretch come from the mesh (:func:`polarface.geometry.uv_raster.rasterize_uv`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from polarface.capture.rig import Rig
from polarface.device import resolve_device
from polarface.inverse.biophysical import BiophysicalConfig, BiophysicalFit, fit_biophysical
from polarface.inverse.biophysical.model import PARAMETER_ORDER, TotalsTable, local_channel_albedo
from polarface.io import colormap_png, read_exr, read_png, write_exr, write_json_atomic, write_png

__all__ = [
    "PARAMETER_LABELS",
    "evaluate_biophysical",
    "load_stage_inputs",
    "report_section",
    "run_biophysical_stage",
    "write_previews",
]

LOGGER = logging.getLogger(__name__)

#: Human-readable names and preview colour ranges of the four maps (volume fractions).
PARAMETER_LABELS: dict[str, tuple[str, float, float, str]] = {
    "c_m": ("Melanin C_m", 0.0, 0.15, "copper"),
    "beta_m": ("Eumelanin fraction beta_m", 0.0, 0.3, "cividis"),
    "c_h_in": ("Inner haemoglobin C_h,in", 0.0, 0.08, "Reds"),
    "c_h_out": ("Outer haemoglobin C_h,out", 0.0, 0.2, "Reds"),
}


def _read_mask(path: Path, shape: tuple[int, int]) -> np.ndarray:
    if not path.is_file():
        raise FileNotFoundError(f"mask '{path}' does not exist")
    mask = read_png(path)
    mask = mask[..., 0] if mask.ndim == 3 else mask
    if mask.shape != shape:
        raise ValueError(f"mask '{path}' is {mask.shape}, expected {shape}")
    return mask > (0.5 if mask.dtype.kind == "f" else 127)


def load_stage_inputs(result_dir: str | Path) -> dict[str, Any]:
    """Read and validate the stage's inputs from ``result_dir``.

    Returns:
        dict with ``rho_sss_bar`` ``(H, W, 6)`` float32, ``mask`` ``(H, W)`` bool, ``calibration``
        (``SpectralCalibration``), ``channel_names``, ``rig``, ``texel_size_mm`` (float, median, mm),
        ``stretch`` ``(H, W, 2)`` float32.

    Raises:
        FileNotFoundError: a required file is missing. ValueError: no spectral calibration, channel
        names that do not match it, NaN/inf or values outside [0, 1] in ``rho_sss_bar``.
    """
    from polarface.geometry.mesh import load_mesh
    from polarface.geometry.uv_raster import rasterize_uv

    root = Path(result_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"result folder '{root}' does not exist")
    rig = Rig.load(root / "rig.json")
    if rig.spectral is None:
        raise ValueError(
            f"'{root / 'rig.json'}' has no spectral calibration; the biophysical stage needs the six "
            "channels' responses (rig.spectral)"
        )
    calibration = rig.spectral.to_calibration()
    rho_path = root / "maps" / "rho_sss_bar.exr"
    if not rho_path.is_file():
        raise FileNotFoundError(f"'{rho_path}' does not exist (run the polarimetric stage first)")
    channels = read_exr(rho_path)
    names = list(calibration.channel_names)
    missing = [n for n in names if n not in channels]
    if missing:
        raise ValueError(f"'{rho_path}' lacks channel(s) {missing} of the rig's calibration {names}")
    rho = np.stack([channels[n] for n in names], axis=-1).astype(np.float32)
    mask = _read_mask(root / "maps" / "mask.png", rho.shape[:2])
    values = rho[mask]
    if not np.isfinite(values).all():
        raise ValueError(f"'{rho_path}': rho_sss_bar contains NaN or infinite values inside the mask")
    if values.size and (values.min() < 0.0 or values.max() > 1.0):
        raise ValueError(
            f"'{rho_path}': rho_sss_bar must lie in [0, 1] (a dimensionless albedo); "
            f"got {values.min():.4g}..{values.max():.4g}"
        )
    mesh_path = root / "mesh.obj"
    if not mesh_path.is_file():
        raise FileNotFoundError(f"'{mesh_path}' does not exist")
    raster = rasterize_uv(load_mesh(mesh_path), rho.shape[:2])
    sizes = np.stack([raster.texel_size_u, raster.texel_size_v], axis=-1)
    valid = raster.mask & mask
    texel_size = float(np.median(sizes[valid])) if valid.any() else float(np.median(sizes[raster.mask]))
    stretch = np.where(raster.mask[..., None], np.clip(sizes / texel_size, 0.05, 20.0), 1.0).astype(
        np.float32
    )
    return {
        "rho_sss_bar": rho,
        "mask": mask,
        "calibration": calibration,
        "channel_names": names,
        "rig": rig,
        "texel_size_mm": texel_size,
        "stretch": stretch,
    }


def per_texel_relative_residual(rendered: np.ndarray, observed: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``(H, W)`` float32 per-texel relative residual ``||rendered - observed|| / ||observed||`` (over
    the channels of ``(H, W, C)`` maps), 0 outside ``mask``."""
    norm = np.sqrt((observed.astype(np.float64) ** 2).sum(-1))
    error = np.sqrt(((rendered.astype(np.float64) - observed) ** 2).sum(-1))
    return np.where(mask, error / np.maximum(norm, 1e-12), 0.0).astype(np.float32)


def _write_maps(root: Path, fit: BiophysicalFit, calibration, mask: np.ndarray, observed: np.ndarray) -> None:
    maps = root / "maps"
    params = fit.parameters.numpy()
    for i, name in enumerate(PARAMETER_ORDER):
        write_exr(maps / f"{name}.exr", {"Y": np.where(mask, params[..., i], 0.0)})
    names = list(calibration.channel_names)
    rendered = fit.rendered.numpy()
    write_exr(maps / "rho_sss_bar_rendered.exr", {n: rendered[..., i] for i, n in enumerate(names)})
    write_exr(
        maps / "rho_sss_bar_residual.exr",
        {
            "relative": per_texel_relative_residual(rendered, observed, mask),
            "gamut_distance": np.where(mask, fit.gamut_distance.numpy(), 0.0).astype(np.float32),
        },
    )
    write_png(maps / "in_gamut.png", (fit.in_gamut.numpy() & mask).astype(np.uint8) * 255)
    grid = calibration.wavelengths_nm.tolist()
    spectral = fit.spectral.numpy()
    write_exr(maps / "subsurface_spectral.exr", {f"nm{w:g}": spectral[i] for i, w in enumerate(grid)})
    from polarface.skin.sog import sog_variances

    sog = {
        "format": "polarface-sog",
        "version": 1,
        "wavelengths_nm": grid,
        "variances_mm2": sog_variances().tolist(),
        "normalised": True,
        "layers": {
            name: getattr(fit.shapes, name).tolist()
            for name in ("r_out_f", "t_out_f", "r_out_b", "t_out_b", "r_in_f")
        },
        "relative_fit_error": None
        if fit.shapes.relative_error is None
        else fit.shapes.relative_error.tolist(),
    }
    write_json_atomic(maps / "sog.json", sog)


def load_sog(path: str | Path):
    """Read ``sog.json`` back as a :class:`polarface.skin.heterogeneous.ProfileShapes` (float64)."""
    from polarface.skin.heterogeneous import ProfileShapes

    data = json.loads(Path(path).read_text(encoding="utf-8"))
    layers = data["layers"]
    return ProfileShapes(
        *(
            torch.tensor(layers[k], dtype=torch.float64)
            for k in ("r_out_f", "t_out_f", "r_out_b", "t_out_b", "r_in_f")
        )
    )


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
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from polarface.io.atomic import atomic_path
    from polarface.skin.spectral import spectrum_to_srgb

    out = Path(root) / "previews"
    written = []
    for i, name in enumerate(PARAMETER_ORDER):
        label, low, high, cmap = PARAMETER_LABELS[name]
        written.append(
            colormap_png(
                out / f"{name}.png",
                parameters[..., i],
                vmin=low,
                vmax=high,
                cmap=cmap,
                mask=mask,
                title=label,
                colorbar=True,
            )
        )
    fig, axes = plt.subplots(1, 4, figsize=(16, 4.4), dpi=100)
    for ax, (i, name) in zip(axes, enumerate(PARAMETER_ORDER), strict=True):
        label, low, high, cmap = PARAMETER_LABELS[name]
        shown = np.ma.array(parameters[..., i], mask=~mask)
        handle = ax.imshow(shown, cmap=cmap, vmin=low, vmax=high, interpolation="nearest")
        ax.set_title(label)
        ax.set_axis_off()
        fig.colorbar(handle, ax=ax, fraction=0.046, pad=0.04)
    fig.tight_layout()
    with atomic_path(out / "chromophores.png") as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    written.append(out / "chromophores.png")
    _, srgb = spectrum_to_srgb(np.moveaxis(spectral, 0, -1).astype(np.float64), wavelengths_nm)
    srgb = np.where(mask[..., None], srgb, 0.0)
    written.append(write_png(out / "subsurface_srgb.png", srgb, bit_depth=8))
    return written


def _write_residual_previews(root: Path, fit: BiophysicalFit, mask: np.ndarray, observed: np.ndarray) -> None:
    residual = per_texel_relative_residual(fit.rendered.numpy(), observed, mask)
    colormap_png(
        root / "previews" / "rho_sss_bar_residual.png",
        residual,
        vmin=0.0,
        vmax=0.1,
        cmap="magma",
        mask=mask,
        title="re-render relative residual (clipped at 10 %)",
        colorbar=True,
    )
    # Pixel-exact: grey = input inside the skin gamut, red = outside it, black = not a valid texel.
    in_gamut = fit.in_gamut.numpy() & mask
    preview = np.zeros((*mask.shape, 3), np.uint8)
    preview[in_gamut] = (150, 150, 150)
    preview[mask & ~in_gamut] = (230, 30, 30)
    write_png(root / "previews" / "in_gamut.png", preview)


def run_biophysical_stage(
    result_dir: str | Path,
    config: BiophysicalConfig = BiophysicalConfig(),  # noqa: B008 - frozen dataclass
    device: str | torch.device | None = None,
    progress: bool = True,
    threads: int | None = 1,
) -> dict[str, Any]:
    """Run the biophysical stage on a RESULT folder (module docstring); returns its summary.

    Args:
        result_dir: the RESULT folder (``maps/rho_sss_bar.exr``, ``maps/mask.png``, ``mesh.obj``,
            ``rig.json``).
        config: :class:`BiophysicalConfig` (``albedo_model="local"`` for blur-free inputs).
        device: torch device for the fit (default CPU; the stage is light enough for it).
        progress: show a tqdm progress bar.
        threads: torch intra-op threads during a CPU fit (restored afterwards; ``None`` leaves them).
            Default 1: the fit is many small batched kernels, where a second OpenMP thread costs more
            than it gains on a busy machine - demo preset on the shared 2-core machine (load ~6):
            1 thread 23 s CPU / 35 s wall, 2 threads 101 s CPU / 139 s wall (docs/biophysical.md).

    Raises:
        ValueError: ``threads < 1`` and the input errors of :func:`load_stage_inputs`.

    Returns:
        The summary stored under ``result.json``'s ``stages.biophysical``: timings (s), fit residual,
        texel size, median parameters, configuration.
    """
    if threads is not None and int(threads) < 1:
        raise ValueError(f"argument 'threads' must be >= 1; got {threads}")
    started = time.perf_counter()
    root = Path(result_dir)
    inputs = load_stage_inputs(root)
    calibration = inputs["calibration"]
    table = TotalsTable(calibration.wavelengths_nm, config.constants)
    read_s = time.perf_counter() - started
    target = resolve_device(device) if device is not None else torch.device("cpu")
    steps = 3 + (config.shape_rounds if config.albedo_model == "blurred" else 0)
    previous_threads = torch.get_num_threads()
    if threads is not None and target.type == "cpu":
        torch.set_num_threads(int(threads))
    try:
        with tqdm(total=steps, desc="biophysical", disable=not progress, unit="step") as bar:
            fit = fit_biophysical(
                torch.from_numpy(inputs["rho_sss_bar"]).to(target),
                torch.from_numpy(inputs["mask"]).to(target),
                table,
                calibration.weights.float().to(target),
                inputs["texel_size_mm"],
                config,
                stretch=torch.from_numpy(inputs["stretch"]).to(target),
                progress=lambda name: (bar.set_postfix_str(name), bar.update(1)),
            )
    finally:
        torch.set_num_threads(previous_threads)
    fit = dataclasses.replace(
        fit,
        parameters=fit.parameters.cpu(),
        rendered=fit.rendered.cpu(),
        spectral=fit.spectral.cpu(),
        in_gamut=fit.in_gamut.cpu(),
        gamut_distance=fit.gamut_distance.cpu(),
    )
    write_started = time.perf_counter()
    mask = inputs["mask"]
    _write_maps(root, fit, calibration, mask, inputs["rho_sss_bar"])
    write_previews(
        root, fit.parameters.numpy(), mask, fit.spectral.numpy(), calibration.wavelengths_nm.numpy()
    )
    _write_residual_previews(root, fit, mask, inputs["rho_sss_bar"])
    params = fit.parameters.numpy()[mask]
    out_of_gamut = int(mask.sum() - fit.in_gamut.numpy().sum())
    summary = {
        "albedo_model": config.albedo_model,
        "texel_size_mm": inputs["texel_size_mm"],
        "texels": int(mask.sum()),
        "rho_sss_bar_relative_rmse": fit.residual_rmse,
        "rho_sss_bar_relative_rmse_in_gamut": fit.residual_rmse_in_gamut,
        "gamut_floor_relative_rmse": fit.gamut_floor_rmse,
        "out_of_gamut_texels": out_of_gamut,
        "out_of_gamut_fraction": out_of_gamut / max(int(mask.sum()), 1),
        "median_parameters": {n: float(np.median(params[:, i])) for i, n in enumerate(PARAMETER_ORDER)},
        "timings_s": {
            "read_s": read_s,
            **fit.timings_s,
            "write_s": time.perf_counter() - write_started,
            "total_s": time.perf_counter() - started,
        },
        "torch_threads": int(threads) if threads is not None and target.type == "cpu" else previous_threads,
        "config": {k: v for k, v in vars(config).items() if k != "constants"},
    }
    _update_result_json(root, summary, inputs["channel_names"], mask.shape)
    return summary


def _update_result_json(root: Path, summary: dict, channel_names: list[str], shape: tuple[int, int]) -> None:
    path = root / "result.json"
    data: dict[str, Any] = {}
    if path.is_file():
        data = json.loads(path.read_text(encoding="utf-8"))
    data.setdefault("format", "polarface-result")
    data.setdefault("version", 1)
    data.setdefault("channel_names", channel_names)
    data.setdefault("texture_resolution", list(shape))
    data.setdefault("texel_size_mm", summary["texel_size_mm"])
    data.setdefault("stages", {})["biophysical"] = summary
    write_json_atomic(path, data)


def _relative_rmse(estimate: np.ndarray, reference: np.ndarray) -> float:
    return float(np.sqrt(np.mean((estimate - reference) ** 2)) / max(np.sqrt(np.mean(reference**2)), 1e-12))


def evaluate_biophysical(result_dir: str | Path, gt_dir: str | Path) -> dict[str, Any]:
    """Chromophore errors of a RESULT against simulator ground truth, and re-render errors.

    Args:
        result_dir: RESULT folder after the biophysical stage.
        gt_dir: the simulator's ``SIM/ground_truth`` folder (or ``SIM`` itself).

    All relative RMSEs are ``||a - b|| / ||b||`` over texels and channels, over **all** texels valid in
    both masks (``texels``) unless the key says otherwise.

    Returns:
        ``{"texels": N, "c_m": {"median_abs", "mean_abs", "p95_abs"}, ... (the four maps),``

        * ``"rho_sss_bar_relative_rmse"`` - the issue's "re-rendered rho_sss_bar relative RMSE": the
          stage's own re-render (``maps/rho_sss_bar_rendered.exr``, the model it fitted) against
          the albedo it was given (``maps/rho_sss_bar.exr``): its ability to reproduce its input.
          (Before issue 7's follow-up this key held ``rerender_vs_gt_relative_rmse``.)
        * ``"rho_sss_bar_relative_rmse_in_gamut"`` - the same over the texels whose input lies inside
          the skin model's gamut (``maps/in_gamut.png``), and ``"out_of_gamut_texels"``;
        * ``"gamut_floor_relative_rmse"`` (from ``result.json``): the input's own distance to the
          gamut, a floor no chromophore map can beat under the local model;
        * ``"rerender_vs_gt_relative_rmse"`` - the recovered maps rendered with the **local** model
          against the ground-truth local ``rho_sss_bar`` (both stages' errors together), and
          ``"input_vs_gt_relative_rmse"`` - the input itself against it (the polarimetric stage's
          error; with ground-truth input it is 0);
        * ``"fit_relative_rmse"`` - alias of ``rho_sss_bar_relative_rmse`` (older name).}
    """
    root, gt = Path(result_dir), Path(gt_dir)
    if (gt / "ground_truth").is_dir():
        gt = gt / "ground_truth"
    inputs_rig = Rig.load(root / "rig.json")
    if inputs_rig.spectral is None:
        raise ValueError(f"'{root / 'rig.json'}' has no spectral calibration")
    calibration = inputs_rig.spectral.to_calibration()
    names = list(calibration.channel_names)
    estimate = {n: read_exr(root / "maps" / f"{n}.exr")["Y"] for n in PARAMETER_ORDER}
    truth = {n: read_exr(gt / "maps" / f"{n}.exr")["Y"] for n in PARAMETER_ORDER}
    shape = estimate["c_m"].shape
    if truth["c_m"].shape != shape:
        raise ValueError(f"resolution mismatch: result {shape}, ground truth {truth['c_m'].shape}")
    mask = _read_mask(root / "maps" / "mask.png", shape) & _read_mask(gt / "maps" / "mask.png", shape)
    metrics: dict[str, Any] = {"texels": int(mask.sum())}
    for name in PARAMETER_ORDER:
        error = np.abs(estimate[name][mask] - truth[name][mask])
        metrics[name] = {
            "median_abs": float(np.median(error)),
            "mean_abs": float(np.mean(error)),
            "p95_abs": float(np.percentile(error, 95)),
        }
    table = TotalsTable(calibration.wavelengths_nm)
    params = torch.from_numpy(np.stack([estimate[n][mask] for n in PARAMETER_ORDER], -1).astype(np.float64))
    rendered = local_channel_albedo(params, table, calibration.weights).numpy()
    gt_rho = read_exr(gt / "maps" / "rho_sss_bar.exr")
    reference = np.stack([gt_rho[n][mask] for n in names], -1)
    observed_maps = read_exr(root / "maps" / "rho_sss_bar.exr")
    observed = np.stack([observed_maps[n][mask] for n in names], -1)
    own = root / "maps" / "rho_sss_bar_rendered.exr"
    if not own.is_file():
        raise FileNotFoundError(f"'{own}' does not exist (run the biophysical stage first)")
    fitted_maps = read_exr(own)
    fitted = np.stack([fitted_maps[n][mask] for n in names], -1)
    metrics["rho_sss_bar_relative_rmse"] = _relative_rmse(fitted, observed)
    metrics["fit_relative_rmse"] = metrics["rho_sss_bar_relative_rmse"]
    gamut_path = root / "maps" / "in_gamut.png"
    if gamut_path.is_file():
        in_gamut = _read_mask(gamut_path, shape)[mask]
        metrics["out_of_gamut_texels"] = int((~in_gamut).sum())
        metrics["rho_sss_bar_relative_rmse_in_gamut"] = (
            _relative_rmse(fitted[in_gamut], observed[in_gamut]) if in_gamut.any() else float("nan")
        )
    summary = {}
    if (root / "result.json").is_file():
        summary = json.loads((root / "result.json").read_text(encoding="utf-8"))
        summary = summary.get("stages", {}).get("biophysical", {})
    if "gamut_floor_relative_rmse" in summary:
        metrics["gamut_floor_relative_rmse"] = summary["gamut_floor_relative_rmse"]
    metrics["rerender_vs_gt_relative_rmse"] = _relative_rmse(rendered, reference)
    metrics["input_vs_gt_relative_rmse"] = _relative_rmse(observed, reference)
    return metrics


def report_section(page, result_dir: str | Path, metrics: dict[str, Any] | None = None):
    """Add the biophysical section to a :class:`polarface.report.html.HtmlPage` of ``result_dir``.

    Image paths are relative to ``result_dir`` (the report lives at ``RESULT/report.html``).
    Returns the section.
    """
    root = Path(result_dir)
    summary = {}
    if (root / "result.json").is_file():
        summary = (
            json.loads((root / "result.json").read_text(encoding="utf-8"))
            .get("stages", {})
            .get("biophysical", {})
        )
    section = page.section(
        "Biophysical parameters",
        "Chromophore maps recovered from the six-channel subsurface albedo (paper Sec. 5.3): melanin, "
        "eumelanin fraction, inner and outer haemoglobin; and the re-rendered subsurface albedo (sRGB).",
    )
    items = [(f"previews/{n}.png", PARAMETER_LABELS[n][0]) for n in PARAMETER_ORDER]
    items.append(("previews/subsurface_srgb.png", "Rendered subsurface albedo (sRGB, D65)"))
    items.append(("previews/rho_sss_bar_residual.png", "Re-render residual vs input (relative)"))
    items.append(("previews/in_gamut.png", "Input outside the skin model's gamut (red)"))
    section.image_grid([i for i in items if (root / i[0]).is_file()], columns=5)
    if summary:
        rows = {f"median {k}": v for k, v in summary.get("median_parameters", {}).items()}
        rows["re-render relative RMSE vs input (all valid texels)"] = summary.get("rho_sss_bar_relative_rmse")
        rows["same, texels inside the skin gamut"] = summary.get("rho_sss_bar_relative_rmse_in_gamut")
        rows["gamut floor (input's distance to the skin model)"] = summary.get("gamut_floor_relative_rmse")
        rows["texels outside the skin gamut"] = summary.get("out_of_gamut_texels")
        rows["stage time (s)"] = summary.get("timings_s", {}).get("total_s")
        section.table(rows)
    if metrics:
        section.table(
            [(n, metrics[n]["median_abs"], metrics[n]["mean_abs"]) for n in PARAMETER_ORDER if n in metrics],
            header=("parameter", "median |error|", "mean |error|"),
        )
        keys = ("rerender_vs_gt_relative_rmse", "input_vs_gt_relative_rmse")
        section.table(
            [(k, metrics[k]) for k in keys if k in metrics], header=("relative RMSE vs ground truth", "value")
        )
    return section
