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
Deterministic: nothing in a patch's fit is random, and the patches run in a fixed order.

The patches are the units of an executor (:mod:`polarface.executors`; in this process by default, or
Ray tasks): :mod:`polarface.inverse.polarimetric.patch_units` orders them as a wavefront over the patch
grid, and each patch runs once its earlier neighbours are done, so that patches run in parallel and the
maps are, bit for bit, those of fitting the patches one after the other in row-major order. The
checkpoint is rewritten after every patch (by a thread of its own, while the next patches run), so an
interrupted run resumes from the patches done to identical maps.
"""

from __future__ import annotations

import concurrent.futures
import copy
import dataclasses
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy import ndimage
from tqdm import tqdm

from polarface.executors import Executor, LocalExecutor, UnitOutcome
from polarface.inverse.polarimetric.clusters import albedo_clusters, cluster_values
from polarface.inverse.polarimetric.config import (
    PolarimetricConfig,
    fit_maps_from_raw,
    initial_raw,
    raw_from_maps,
)
from polarface.inverse.polarimetric.engines import resolve_engine
from polarface.inverse.polarimetric.patch_units import (
    PatchResult,
    PatchUnit,
    haloed_slices,
    patch_fronts,
    patch_side,
    patch_waits,
    run_patch_unit,
    shared_unwrap,
    torch_fit_settings,
)
from polarface.texture import UnwrapStore

__all__ = ["PolarimetricFit", "fit_coverage", "fit_polarimetric"]

LOGGER = logging.getLogger(__name__)


@dataclasses.dataclass
class PolarimetricFit:
    """Result of :func:`fit_polarimetric`.

    Attributes:
        maps: name -> ``(Ht, Wt)`` float32 (``rho_sss_bar``: ``(Ht, Wt, 6)``).
        mask: ``(Ht, Wt)`` bool texels seen by at least ``config.min_views`` fitting views, at least
            ``config.boundary_margin`` texels inside the region of such texels.
        loss_curve: mean total loss per iteration (averaged over patches).
        timings: seconds: ``fit_s`` (all), and summed over the patches (where they ran) ``optimise_s``,
            ``refine_s``, ``read_s``, ``samples_s``, ``starts_s``; throughput: texel-view iterations per
            second of the optimisation.
        sample_count: samples (texel x view) fitted; patches: number of patches.
        view_count: ``(Ht, Wt)`` int32 fitting views that see each texel (a reliability map).
        units: per patch index (a string), where and how long it ran (:meth:`UnitOutcome.placement`;
            the patches of earlier, resumed runs included). fronts: the wavefront's fronts, lists of
            patch indices (:func:`polarface.inverse.polarimetric.patch_units.patch_fronts`).
        homogeneous_values: ``config.homogeneous``'s maps -> the one value each was held at (the median
            of the first, free fit over its mask); empty without ``homogeneous``.
        cluster_labels: ``(Ht, Wt)`` int32 cluster of each texel with ``config.clustered`` (else None).
        cluster_values: ``config.clustered``'s maps -> the value each was held at, per cluster.
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
    units: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)
    fronts: list[list[int]] = dataclasses.field(default_factory=list)
    homogeneous_values: dict[str, float] = dataclasses.field(default_factory=dict)
    cluster_labels: np.ndarray | None = None
    cluster_values: dict[str, list[float]] = dataclasses.field(default_factory=dict)


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
    executor: Executor | None = None,
) -> PolarimetricFit:
    """Fit the static polarimetric maps to the fitting (not held-out) views of ``unwrap``.

    Args:
        unwrap: a complete :class:`UnwrapStore`.
        config: :class:`PolarimetricConfig`.
        device: torch device, or ``"auto"`` (``polarface.device.resolve_device``); checked here and
            resolved again by each patch where it runs.
        checkpoint: ``.npz`` path; resumes from it when present, rewritten atomically after every patch.
        progress: tqdm bar over patches.
        stop_after_patches: stop (returning ``complete=False``) after this many newly fitted patches
            (tests of interruption/resume).
        on_patch: callback ``(done, total)``.
        threads: torch intra-op threads during the fit and each patch (None: unchanged). Patch tensors
            hold ~1e5 elements, where OpenMP threads gain little and, on a busy machine, spin against
            other processes (docs/reconstruct.md): 1 is a safe choice. The fused
            kernel's threads are numba's (``NUMBA_NUM_THREADS``, default: all cores).
        engine: data-loss implementation: ``fused`` (numba kernel with analytic gradients, CPU),
            ``torch`` (vectorised autograd reference, any device) or ``auto`` (fused on CPU, torch
            otherwise). Both give the same loss and gradient (tests).
        executor: runs the patches, each once its earlier neighbours are done
            (:class:`~polarface.inverse.polarimetric.patch_units.PatchUnit`,
            :func:`~polarface.inverse.polarimetric.patch_units.run_patch_unit`); None: in this process
            (:class:`polarface.executors.LocalExecutor`). Started here, before the checkpoint is first
            written, and left open. The maps do not depend on it.

    Raises:
        ValueError: incomplete unwrap store, no fitting view, no texel visible in any fitting view, a
            bad device, engine or ``threads``; an unreachable executor (naming its argument).
        InterruptedError: a patch whose worker died on every attempt the executor makes (the patches
            done are kept in the checkpoint; a rerun resumes).
    """
    from polarface.device import resolve_device

    spec = "auto" if isinstance(device, str) and device == "auto" else str(torch.device(device))
    resolve_engine(engine, resolve_device(spec))  # a bad engine or device is refused here
    options = _PatchOptions(str(unwrap.path), config or PolarimetricConfig(), spec, engine, threads)
    fit = _fit_homogeneous if options.config.homogeneous else _fit
    fit = _fit_clustered if options.config.clustered else fit
    with torch_fit_settings(threads), shared_unwrap(options.unwrap, options.config.unwrap_cache_mb << 20):
        return fit(unwrap, options, checkpoint, progress, stop_after_patches, on_patch,
                   executor or LocalExecutor())


@dataclasses.dataclass(frozen=True)
class _PatchOptions:
    """What every :class:`PatchUnit` of a fit shares: the store's path, options, device spec, engine,
    threads."""

    unwrap: str
    config: PolarimetricConfig
    device: str
    engine: str
    threads: int | None

    def unit(self, index: int, rows: slice, cols: slice, scale: float, state: _FitState) -> PatchUnit:
        """Patch ``index``'s unit, with a copy of its haloed region of ``state``."""
        hrows, hcols, _ = haloed_slices(rows, cols, self.config.halo, state.initialised.shape)
        return PatchUnit(
            self.unwrap, index, rows, cols, self.config, scale, self.device, self.engine, self.threads,
            {k: np.array(v[hrows, hcols]) for k, v in state.raw.items()},
            np.array(state.initialised[hrows, hcols]),
        )  # fmt: skip


@dataclasses.dataclass
class _FitState:
    """What a checkpoint holds: raw variables (name -> ``(Ht, Wt, c)``), the ``(Ht, Wt)`` bool texels that
    have their closed-form starts, the indices of the patches done, the loss curve and the units'
    placements (:attr:`PolarimetricFit.units`).

    The loss curve is summed over the patches in row-major order, whatever order they finish in (float
    sums depend on it): ``curve`` holds the sum over patches ``0 .. folded - 1``, ``pending`` the
    curves of the patches done after them.
    """

    raw: dict[str, np.ndarray]
    initialised: np.ndarray
    done: set[int]
    curve: list[float]
    folded: int = 0
    pending: dict[int, list[float]] = dataclasses.field(default_factory=dict)
    units: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)

    @classmethod
    def start(
        cls, resolution: tuple[int, int], side: int, config: PolarimetricConfig, checkpoint: Path | None,
        start_maps: dict[str, np.ndarray] | None = None,
    ) -> _FitState:
        """The initial state (``start_maps``: name -> ``(Ht, Wt)`` values of those maps over the default
        starts), or the checkpoint's when it exists and matches ``side`` and ``resolution`` (a checkpoint
        of the row-major loop, without pending curves, too)."""
        height, width = resolution
        state = cls(initial_raw((height, width), config), np.zeros((height, width), bool), set(), [])
        if start_maps:
            maps = fit_maps_from_raw(state.raw, config)
            maps = {k: v[..., None] if v.ndim == 2 else v for k, v in maps.items()}
            maps.update({k: np.asarray(v, np.float64)[..., None] for k, v in start_maps.items()})
            raw = raw_from_maps(maps, config)
            names = set(start_maps) | ({"alpha_ss"} if "alpha_s" in start_maps else set())  # > alpha_s
            if config.lobes == "one":
                names -= {"alpha_ss", "rho_ss"}  # the absent lobe keeps its raw value
            for name in names:
                state.raw[name] = raw[name].astype(np.float32)
        if checkpoint is None or not checkpoint.exists():
            return state
        with np.load(checkpoint) as saved:
            if int(saved["patch_side"]) != side or tuple(saved["resolution"]) != (height, width):
                return state
            state.raw = {k: saved[f"raw_{k}"] for k in state.raw}
            state.initialised = saved["initialised"]
            state.done = {int(i) for i in saved["done"]}
            state.curve = [float(v) for v in saved["curve"]]
            state.folded = int(saved["curve_folded"]) if "curve_folded" in saved.files else len(state.done)
            if "pending_index" in saved.files:
                state.pending = _pending_curves(saved["pending_index"], saved["pending_lengths"],
                                                saved["pending_curve"])
            if "units" in saved.files:
                state.units = json.loads(str(saved["units"]))
        return state

    def apply(self, result: PatchResult, rows: slice, cols: slice, halo: int) -> None:
        """Write a patch's result: the starts into its halo, then its interior; mark it done."""
        hrows, hcols, _ = haloed_slices(rows, cols, halo, self.initialised.shape)
        if result.started is not None and result.starts is not None:
            for k, values in result.starts.items():
                self.raw[k][hrows, hcols][result.started] = values
            self.initialised[hrows, hcols] = True
        for k, values in (result.interior or {}).items():
            self.raw[k][rows, cols] = values
        self.done.add(result.index)
        self.pending[result.index] = list(result.curve)
        while self.folded in self.pending:  # curve[step] += the patch's value, patches in row-major order
            for step, value in enumerate(self.pending.pop(self.folded)):
                if len(self.curve) <= step:
                    self.curve.append(0.0)
                self.curve[step] += value
            self.folded += 1

    def snapshot(self) -> _FitState:
        """A copy that later patches do not change (what a checkpoint written in the background holds)."""
        return copy.deepcopy(self)

    def save(self, checkpoint: Path, side: int, resolution: tuple[int, int]) -> None:
        """Write the state to ``checkpoint`` (``.npz``) atomically."""
        from polarface.io import atomic_path

        height, width = resolution
        order = sorted(self.pending)
        with atomic_path(checkpoint) as tmp:
            with open(tmp, "wb") as handle:
                np.savez(
                    handle,
                    patch_side=side,
                    resolution=np.array([height, width]),
                    initialised=self.initialised,
                    done=np.array(sorted(self.done), dtype=np.int64),
                    curve=np.array(self.curve, dtype=np.float64),
                    curve_folded=self.folded,
                    pending_index=np.array(order, dtype=np.int64),
                    pending_lengths=np.array([len(self.pending[i]) for i in order], dtype=np.int64),
                    pending_curve=np.array([v for i in order for v in self.pending[i]], dtype=np.float64),
                    units=np.array(json.dumps(self.units)),
                    **{f"raw_{k}": v for k, v in self.raw.items()},
                )


def _pending_curves(indices: np.ndarray, lengths: np.ndarray, values: np.ndarray) -> dict[int, list[float]]:
    """A checkpoint's pending curves: patch index -> its ``length`` values, concatenated in ``values``."""
    ends = np.cumsum(lengths)
    return {int(index): [float(v) for v in values[end - length : end]]
            for index, length, end in zip(indices, lengths, ends, strict=True)}


@dataclasses.dataclass
class _Tally:
    """Running totals of a fit: samples fitted, optimiser seconds and work (samples x iterations),
    seconds of the lobe refinement, of reading the store, of building samples and of the closed-form
    starts, and the ``(Ht, Wt)`` bool texels seen by a fitted patch."""

    seen: np.ndarray
    samples: int = 0
    optimise_s: float = 0.0
    work: float = 0.0
    refine_s: float = 0.0
    read_s: float = 0.0
    samples_s: float = 0.0
    starts_s: float = 0.0

    def add(self, result: PatchResult, rows: slice, cols: slice, iterations: int) -> None:
        """Add one patch's counters."""
        self.samples += result.samples
        self.work += result.samples * int(iterations)
        self.optimise_s += result.optimise_s
        self.refine_s += result.refine_s
        self.read_s += result.read_s
        self.samples_s += result.samples_s
        self.starts_s += result.starts_s
        if result.seen is not None:
            self.seen[rows, cols] |= result.seen


def fit_coverage(unwrap: UnwrapStore, counts: np.ndarray, config: PolarimetricConfig
                 ) -> tuple[np.ndarray, np.ndarray]:
    """``(mask, view_count)`` of :class:`PolarimetricFit` from the store's ``counts``
    (:meth:`UnwrapStore.visible_count`; so it also counts the texels of patches fitted before a resume)."""
    view_count = counts * np.asarray(unwrap.root["texel/mask"][...])
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


def _checked_scale(unwrap: UnwrapStore) -> float:
    """The observation scale (mean ``I_sss`` of the fitting views) of a store fit to be fitted."""
    if not unwrap.complete:
        raise ValueError(f"unwrap store '{unwrap.path}' is incomplete; rerun the unwrapping")
    fitting = [i for i, v in enumerate(unwrap.views) if not v.held_out]
    if not fitting:
        raise ValueError("no fitting view: every view is held out")
    scale = unwrap.mean_i_sss(fitting)
    if not scale > 0:
        raise ValueError("no texel is visible in any fitting view (all-invisible texels)")
    return scale


def _lost_patch_error(failed: dict[int, str], patches: list[tuple[slice, slice]], done: int,
                      checkpoint: Path | None) -> InterruptedError:
    """The error of a fit whose patches' workers died more often than the executor retries (the first
    such patch named)."""
    index, reason = min(failed.items())
    rows, cols = patches[index]
    kept = f"kept in '{checkpoint}'" if checkpoint is not None else "not kept (no checkpoint)"
    return InterruptedError(
        f"polarimetric patch {index} (texture rows {rows.start}-{rows.stop - 1}, columns {cols.start}-"
        f"{cols.stop - 1}): {reason}; the {done} patches done are {kept}: rerun to resume"
    )


def _pass_checkpoint(checkpoint: str | Path | None, tag: str) -> Path | None:
    """The checkpoint of a fit's earlier pass ``tag``: ``STEM_<tag>.npz`` beside ``checkpoint`` (None
    without one)."""
    if checkpoint is None:
        return None
    return Path(checkpoint).with_name(f"{Path(checkpoint).stem}_{tag}.npz")


def _fit_homogeneous(
    unwrap: UnwrapStore,
    options: _PatchOptions,
    checkpoint: str | Path | None,
    progress: bool,
    stop_after_patches: int | None,
    on_patch: Callable[[int, int], None] | None,
    executor: Executor,
) -> PolarimetricFit:
    """``config.homogeneous``: :func:`_fit` with those maps free per texel (checkpoint ``STEM_free.npz``
    beside ``checkpoint``), then again with each fixed at its median over the first fit's mask. The
    median stands for the one value a joint fit over the face would find (the texels' free values
    scatter around it); both passes resume from their checkpoints."""
    config = options.config
    free = dataclasses.replace(options, config=dataclasses.replace(config, homogeneous=()))
    free_checkpoint = _pass_checkpoint(checkpoint, "free")
    first = _fit(unwrap, free, free_checkpoint, progress, stop_after_patches, on_patch, executor)
    if not first.complete:
        return first
    values = {name: float(np.median(first.maps[name][first.mask])) for name in config.homogeneous}
    fixed = dataclasses.replace(config, homogeneous=(), **{f"fixed_{name}": v for name, v in values.items()})
    second = _fit(unwrap, dataclasses.replace(options, config=fixed), checkpoint, progress,
                  stop_after_patches, on_patch, executor)
    second.homogeneous_values = values
    second.timings["free_fit_s"] = first.timings.get("fit_s", 0.0)
    return second


def _fit_clustered(
    unwrap: UnwrapStore,
    options: _PatchOptions,
    checkpoint: str | Path | None,
    progress: bool,
    stop_after_patches: int | None,
    on_patch: Callable[[int, int], None] | None,
    executor: Executor,
) -> PolarimetricFit:
    """``config.clustered`` (the ``hwang2022`` variant): a free fit (checkpoint ``STEM_free.npz``), k-means
    clusters of its diffuse albedo and each clustered map's median per cluster; then ``cluster_rounds``
    alternations of an index pass (eta free, the other clustered maps held at their cluster values;
    ``STEM_index<r>.npz``) and a specular pass (eta held, the others free; ``STEM_specular<r>.npz``),
    each updating the cluster values of the maps it freed; last the final pass with every clustered map
    held (``checkpoint``). Per-texel maps (the diffuse albedo, the detail) are fitted in every pass. Every
    pass resumes from its checkpoint."""
    config = options.config
    base = dataclasses.replace(config, clustered=(), held=())

    def run(tag: str, held: tuple[str, ...], start: dict[str, np.ndarray] | None) -> PolarimetricFit:
        path = _pass_checkpoint(checkpoint, tag) if tag else checkpoint
        return _fit(unwrap, dataclasses.replace(options, config=dataclasses.replace(base, held=held)), path,
                    progress, stop_after_patches, on_patch, executor, start)

    fit = run("free", (), None)
    if not fit.complete:
        return fit
    labels = albedo_clusters(fit.maps["rho_sss_bar"], fit.mask, config.clusters, config.seed)
    shared = {name: cluster_values(fit.maps[name], labels, fit.mask, config.clusters)
              for name in config.clustered}
    index = tuple(name for name in config.clustered if name == "eta")
    specular = tuple(name for name in config.clustered if name != "eta")
    for round_ in range(config.cluster_rounds if index and specular else 0):
        for tag, held, freed in ((f"index{round_}", specular, index), (f"specular{round_}", index, specular)):
            fit = run(tag, held, {name: shared[name][labels] for name in held})
            if not fit.complete:
                return fit
            shared.update({name: cluster_values(fit.maps[name], labels, fit.mask, config.clusters)
                           for name in freed})
    final = run("", config.clustered, {name: shared[name][labels] for name in config.clustered})
    final.cluster_labels = labels
    final.cluster_values = {name: [float(v) for v in values] for name, values in shared.items()}
    return final


def _fit(
    unwrap: UnwrapStore,
    options: _PatchOptions,
    checkpoint: str | Path | None,
    progress: bool,
    stop_after_patches: int | None,
    on_patch: Callable[[int, int], None] | None,
    executor: Executor,
    start_maps: dict[str, np.ndarray] | None = None,
) -> PolarimetricFit:
    """The patches as executor units in wavefront order, each once its earlier neighbours are done
    (module docstring of :mod:`~polarface.inverse.polarimetric.patch_units`); ``start_maps``: name ->
    ``(Ht, Wt)`` starting values of those maps (:meth:`_FitState.start`)."""
    config = options.config
    torch.manual_seed(config.seed)
    scale = _checked_scale(unwrap)
    started = time.perf_counter()
    counts = unwrap.visible_count()
    side = patch_side(counts, config)
    patches = list(unwrap.patches(side))
    fronts = patch_fronts(patches, side, config.halo)
    ckpt = Path(checkpoint) if checkpoint is not None else None
    state = _FitState.start(unwrap.resolution, side, config, ckpt, start_maps)
    tally = _Tally(np.zeros(unwrap.resolution, bool))
    executor.start()
    failed: dict[int, str] = {}
    bar = tqdm(total=len(patches), desc="polarimetric fit", unit="patch", disable=not progress)
    bar.update(len(state.done))

    def done(outcome: UnitOutcome) -> None:
        index = outcome.unit.index
        if not outcome.ok:
            failed[index] = str(outcome.error)
            return
        rows, cols = patches[index]
        state.apply(outcome.value, rows, cols, config.halo)
        tally.add(outcome.value, rows, cols, config.iterations)
        state.units[str(index)] = outcome.placement()
        if ckpt is not None:  # written by the saver thread while the workers go on with the next patches
            saves.append(saver.submit(state.snapshot().save, ckpt, side, unwrap.resolution))
        bar.update(1)
        if on_patch is not None:
            on_patch(len(state.done), len(patches))

    # the patches not done, front by front (the order the schedule prefers); each waits for its earlier
    # neighbours not done yet, and its unit is built from the state once they are
    todo = [index for front in fronts for index in front if index not in state.done]
    if stop_after_patches is not None:
        todo = todo[:stop_after_patches]  # a prefix of the front order holds every patch its patches wait for
    position = {index: k for k, index in enumerate(todo)}
    waits = patch_waits(patches, side, config.halo)
    after = [[position[w] for w in waits[index] if w in position] for index in todo]
    saves: list[concurrent.futures.Future] = []
    try:
        # one saver thread writes the checkpoints in order; leaving the block waits for the last one
        with concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="checkpoint") as saver:
            executor.map_dependent(run_patch_unit, len(todo),
                                   lambda k: options.unit(todo[k], *patches[todo[k]], scale, state), after,
                                   failures=(), on_done=done)
    finally:
        bar.close()
    for save in saves:
        save.result()  # a checkpoint that could not be written fails the fit
    if failed:
        raise _lost_patch_error(failed, patches, len(state.done), ckpt)
    if len(state.done) < len(patches):  # stopped after stop_after_patches
        return PolarimetricFit(
            fit_maps_from_raw(state.raw, config), tally.seen, state.curve, {}, 0.0, tally.samples,
            len(patches), complete=False, units=state.units, fronts=fronts,
        )  # fmt: skip
    mask_seen, view_count = fit_coverage(unwrap, counts, config)
    curve_mean = [v / max(len(patches), 1) for v in state.curve]
    timings = {
        "fit_s": time.perf_counter() - started, "optimise_s": tally.optimise_s, "refine_s": tally.refine_s,
        "read_s": tally.read_s, "samples_s": tally.samples_s, "starts_s": tally.starts_s,
    }  # fmt: skip
    throughput = tally.work / tally.optimise_s if tally.optimise_s > 0 else 0.0
    return PolarimetricFit(
        fit_maps_from_raw(state.raw, config), mask_seen, curve_mean, timings, throughput, tally.samples,
        len(patches), view_count=view_count.astype(np.int32), units=state.units, fronts=fronts,
    )  # fmt: skip
