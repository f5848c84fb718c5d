"""The biophysical stage on a RESULT folder: read rho_sss_bar, fit, write maps, previews and the record.

Reads (:class:`polarface.results.ResultFolder`, layout ``docs/result_folder.md``):
``maps/rho_sss_bar.exr`` (six channels named by the rig's spectral calibration), ``maps/mask.png``,
``mesh.obj`` (rest mesh with UVs, mm) and ``rig.json`` (spectral calibration required). Writes:

* ``maps/c_m.exr``, ``maps/beta_m.exr``, ``maps/c_h_in.exr``, ``maps/c_h_out.exr`` (channel ``Y``,
  volume fractions);
* ``maps/sog.json``: per-layer normalised sum-of-Gaussians weights per wavelength (``(L, 9)`` each),
  the variances (mm^2), wavelengths (nm) and the fit's relative error;
* ``maps/subsurface_spectral.exr``: the rendered subsurface albedo at each of the L wavelengths
  (channels ``nm420`` ...), ``maps/rho_sss_bar_rendered.exr``: its six-channel integration;
* ``maps/rho_sss_bar_residual.exr``: per texel ``relative`` (``||rendered - input|| / ||input||``) and
  ``gamut_distance`` (the input's distance to the skin model's gamut), ``maps/in_gamut.png`` (255 where
  the input is inside the gamut, :class:`~polarface.inverse.biophysical.BiophysicalConfig`
  ``gamut_tolerance``);
* previews (:mod:`polarface.pipeline.biophysical.previews`);
* ``result.json``: ``stages.biophysical`` with timings, the re-render relative RMSE against the input
  over all valid texels (``rho_sss_bar_relative_rmse``) and over the in-gamut ones, the gamut floor
  and the number of out-of-gamut texels, and ``start``: ``"scratch"`` or the RESULT folder whose
  maps started the fit (``start_from``; a dynamic frame's static result, ``docs/dynamic.md``).

Texel size and per-texel stretch come from the mesh (:func:`polarface.geometry.uv_raster.rasterize_uv`).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from polarface.device import resolve_device
from polarface.evaluate import check_ground_truth
from polarface.executors import ThreadSettings
from polarface.inverse.biophysical import (
    PARAMETER_ORDER,
    BiophysicalConfig,
    BiophysicalFit,
    BiophysicalStart,
    TotalsTable,
    fit_biophysical,
    per_texel_relative_residual,
)
from polarface.pipeline.biophysical.previews import write_previews, write_residual_previews
from polarface.results import RESULT_FORMAT, RESULT_VERSION, RHO_SSS_BAR, ResultFolder
from polarface.results import layout as names_

__all__ = ["check_coarse_factor", "largest_coarse_factor", "load_stage_inputs", "load_start",
           "run_biophysical_stage"]

LOGGER = logging.getLogger(__name__)


def _check_albedo(rho: np.ndarray, mask: np.ndarray, path: Path) -> None:
    values = rho[mask]
    if not np.isfinite(values).all():
        raise ValueError(f"'{path}': rho_sss_bar contains NaN or infinite values inside the mask")
    if values.size and (values.min() < 0.0 or values.max() > 1.0):
        raise ValueError(
            f"'{path}': rho_sss_bar must lie in [0, 1] (a dimensionless albedo); "
            f"got {values.min():.4g}..{values.max():.4g}"
        )


def load_stage_inputs(result_dir: str | Path | ResultFolder) -> dict[str, Any]:
    """Read and validate the stage's inputs from a RESULT folder.

    Returns:
        dict with ``rho_sss_bar`` ``(H, W, 6)`` float32, ``mask`` ``(H, W)`` bool, ``calibration``
        (``SpectralCalibration``), ``channel_names``, ``rig``, ``texel_size_mm`` (float, median, mm),
        ``stretch`` ``(H, W, 2)`` float32.

    Raises:
        FileNotFoundError: a required file is missing. ValueError: a malformed ``result.json`` (or one
        whose channel names / texture resolution disagree with the rig / maps), no spectral
        calibration, channel names that do not match it, NaN/inf or values outside [0, 1] in ``rho_sss_bar``.
    """
    from polarface.geometry.uv_raster import rasterize_uv

    folder = result_dir if isinstance(result_dir, ResultFolder) else ResultFolder(result_dir)
    if not folder.root.is_dir():
        raise FileNotFoundError(f"result folder '{folder.root}' does not exist")
    recorded = folder.read_result()  # a malformed result.json fails here, before any map is written
    rig = folder.read_rig()
    if rig.spectral is None:
        raise ValueError(
            f"'{folder.rig_path}' has no spectral calibration; the biophysical stage needs the six "
            "channels' responses (rig.spectral)"
        )
    calibration = rig.spectral.to_calibration()
    names = list(calibration.channel_names)
    if recorded.get("channel_names", names) != names:
        raise ValueError(
            f"'{folder.result_json_path}': 'channel_names' {recorded['channel_names']} do not match the "
            f"spectral calibration of '{folder.rig_path}' {names}"
        )
    rho = folder.read_channel_map(RHO_SSS_BAR, names).astype(np.float32)
    resolution = recorded.get("texture_resolution", list(rho.shape[:2]))
    if list(resolution) != list(rho.shape[:2]):
        raise ValueError(
            f"'{folder.result_json_path}': 'texture_resolution' {resolution} does not match "
            f"'{folder.map_path(RHO_SSS_BAR)}' {list(rho.shape[:2])}"
        )
    mask = folder.read_mask(rho.shape[:2])
    _check_albedo(rho, mask, folder.map_path(RHO_SSS_BAR))
    raster = rasterize_uv(folder.read_mesh(), rho.shape[:2])
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


def _has_coarse_texel(mask: torch.Tensor, factor: int) -> bool:
    """Whether the coarse grid of ``factor`` keeps a texel (one covered more than a quarter by ``mask``:
    :func:`polarface.inverse.biophysical.resample.downsample_masked`)."""
    from polarface.inverse.biophysical.resample import downsample_masked

    _, coarse = downsample_masked(mask[..., None].to(torch.float32), mask, factor)
    return bool(coarse.any())


def largest_coarse_factor(mask: np.ndarray) -> int:
    """The largest coarse-stage factor for the texture of ``mask`` ``(H, W)`` bool: at most the texture's
    longer side, and its coarse grid keeps a texel covered more than a quarter by the mask (the coarse fit
    needs one). Found by bisection (the coverage shrinks as the factor grows); 0 for an empty mask."""
    valid = torch.from_numpy(np.asarray(mask, dtype=bool))
    low, high = 0, max(valid.shape)
    while low < high:  # invariant: low is valid (or 0), every factor > high invalid
        middle = (low + high + 1) // 2
        if _has_coarse_texel(valid, middle):
            low = middle
        else:
            high = middle - 1
    return low


def check_coarse_factor(factor: int, mask: np.ndarray) -> None:
    """Refuse a coarse-stage factor outside ``[1, largest_coarse_factor(mask)]`` (naming the option
    ``--coarse-factor`` and the range for this texture).

    Raises:
        ValueError: the factor leaves the coarse fit no texel (or is < 1).
    """
    mask = np.asarray(mask, dtype=bool)
    if not mask.any():
        return  # the fit's own error
    if 1 <= factor <= max(mask.shape) and _has_coarse_texel(torch.from_numpy(mask), factor):
        return
    largest = largest_coarse_factor(mask)
    height, width = mask.shape
    raise ValueError(
        f"argument '--coarse-factor' must lie in [1, {largest}] for this RESULT's {height} x {width} texture "
        f"(a larger factor leaves the coarse stage no texel covered more than a quarter by the mask); "
        f"got {factor}"
    )


def load_start(result_dir: str | Path | ResultFolder, calibration, resolution: tuple[int, int]
               ) -> BiophysicalStart:
    """A finished biophysical stage's maps as the start of another fit on the same atlas (a dynamic
    frame from the static RESULT): ``maps/{c_m,beta_m,c_h_in,c_h_out}.exr`` on ``maps/mask.png``, and
    the SoG shapes of ``maps/sog.json`` when they are on ``calibration``'s wavelength grid (else None:
    the fit re-fits them).

    Raises:
        ValueError: the folder's biophysical stage is not complete, or its maps are not ``resolution``
            ``(H, W)`` texels (naming the folder). FileNotFoundError: a map is missing.
    """
    from polarface.skin.heterogeneous import ProfileShapes

    folder = result_dir if isinstance(result_dir, ResultFolder) else ResultFolder(result_dir)
    if not folder.stage_complete("biophysical"):
        raise ValueError(
            f"'{folder.root}' holds no finished biophysical stage to start from; run 'polarface "
            "biophysical' on it first or fit from scratch"
        )
    parameters = np.stack([folder.read_scalar_map(name) for name in PARAMETER_ORDER], axis=-1)
    if parameters.shape[:2] != tuple(resolution):
        raise ValueError(
            f"'{folder.root}': chromophore maps of {parameters.shape[:2]} texels cannot start a fit of "
            f"{tuple(resolution)} texels (another texture resolution)"
        )
    valid = folder.read_mask(parameters.shape[:2])
    sog = folder.read_sog() or {}
    shapes = None
    layers = sog.get("layers", {})
    grid = [float(w) for w in calibration.wavelengths_nm.tolist()]
    if sog.get("wavelengths_nm") == grid and all(name in layers for name in names_.SOG_LAYERS):
        shapes = ProfileShapes(*(torch.tensor(layers[n], dtype=torch.float64) for n in names_.SOG_LAYERS))
    return BiophysicalStart(torch.from_numpy(parameters.astype(np.float32)), torch.from_numpy(valid), shapes)


def _write_maps(
    folder: ResultFolder, fit: BiophysicalFit, calibration, mask: np.ndarray, observed: np.ndarray
) -> None:
    from polarface.skin.sog import sog_variances

    params = fit.parameters.numpy()
    for i, name in enumerate(PARAMETER_ORDER):
        folder.write_scalar_map(name, np.where(mask, params[..., i], 0.0))
    channel_names = list(calibration.channel_names)
    rendered = fit.rendered.numpy()
    folder.write_channel_map(names_.RHO_SSS_BAR_RENDERED, rendered, channel_names)
    residual = {
        "relative": per_texel_relative_residual(rendered, observed, mask),
        "gamut_distance": np.where(mask, fit.gamut_distance.numpy(), 0.0).astype(np.float32),
    }
    folder.write_channel_map(
        names_.RHO_SSS_BAR_RESIDUAL, np.stack([residual[k] for k in names_.RESIDUAL_CHANNELS], -1),
        names_.RESIDUAL_CHANNELS,
    )
    folder.write_mask(fit.in_gamut.numpy() & mask, names_.IN_GAMUT)
    grid = calibration.wavelengths_nm.tolist()
    spectral = fit.spectral.numpy()
    folder.write_channel_map(
        names_.SUBSURFACE_SPECTRAL, np.moveaxis(spectral, 0, -1), [f"nm{w:g}" for w in grid]
    )
    folder.write_sog(
        {
            "format": names_.SOG_FORMAT,
            "version": 1,
            "wavelengths_nm": grid,
            "variances_mm2": sog_variances().tolist(),
            "normalised": True,
            "layers": {name: getattr(fit.shapes, name).tolist() for name in names_.SOG_LAYERS},
            "relative_fit_error": None
            if fit.shapes.relative_error is None
            else fit.shapes.relative_error.tolist(),
        }
    )


def _fit(inputs: dict[str, Any], config: BiophysicalConfig, table: TotalsTable, target: torch.device,
         threads: int | None, progress: bool, start: BiophysicalStart | None = None
         ) -> tuple[BiophysicalFit, int]:
    """Run :func:`fit_biophysical` on ``target`` (CPU threads, torch's and numba's, set and restored);
    results on the CPU.

    Returns the fit and the torch thread count before the call.
    """
    steps = 3 + (config.shape_rounds if config.albedo_model == "blurred" else 0)
    previous = ThreadSettings.of_this_process()
    if threads is not None and target.type == "cpu":
        ThreadSettings(int(threads), int(threads)).apply()
    try:
        with tqdm(total=steps, desc="biophysical", disable=not progress, unit="step") as bar:
            fit = fit_biophysical(
                torch.from_numpy(inputs["rho_sss_bar"]).to(target),
                torch.from_numpy(inputs["mask"]).to(target),
                table,
                inputs["calibration"].weights.float().to(target),
                inputs["texel_size_mm"],
                config,
                stretch=torch.from_numpy(inputs["stretch"]).to(target),
                progress=lambda name: (bar.set_postfix_str(name), bar.update(1)),
                start=start,
            )
    finally:
        previous.apply()
    fit = dataclasses.replace(
        fit,
        parameters=fit.parameters.cpu(),
        rendered=fit.rendered.cpu(),
        spectral=fit.spectral.cpu(),
        in_gamut=fit.in_gamut.cpu(),
        gamut_distance=fit.gamut_distance.cpu(),
    )
    return fit, int(previous.torch_threads)


def _summary(fit: BiophysicalFit, inputs: dict[str, Any], config: BiophysicalConfig) -> dict[str, Any]:
    mask = inputs["mask"]
    params = fit.parameters.numpy()[mask]
    out_of_gamut = int(mask.sum() - fit.in_gamut.numpy().sum())
    return {
        "albedo_model": config.albedo_model,
        "texel_size_mm": inputs["texel_size_mm"],
        "texels": int(mask.sum()),
        "rho_sss_bar_relative_rmse": fit.residual_rmse,
        "rho_sss_bar_relative_rmse_in_gamut": fit.residual_rmse_in_gamut,
        "gamut_floor_relative_rmse": fit.gamut_floor_rmse,
        "out_of_gamut_texels": out_of_gamut,
        "out_of_gamut_fraction": out_of_gamut / max(int(mask.sum()), 1),
        "median_parameters": {n: float(np.median(params[:, i])) for i, n in enumerate(PARAMETER_ORDER)},
    }


def run_biophysical_stage(
    result_dir: str | Path | ResultFolder,
    config: BiophysicalConfig = BiophysicalConfig(),  # noqa: B008 - frozen dataclass
    device: str | torch.device | None = None,
    progress: bool = True,
    threads: int | None = 1,
    ground_truth: str | Path | None = None,
    start_from: str | Path | ResultFolder | None = None,
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
            than it gains on a busy machine (measurements in ``docs/biophysical.md``).
        ground_truth: the simulator folder a later
            :func:`~polarface.evaluate.biophysical.evaluate_biophysical` will read; checked
            first (:func:`~polarface.evaluate.biophysical.check_ground_truth`), so a bad one
            fails before the fit and before anything is written.
        start_from: a RESULT folder on the same atlas whose finished biophysical maps start the fit
            (:func:`load_start`; a dynamic frame's static RESULT): no coarse search, the previous maps
            as start and prior (``polarface.inverse.biophysical.warm_start``). None: from scratch.

    Raises:
        ValueError: ``threads < 1`` and the input errors of :func:`load_stage_inputs`.
        FileNotFoundError: a missing input, or a ``ground_truth`` folder without the ground-truth maps.

    Returns:
        The summary stored under ``result.json``'s ``stages.biophysical``: timings (s), fit residual,
        texel size, median parameters, configuration.
    """
    if threads is not None and int(threads) < 1:
        raise ValueError(f"argument 'threads' must be >= 1; got {threads}")
    if ground_truth is not None:
        check_ground_truth(ground_truth)
    target = resolve_device(device) if device is not None else torch.device("cpu")
    started = time.perf_counter()
    folder = result_dir if isinstance(result_dir, ResultFolder) else ResultFolder(result_dir)
    inputs = load_stage_inputs(folder)
    if start_from is None:  # a warm start skips the coarse stage
        check_coarse_factor(int(config.coarse_factor), inputs["mask"])
    calibration = inputs["calibration"]
    table = TotalsTable(calibration.wavelengths_nm, config.constants)
    start = None if start_from is None else load_start(start_from, calibration, inputs["mask"].shape)
    read_s = time.perf_counter() - started
    fit, previous_threads = _fit(inputs, config, table, target, threads, progress, start)
    write_started = time.perf_counter()
    mask = inputs["mask"]
    _write_maps(folder, fit, calibration, mask, inputs["rho_sss_bar"])
    write_previews(
        folder.root, fit.parameters.numpy(), mask, fit.spectral.numpy(), calibration.wavelengths_nm.numpy()
    )
    write_residual_previews(folder, fit.rendered.numpy(), fit.in_gamut.numpy(), mask, inputs["rho_sss_bar"])
    summary = _summary(fit, inputs, config)
    summary["timings_s"] = {
        "read_s": read_s,
        **fit.timings_s,
        "write_s": time.perf_counter() - write_started,
        "total_s": time.perf_counter() - started,
    }
    summary["torch_threads"] = (
        int(threads) if threads is not None and target.type == "cpu" else previous_threads
    )
    summary["config"] = {k: v for k, v in vars(config).items() if k != "constants"}
    summary["start"] = "scratch" if start_from is None else str(
        start_from.root if isinstance(start_from, ResultFolder) else start_from
    )
    folder.update_result(
        defaults={
            "format": RESULT_FORMAT,
            "version": RESULT_VERSION,
            "channel_names": inputs["channel_names"],
            "texture_resolution": list(mask.shape),
            "texel_size_mm": summary["texel_size_mm"],
        },
        stage="biophysical",
        record=summary,
    )
    return summary
