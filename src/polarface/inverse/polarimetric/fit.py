"""Patch-based optimisation of the static polarimetric maps (paper Sec. 5.2, Eq. p-inverse-main-loss).

Unknowns per texel: eta, alpha_s, alpha_ss, rho_s, rho_ss, rho_sss_bar (6 channels) and the
displacement H (mm). They are optimised jointly, by L-BFGS by default (the paper's RMSprop, lr 1e-3,
is an option; :mod:`polarface.inverse.polarimetric.optimise` says why), on reparameterised variables
that keep them in physical ranges:

* ``eta = eta_lo + (eta_hi - eta_lo) sigmoid(z)`` (default 1.05..2.5: reaches the paper's 1.15-2.4
  validation range);
* ``alpha_s = a_lo + (a_hi - a_lo) sigmoid(z)``, ``alpha_ss = alpha_s + (a_hi - alpha_s) sigmoid(z')``:
  the single-scattering lobe is by construction the broader one, so the two lobes cannot swap (no
  lobe mixing; the authors' release instead overwrote the single-scattering image inside the
  specular mask);
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
(:mod:`polarface.inverse.polarimetric.refine`) follow each patch's optimisation: they move the
patch-wide alpha_s mode that RMSprop leaves where the start put it (L-BFGS moves it itself).
Deterministic for a seed (the
order of patches is fixed; nothing is random except an optional sample shuffle seeded by ``seed``).
Checkpoints after every patch allow an interrupted run to resume to identical maps.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage
from tqdm import tqdm

from polarface.inverse.polarimetric.config import PolarimetricConfig, initial_raw, maps_from_raw
from polarface.inverse.polarimetric.engines import PolarimetricEngine, resolve_engine
from polarface.inverse.polarimetric.init import apply_closed_form_starts
from polarface.inverse.polarimetric.optimise import optimise_patch
from polarface.inverse.polarimetric.problem import PatchProblem, build_patch_samples
from polarface.inverse.polarimetric.refine import refine_patch_lobes
from polarface.texture import UnwrapStore, ViewSpec

__all__ = ["PolarimetricFit", "fit_polarimetric"]

LOGGER = logging.getLogger(__name__)


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
            processes (docs/reconstruct.md): 1 is a safe choice. The fused
            kernel's threads are numba's (``NUMBA_NUM_THREADS``, default: all cores).
        engine: data-loss implementation: ``fused`` (numba kernel with analytic gradients, CPU),
            ``torch`` (vectorised autograd reference, any device) or ``auto`` (fused on CPU, torch
            otherwise). Both give the same loss and gradient (tests).

    Raises:
        ValueError: incomplete unwrap store, no fitting view, or no texel visible in any fitting view.
    """
    device = torch.device(device)
    chosen = resolve_engine(engine, device)
    with torch_fit_settings(threads):
        return _fit(
            unwrap,
            config or PolarimetricConfig(),
            device,
            checkpoint,
            progress,
            stop_after_patches,
            on_patch,
            chosen,
        )


@contextlib.contextmanager
def torch_fit_settings(threads: int | None) -> Iterator[None]:
    """Torch settings of a fit, restored afterwards: ``threads`` intra-op threads (None: unchanged) and
    denormals flushed to zero (RMSprop's running averages of tiny gradients reach denormal floats, whose
    arithmetic is ~20x slower).

    Raises:
        ValueError: ``threads < 1``.
    """
    if threads is not None and int(threads) < 1:
        raise ValueError(f"argument 'threads' must be >= 1; got {threads}")
    previous_threads = torch.get_num_threads()
    flushing = torch.set_flush_denormal(True)
    if threads is not None:
        torch.set_num_threads(int(threads))
    try:
        yield
    finally:
        torch.set_num_threads(previous_threads)
        if flushing:
            torch.set_flush_denormal(False)


def haloed_slices(rows: slice, cols: slice, halo: int, resolution: tuple[int, int]
                  ) -> tuple[slice, slice, tuple[slice, slice]]:
    """A patch's region with its halo (clipped to the texture ``resolution``) and, within that region,
    the interior ``rows x cols``: ``(halo rows, halo cols, (interior rows, interior cols))``."""
    height, width = resolution
    r0, r1 = max(rows.start - halo, 0), min(rows.stop + halo, height)
    c0, c1 = max(cols.start - halo, 0), min(cols.stop + halo, width)
    interior = (slice(rows.start - r0, rows.stop - r0), slice(cols.start - c0, cols.stop - c0))
    return slice(r0, r1), slice(c0, c1), interior


@dataclasses.dataclass
class _FitState:
    """What a checkpoint holds: raw variables (name -> ``(Ht, Wt, c)``), the ``(Ht, Wt)`` bool texels that
    have their closed-form starts, the indices of the patches done and the loss curve (sums over patches)."""

    raw: dict[str, np.ndarray]
    initialised: np.ndarray
    done: set[int]
    curve: list[float]

    @classmethod
    def start(
        cls, resolution: tuple[int, int], side: int, config: PolarimetricConfig, checkpoint: Path | None
    ) -> _FitState:
        """The initial state, or the checkpoint's when it exists and matches ``side`` and ``resolution``."""
        height, width = resolution
        state = cls(initial_raw((height, width), config), np.zeros((height, width), bool), set(), [])
        if checkpoint is not None and checkpoint.exists():
            with np.load(checkpoint) as saved:
                if int(saved["patch_side"]) == side and tuple(saved["resolution"]) == (height, width):
                    state.raw = {k: saved[f"raw_{k}"] for k in state.raw}
                    state.initialised = saved["initialised"]
                    state.done = {int(i) for i in saved["done"]}
                    state.curve = [float(v) for v in saved["curve"]]
        return state

    def save(self, checkpoint: Path, side: int, resolution: tuple[int, int]) -> None:
        """Write the state to ``checkpoint`` (``.npz``) atomically."""
        from polarface.io import atomic_path

        height, width = resolution
        with atomic_path(checkpoint) as tmp:
            with open(tmp, "wb") as handle:
                np.savez(
                    handle,
                    patch_side=side,
                    resolution=np.array([height, width]),
                    initialised=self.initialised,
                    done=np.array(sorted(self.done), dtype=np.int64),
                    curve=np.array(self.curve),
                    **{f"raw_{k}": v for k, v in self.raw.items()},
                )


@dataclasses.dataclass
class _Tally:
    """Running totals of a fit: samples fitted, optimiser seconds and work (samples x iterations),
    lobe-refinement seconds, and the ``(Ht, Wt)`` bool texels seen by a fitted patch."""

    seen: np.ndarray
    samples: int = 0
    optimise_s: float = 0.0
    work: float = 0.0
    refine_s: float = 0.0


def _fit_patch(
    unwrap: UnwrapStore,
    rows: slice,
    cols: slice,
    fitting: list[int],
    views: list[ViewSpec],
    engine: PolarimetricEngine,
    config: PolarimetricConfig,
    scale: float,
    device: torch.device,
    state: _FitState,
    tally: _Tally,
) -> None:
    """Fit one patch (its interior ``rows x cols`` plus a halo): closed-form starts of the texels not yet
    started, the optimiser, the optional lobe refinement (``views``: the store's view list); writes the
    interior back into ``state`` and adds to ``tally``."""
    dtype = torch.float32
    hrows, hcols, (ir, ic) = haloed_slices(rows, cols, config.halo, unwrap.resolution)
    built = build_patch_samples(
        unwrap, hrows, hcols, fitting, views, dtype=dtype, device=device, fused=engine.fused_samples
    )
    batch, geometry = built[0], built[1]
    if batch is None:
        return
    problem = PatchProblem(
        batch, geometry, config, scale, dtype, device, built[2] if engine.fused_samples else None
    )
    patch_raw = {
        k: torch.as_tensor(v[hrows, hcols], dtype=dtype, device=device) for k, v in state.raw.items()
    }
    todo = ~state.initialised[hrows, hcols]
    if todo.any():
        apply_closed_form_starts(batch, patch_raw, todo, problem.normals, config, dtype, device)
    sample_count = batch.count
    seen_texels = batch.texel.cpu().numpy()
    # the reference batch serves the closed-form starts and the lobe refinement only
    reference = batch if config.refine_lobes_iterations > 0 else None
    if engine.fused_samples:
        problem.batch = batch = None
    tick = time.perf_counter()
    result = optimise_patch(problem, patch_raw, config, state.curve)
    tally.optimise_s += time.perf_counter() - tick
    if reference is not None:  # Levenberg-Marquardt on the four lobe maps
        tick = time.perf_counter()
        with torch.no_grad():
            normal = problem.normals(maps_from_raw(result, config)["displacement_mm"][..., 0])
        result = refine_patch_lobes(reference, result, normal, problem.mask, config, scale)
        tally.refine_s += time.perf_counter() - tick
        reference = None
    tally.work += sample_count * int(config.iterations)
    tally.samples += sample_count
    for k, v in result.items():
        state.raw[k][rows, cols] = v[ir, ic].cpu().numpy()
        # halo texels not yet fitted keep their refined initial albedos (better start for neighbours)
    if todo.any():
        for k in ("rho_sss_bar", "rho_s", "eta", "alpha_s"):
            fresh = patch_raw[k].cpu().numpy()
            region = state.raw[k][hrows, hcols]
            region[todo] = fresh[todo]
            state.raw[k][rows, cols] = result[k][ir, ic].cpu().numpy()
        state.initialised[hrows, hcols] = True
    seen = np.zeros(geometry.mask.shape, bool)
    seen.reshape(-1)[seen_texels] = True
    tally.seen[rows, cols] |= seen[ir, ic]


def _coverage(unwrap: UnwrapStore, config: PolarimetricConfig) -> tuple[np.ndarray, np.ndarray]:
    """``(mask, view_count)`` of :class:`PolarimetricFit` from the store (it also counts the texels of
    patches fitted before a resume)."""
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
    return mask_seen, view_count


def _fit(
    unwrap: UnwrapStore,
    config: PolarimetricConfig,
    device: torch.device,
    checkpoint: str | Path | None,
    progress: bool,
    stop_after_patches: int | None,
    on_patch: Callable[[int, int], None] | None,
    engine: PolarimetricEngine,
) -> PolarimetricFit:
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
    ckpt = Path(checkpoint) if checkpoint is not None else None
    state = _FitState.start(unwrap.resolution, side, config, ckpt)
    tally = _Tally(np.zeros(unwrap.resolution, bool))
    newly = 0
    bar = tqdm(total=len(patches), desc="polarimetric fit", unit="patch", disable=not progress)
    bar.update(len(state.done))
    for index, (rows, cols) in enumerate(patches):
        if index in state.done:
            continue
        if stop_after_patches is not None and newly >= stop_after_patches:
            bar.close()
            return PolarimetricFit(
                _to_maps(state.raw, config), tally.seen, state.curve, {}, 0.0, tally.samples, len(patches),
                complete=False,
            )  # fmt: skip
        _fit_patch(unwrap, rows, cols, fitting, views, engine, config, scale, device, state, tally)
        state.done.add(index)
        newly += 1
        if ckpt is not None:
            state.save(ckpt, side, unwrap.resolution)
        bar.update(1)
        if on_patch is not None:
            on_patch(len(state.done), len(patches))
    bar.close()
    mask_seen, view_count = _coverage(unwrap, config)
    patches_fitted = max(len(patches), 1)
    curve_mean = [v / patches_fitted for v in state.curve]
    timings = {
        "fit_s": time.perf_counter() - started,
        "optimise_s": tally.optimise_s,
        "refine_s": tally.refine_s,
    }
    throughput = tally.work / tally.optimise_s if tally.optimise_s > 0 else 0.0
    return PolarimetricFit(
        _to_maps(state.raw, config),
        mask_seen,
        curve_mean,
        timings,
        throughput,
        tally.samples,
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
