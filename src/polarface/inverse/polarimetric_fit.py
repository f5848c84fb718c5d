"""Patch-based optimisation of the static polarimetric maps (paper Sec. 5.2, Eq. p-inverse-main-loss).

Unknowns per texel: eta, alpha_s, alpha_ss, rho_s, rho_ss, rho_sss_bar (6 channels) and the
displacement H (mm). They are optimised jointly with RMSprop (paper: RMSprop, lr 1e-3) on
reparameterised variables that keep them in physical ranges:

* ``eta = eta_lo + (eta_hi - eta_lo) sigmoid(z)`` (default 1.05..2.5: reaches the paper's 1.15-2.4
  validation range);
* ``alpha_s = a_lo + (a_hi - a_lo) sigmoid(z)``, ``alpha_ss = alpha_s + (a_hi - alpha_s) sigmoid(z')``:
  the single-scattering lobe is by construction the broader one, so the two lobes cannot swap (no
  lobe mixing; the authors' release instead overwrote the single-scattering image inside the
  specular mask, DESIGN.md);
* ``rho_s, rho_ss = rho_max sigmoid(z)``, ``rho_sss_bar = sigmoid(z)`` (in [0, 1]);
* ``H = h_scale z`` (mm); normals through :func:`polarface.geometry.heights.normals_from_heights`
  (its precomputed form :class:`~polarface.geometry.heights.HeightNormals`).

The texture is processed patch by patch (a halo of ``halo`` texels gives the regularisers and the
height finite differences their neighbours; only the interior is written back), each patch holding
all its fitting samples in memory; the patch side is chosen so that the sample count stays under
``sample_budget``, hence memory does not grow with the number of views. Starts per texel (closed form, on
the patch's samples): eta from a grid search of the signed DoP ratio ``I_zeta / I_sss`` (independent of
albedos and lighting), rho_sss_bar by linear least squares on I_sss, and (alpha_s, rho_s) by a grid over
alpha_s with rho_s in closed form on the I_s residual. Optionally (``config.refine_lobes_iterations``,
default 0) Levenberg-Marquardt iterations on the four lobe maps
(:mod:`polarface.inverse.polarimetric_refine`) follow each patch's optimisation: they move the
patch-wide alpha_s mode that RMSprop leaves where the start put it. Deterministic for a seed (the
order of patches is fixed; nothing is random except an optional sample shuffle seeded by ``seed``).
Checkpoints after every patch allow an interrupted run to resume to identical maps.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage
from tqdm import tqdm

from polarface.geometry.heights import HeightNormals
from polarface.inverse.polarimetric_config import (
    PARAMETER_NAMES,
    PolarimetricConfig,
    initial_raw,
    maps_from_raw,
    raw_from_maps,
)
from polarface.inverse.polarimetric_fused import (
    FusedSamples,
    build_fused_samples,
    fused_data_loss,
    pack_parameters,
)
from polarface.inverse.polarimetric_init import init_albedos, init_eta, nan_median_filter
from polarface.inverse.polarimetric_losses import data_losses, laplacian_penalty, smoothness_penalty
from polarface.inverse.polarimetric_model import SampleBatch, precompute_samples, render_samples
from polarface.inverse.polarimetric_refine import refine_patch_lobes
from polarface.inverse.polarimetric_step import optimise_patch_fused
from polarface.texture import TexelGeometry, UnwrapStore, ViewSpec

__all__ = [
    "PARAMETER_NAMES",
    "PolarimetricConfig",
    "PolarimetricFit",
    "build_patch_samples",
    "fit_polarimetric",
    "maps_from_raw",
    "raw_from_maps",
]

LOGGER = logging.getLogger(__name__)


def _patch_arrays(unwrap: UnwrapStore, rows: slice, cols: slice, view_indices: list[int]):
    """Geometry and the visible samples ``(v, r, c)`` of a texture region with their obs and lit masks."""
    geometry = unwrap.geometry(rows, cols)
    obs, valid, lit = unwrap.read(rows, cols, view_indices)
    valid = valid & geometry.mask[None]
    v_idx, r_idx, c_idx = np.nonzero(valid)
    return geometry, v_idx, r_idx, c_idx, obs[v_idx, r_idx, c_idx], lit[v_idx, r_idx, c_idx]


def _view_table(views: list[ViewSpec], attribute: str) -> np.ndarray:
    return np.array([getattr(v, attribute) for v in views])


def build_patch_samples(
    unwrap: UnwrapStore,
    rows: slice,
    cols: slice,
    view_indices: list[int],
    views: list[ViewSpec],
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
    fused: bool = False,
) -> tuple[SampleBatch | None, TexelGeometry] | tuple[SampleBatch | None, TexelGeometry, FusedSamples | None]:
    """The samples of a texture region for the given views (None when nothing is visible).

    With ``fused=True`` also the compact :class:`~polarface.inverse.polarimetric_fused.FusedSamples`
    of the same samples (third element), for the fused CPU kernel.
    """
    geometry, v_idx, r_idx, c_idx, obs, lit = _patch_arrays(unwrap, rows, cols, view_indices)
    if v_idx.size == 0:
        return (None, geometry, None) if fused else (None, geometry)
    width = geometry.mask.shape[1]
    chosen = [views[i] for i in view_indices]
    table = {name: _view_table(chosen, name) for name in (
        "camera_center", "camera_up", "reference_up", "light_positions", "light_intensity", "channels"
    )}  # fmt: skip
    batch = precompute_samples(
        geometry.position[r_idx, c_idx],
        r_idx * width + c_idx,
        np.asarray(view_indices)[v_idx],
        table["camera_center"][v_idx],
        table["camera_up"][v_idx],
        table["reference_up"][v_idx],
        table["light_positions"][v_idx],
        table["light_intensity"][v_idx],
        table["channels"][v_idx],
        lit,
        obs,
        dtype=dtype,
        device=device,
    )
    if not fused:
        return batch, geometry
    packed = build_fused_samples(
        geometry.position.reshape(-1, 3),
        r_idx * width + c_idx,
        v_idx,
        lit,
        obs,
        table["camera_center"],
        table["camera_up"],
        table["reference_up"],
        table["light_positions"],
        table["light_intensity"],
        table["channels"],
        dtype=np.float64 if dtype == torch.float64 else np.float32,
    )
    return batch, geometry, packed


@dataclasses.dataclass
class PolarimetricFit:
    """Result of :func:`fit_polarimetric`.

    Attributes:
        maps: name -> ``(Ht, Wt)`` float32 (``rho_sss_bar``: ``(Ht, Wt, 6)``).
        mask: ``(Ht, Wt)`` bool texels seen by at least ``config.min_views`` fitting views, at least
            ``config.boundary_margin`` texels inside the region of such texels.
        loss_curve: mean total loss per iteration (averaged over patches).
        timings: seconds per phase; throughput: texel-view iterations per second of the optimisation.
        sample_count: samples (texel x view) fitted; patches: number of patches.
        view_count: ``(Ht, Wt)`` int32 fitting views that see each texel (a reliability map).
    """

    maps: dict[str, np.ndarray]
    mask: np.ndarray
    loss_curve: list[float]
    timings: dict[str, float]
    throughput: float
    sample_count: int
    patches: int
    complete: bool = True
    view_count: np.ndarray | None = None


def _patch_side(unwrap: UnwrapStore, config: PolarimetricConfig, fitting: list[int]) -> int:
    counts = np.zeros(unwrap.resolution, np.float64)
    for i in fitting:
        counts += np.asarray(unwrap.root["valid"][i])
    seen = counts[counts > 0]
    per_texel = float(seen.mean()) if seen.size else 1.0
    side = int(math.sqrt(config.sample_budget / max(per_texel, 1.0))) - 2 * config.halo
    return int(max(8, min(config.patch, side)))


class _PatchProblem:
    """Everything needed to evaluate the loss of one patch (parameters as raw leaf tensors)."""

    def __init__(
        self,
        batch: SampleBatch,
        geometry: TexelGeometry,
        config: PolarimetricConfig,
        scale: float,
        dtype: torch.dtype,
        device: torch.device,
        fused: FusedSamples | None = None,
    ) -> None:
        self.batch = batch
        self.fused = fused
        self.config = config
        self.scale = scale
        t = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
        self.frame = (
            t(geometry.tangent_u),
            t(geometry.tangent_v),
            t(geometry.normal),
            t(geometry.texel_size_u),
            t(geometry.texel_size_v),
        )
        self.mask = torch.as_tensor(geometry.mask, device=device)
        self.positions = geometry.position
        self.shape = geometry.mask.shape
        self.texel_count = int(self.mask.sum())
        self._height_normals: HeightNormals | None = None

    def height_normals(self) -> HeightNormals:
        """The patch's normals-from-H operator (H-independent terms, built once)."""
        if self._height_normals is None:
            self._height_normals = HeightNormals.build(*self.frame, self.mask)
        return self._height_normals

    def normals(self, height: torch.Tensor) -> torch.Tensor:
        return self.height_normals()(height).reshape(-1, 3)

    def loss(self, raw: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        maps = maps_from_raw(raw, self.config)
        h, w = self.shape
        flat = {k: v.reshape(h * w, -1) for k, v in maps.items()}
        normal = self.normals(maps["displacement_mm"][..., 0])
        wts = self.config.weights
        if self.fused is not None:
            params = pack_parameters(
                normal, flat["eta"], flat["alpha_s"], flat["alpha_ss"], flat["rho_s"], flat["rho_ss"],
                flat["rho_sss_bar"],
            )  # fmt: skip
            data = fused_data_loss(params, self.fused, wts, self.scale)
        else:
            b = self.batch
            texel = b.texel
            prediction = render_samples(
                b,
                normal[texel],
                flat["eta"][texel, 0],
                flat["alpha_s"][texel, 0],
                flat["alpha_ss"][texel, 0],
                flat["rho_s"][texel, 0],
                flat["rho_ss"][texel, 0],
                torch.gather(flat["rho_sss_bar"][texel], 1, b.channels),
            )
            terms = data_losses(prediction, b.observed, self.scale)
            data = (
                wts.sss * terms["sss"] + wts.s * terms["s"] + wts.phi * terms["phi"] + wts.psi * terms["psi"]
            )
        height = maps["displacement_mm"][..., 0]
        mask = self.mask
        reg = {
            "h_temporal": ((height * height) * mask).sum(),
            "h_laplacian": laplacian_penalty(height, mask),
            "eta_smooth": smoothness_penalty(maps["eta"][..., 0], mask),
            "alpha_s_smooth": smoothness_penalty(maps["alpha_s"][..., 0], mask),
            "alpha_ss_smooth": smoothness_penalty(maps["alpha_ss"][..., 0], mask),
        }
        total = (
            data
            + wts.h_temporal * reg["h_temporal"]
            + wts.h_laplacian * reg["h_laplacian"]
            + wts.eta * reg["eta_smooth"]
            + wts.alpha_s * reg["alpha_s_smooth"]
            + wts.alpha_ss * reg["alpha_ss_smooth"]
        ) / max(self.texel_count, 1)
        return total, {}


def _optimizer(params: list[torch.Tensor], config: PolarimetricConfig) -> torch.optim.Optimizer:
    if config.optimizer == "adam":
        return torch.optim.Adam(params, lr=config.lr)
    return torch.optim.RMSprop(params, lr=config.lr)


def optimise_patch(
    problem: _PatchProblem,
    raw: dict[str, torch.Tensor],
    config: PolarimetricConfig,
    curve: list[float] | None = None,
    *,
    fused_steps: bool = True,
) -> dict[str, torch.Tensor]:
    """Run the optimiser on one patch; returns detached raw variables.

    With fused samples on the CPU and RMSprop, the whole step runs in numba
    (:func:`polarface.inverse.polarimetric_step.optimise_patch_fused`, the same mathematics without the
    torch glue); otherwise torch autograd drives ``problem.loss``.
    """
    steps = int(config.iterations)
    learning_rates = []
    for step in range(steps):
        # RMSprop's first steps are ~10 lr (its running mean starts at 0): a short linear warm-up
        warm = min(1.0, (step + 1) / max(config.warmup, 1))
        fraction = warm * (
            config.lr_final_fraction
            + (1 - config.lr_final_fraction) * 0.5 * (1 + math.cos(math.pi * step / max(steps, 1)))
        )
        learning_rates.append(config.lr * fraction)
    on_cpu = all(v.device.type == "cpu" for v in raw.values())
    if problem.fused is not None and config.optimizer == "rmsprop" and on_cpu and fused_steps:
        return optimise_patch_fused(problem, raw, config, learning_rates, curve)
    leaves = {k: v.detach().clone().requires_grad_(True) for k, v in raw.items()}
    optimizer = _optimizer(list(leaves.values()), config)
    for step, lr in enumerate(learning_rates):
        for group in optimizer.param_groups:
            group["lr"] = lr
        optimizer.zero_grad(set_to_none=True)
        total, _ = problem.loss(leaves)
        total.backward()
        optimizer.step()
        if curve is not None:
            if len(curve) <= step:
                curve.append(0.0)
            curve[step] += float(total.detach())
    return {k: v.detach() for k, v in leaves.items()}


def fit_polarimetric(
    unwrap: UnwrapStore,
    config: PolarimetricConfig | None = None,
    *,
    device: torch.device | str = "cpu",
    checkpoint: str | Path | None = None,
    progress: bool = True,
    stop_after_patches: int | None = None,
    on_patch: Callable[[int, int], None] | None = None,
    threads: int | None = None,
    engine: str = "auto",
) -> PolarimetricFit:
    """Fit the static polarimetric maps to the fitting (not held-out) views of ``unwrap``.

    Args:
        unwrap: a complete :class:`UnwrapStore`.
        config: :class:`PolarimetricConfig`.
        device: torch device (``polarface.device.resolve_device``).
        checkpoint: ``.npz`` path; resumes from it when present, rewritten atomically after every patch.
        progress: tqdm bar over patches.
        stop_after_patches: stop (returning ``complete=False``) after this many newly fitted patches
            (tests of interruption/resume).
        on_patch: callback ``(done, total)``.
        threads: torch intra-op threads during the fit (None: unchanged). Patch tensors hold ~1e5
            elements, where OpenMP threads gain little and, on a busy machine, spin against other
            processes (measured 10-50x slower with 2 threads under load): 1 is a safe choice. The fused
            kernel's threads are numba's (``NUMBA_NUM_THREADS``, default: all cores).
        engine: data-loss implementation: ``fused`` (numba kernel with analytic gradients, CPU),
            ``torch`` (vectorised autograd reference, any device) or ``auto`` (fused on CPU, torch
            otherwise). Both give the same loss and gradient (tests).

    Raises:
        ValueError: incomplete unwrap store, no fitting view, or no texel visible in any fitting view.
    """
    if engine not in ("auto", "fused", "torch"):
        raise ValueError(f"argument 'engine' must be 'auto', 'fused' or 'torch'; got {engine!r}")
    device = torch.device(device)
    use_fused = engine == "fused" or (engine == "auto" and device.type == "cpu")
    previous_threads = torch.get_num_threads()
    # RMSprop's running averages of tiny gradients reach denormal floats, whose arithmetic is ~20x slower
    flushing = torch.set_flush_denormal(True)
    if threads is not None:
        if int(threads) < 1:
            raise ValueError(f"argument 'threads' must be >= 1; got {threads}")
        torch.set_num_threads(int(threads))
    try:
        return _fit(
            unwrap,
            config or PolarimetricConfig(),
            device,
            checkpoint,
            progress,
            stop_after_patches,
            on_patch,
            use_fused,
        )
    finally:
        torch.set_num_threads(previous_threads)
        if flushing:
            torch.set_flush_denormal(False)


def _fit(
    unwrap, config, device, checkpoint, progress, stop_after_patches, on_patch, use_fused
) -> PolarimetricFit:
    from polarface.io import atomic_path

    torch.manual_seed(config.seed)
    if not unwrap.complete:
        raise ValueError(f"unwrap store '{unwrap.path}' is incomplete; rerun the unwrapping")
    views = unwrap.views
    fitting = [i for i, v in enumerate(views) if not v.held_out]
    if not fitting:
        raise ValueError("no fitting view: every view is held out")
    scale = unwrap.mean_i_sss(fitting)
    if not scale > 0:
        raise ValueError("no texel is visible in any fitting view (all-invisible texels)")
    started = time.perf_counter()
    side = _patch_side(unwrap, config, fitting)
    patches = list(unwrap.patches(side))
    height, width = unwrap.resolution
    raw = initial_raw((height, width), config)
    initialised = np.zeros((height, width), bool)
    done: set[int] = set()
    curve: list[float] = []
    ckpt = Path(checkpoint) if checkpoint is not None else None
    if ckpt is not None and ckpt.exists():
        with np.load(ckpt) as state:
            if int(state["patch_side"]) == side and tuple(state["resolution"]) == (height, width):
                raw = {k: state[f"raw_{k}"] for k in raw}
                initialised = state["initialised"]
                done = {int(i) for i in state["done"]}
                curve = [float(v) for v in state["curve"]]
    dtype = torch.float32
    halo = config.halo
    samples_total, opt_seconds, opt_work, refine_seconds = 0, 0.0, 0.0, 0.0
    mask_seen = np.zeros((height, width), bool)
    newly = 0
    bar = tqdm(total=len(patches), desc="polarimetric fit", unit="patch", disable=not progress)
    bar.update(len(done))
    for index, (rows, cols) in enumerate(patches):
        if index in done:
            continue
        if stop_after_patches is not None and newly >= stop_after_patches:
            bar.close()
            return PolarimetricFit(
                _to_maps(raw, config), mask_seen, curve, {}, 0.0, samples_total, len(patches), complete=False
            )
        r0, r1 = max(rows.start - halo, 0), min(rows.stop + halo, height)
        c0, c1 = max(cols.start - halo, 0), min(cols.stop + halo, width)
        hrows, hcols = slice(r0, r1), slice(c0, c1)
        built = build_patch_samples(
            unwrap, hrows, hcols, fitting, views, dtype=dtype, device=device, fused=use_fused
        )
        batch, geometry = built[0], built[1]
        if batch is not None:
            problem = _PatchProblem(
                batch, geometry, config, scale, dtype, device, built[2] if use_fused else None
            )
            patch_raw = {
                k: torch.as_tensor(v[hrows, hcols], dtype=dtype, device=device) for k, v in raw.items()
            }
            todo = ~initialised[hrows, hcols]
            if todo.any():
                maps0 = maps_from_raw(patch_raw, config)
                h, w = geometry.mask.shape
                flat0 = {k: v.reshape(h * w, -1) for k, v in maps0.items()}
                normal0 = problem.normals(maps0["displacement_mm"][..., 0])
                todo_t = torch.as_tensor(todo, device=device)
                if config.init_eta_search:
                    eta0 = init_eta(batch, normal0, h * w, config.eta_range).reshape(h, w)
                    eta0 = nan_median_filter(eta0, 5)[..., None]
                    e_lo, e_hi = config.eta_range
                    new_eta = torch.logit(((eta0 - e_lo) / (e_hi - e_lo)).to(dtype))
                    use = todo_t[..., None] & torch.isfinite(new_eta)
                    patch_raw["eta"] = torch.where(use, new_eta, patch_raw["eta"])
                    flat0["eta"] = maps_from_raw(patch_raw, config)["eta"].reshape(h * w, 1)
                rho_sss, rho_s, alpha_s0 = init_albedos(batch, normal0, flat0, h * w)
                seen0 = torch.zeros(h * w, dtype=torch.bool, device=device)
                seen0[batch.texel] = True
                masked = torch.where(seen0, alpha_s0, torch.nan).reshape(h, w)
                smooth = nan_median_filter(masked, 5).reshape(-1)
                alpha_s0 = torch.where(torch.isfinite(smooth), smooth, alpha_s0)
                a_lo, a_hi = config.alpha_range
                new_alpha = torch.logit(((alpha_s0 - a_lo) / (a_hi - a_lo)).reshape(h, w, 1).to(dtype))
                patch_raw["alpha_s"] = torch.where(todo_t[..., None], new_alpha, patch_raw["alpha_s"])
                new_sss = torch.logit(rho_sss.reshape(h, w, 6).to(dtype))
                new_s = torch.logit((rho_s / config.rho_max).reshape(h, w, 1).to(dtype))
                patch_raw["rho_sss_bar"] = torch.where(todo_t[..., None], new_sss, patch_raw["rho_sss_bar"])
                patch_raw["rho_s"] = torch.where(todo_t[..., None], new_s, patch_raw["rho_s"])
            sample_count = batch.count
            seen_texels = batch.texel.cpu().numpy()
            # the reference batch serves the closed-form starts and the lobe refinement only
            reference = batch if config.refine_lobes_iterations > 0 else None
            if use_fused:
                problem.batch = batch = None
            tick = time.perf_counter()
            result = optimise_patch(problem, patch_raw, config, curve)
            opt_seconds += time.perf_counter() - tick
            if reference is not None:  # Levenberg-Marquardt on the four lobe maps (issue 6)
                tick = time.perf_counter()
                with torch.no_grad():
                    normal = problem.normals(maps_from_raw(result, config)["displacement_mm"][..., 0])
                result = refine_patch_lobes(reference, result, normal, problem.mask, config, scale)
                refine_seconds += time.perf_counter() - tick
                reference = None
            opt_work += sample_count * int(config.iterations)
            samples_total += sample_count
            ir = slice(rows.start - r0, rows.stop - r0)
            ic = slice(cols.start - c0, cols.stop - c0)
            for k, v in result.items():
                raw[k][rows, cols] = v[ir, ic].cpu().numpy()
                # halo texels not yet fitted keep their refined initial albedos (better start for neighbours)
            if todo.any():
                for k in ("rho_sss_bar", "rho_s", "eta", "alpha_s"):
                    fresh = patch_raw[k].cpu().numpy()
                    region = raw[k][hrows, hcols]
                    region[todo] = fresh[todo]
                    raw[k][rows, cols] = result[k][ir, ic].cpu().numpy()
                initialised[hrows, hcols] = True
            seen = np.zeros(geometry.mask.shape, bool)
            seen.reshape(-1)[seen_texels] = True
            mask_seen[rows, cols] |= seen[ir, ic]
        done.add(index)
        newly += 1
        if ckpt is not None:
            with atomic_path(ckpt) as tmp:
                with open(tmp, "wb") as handle:
                    np.savez(
                        handle,
                        patch_side=side,
                        resolution=np.array([height, width]),
                        initialised=initialised,
                        done=np.array(sorted(done), dtype=np.int64),
                        curve=np.array(curve),
                        **{f"raw_{k}": v for k, v in raw.items()},
                    )
        bar.update(1)
        if on_patch is not None:
            on_patch(len(done), len(patches))
    bar.close()
    # coverage from the store (also counts texels of patches fitted before a resume)
    view_count = unwrap.visible_count() * np.asarray(unwrap.root["texel/mask"][...])
    if not view_count.any():
        raise ValueError("no texel is visible in any fitting view (all-invisible texels)")
    mask_seen = view_count >= int(config.min_views)
    if not mask_seen.any():
        raise ValueError(
            f"no texel is seen by min_views={config.min_views} fitting views (most: {int(view_count.max())})"
        )
    if int(config.boundary_margin) > 0:
        mask_seen &= ndimage.binary_erosion(mask_seen, iterations=int(config.boundary_margin), border_value=0)
        if not mask_seen.any():
            raise ValueError(
                f"no texel lies boundary_margin={config.boundary_margin} inside the reconstructed region"
            )
    patches_fitted = max(len(patches), 1)
    curve_mean = [v / patches_fitted for v in curve]
    timings = {"fit_s": time.perf_counter() - started, "optimise_s": opt_seconds, "refine_s": refine_seconds}
    throughput = opt_work / opt_seconds if opt_seconds > 0 else 0.0
    return PolarimetricFit(
        _to_maps(raw, config),
        mask_seen,
        curve_mean,
        timings,
        throughput,
        samples_total,
        len(patches),
        view_count=view_count.astype(np.int32),
    )


def _to_maps(raw: dict[str, np.ndarray], config: PolarimetricConfig) -> dict[str, np.ndarray]:
    with torch.no_grad():
        maps = maps_from_raw(
            {k: torch.from_numpy(np.asarray(v, dtype=np.float64)) for k, v in raw.items()}, config
        )
    out = {}
    for k, v in maps.items():
        array = v.numpy().astype(np.float32)
        out[k] = array if k == "rho_sss_bar" else array[..., 0]
    return out
