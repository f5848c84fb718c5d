"""The static fit's texture patches as executor units, and the wavefront schedule that lets them run in
parallel with the maps of the row-major patch loop, bit for bit.

A patch (interior ``rows x cols``) is fitted on its *haloed region*: the interior plus ``halo`` texels on
every side (clipped to the texture). It reads the region's raw variables and the flags of the texels that
already have their closed-form starts, and it writes its interior's fitted raw variables plus the starts
of the region's texels not started yet. So the maps depend on the order of the patches: each starts from
what the patches before it wrote into its halo.

Wavefront schedule (:func:`patch_fronts`). On the patch grid (patch ``(i, j)`` covers rows ``i side ..``
and columns ``j side ..``), two haloed regions overlap only for 8-neighbours when ``side >= 2 halo``
(patches two apart are ``side - 2 halo >= 0`` texels apart). In row-major order the neighbours before
``(i, j)`` are ``(i, j-1)``, ``(i-1, j-1)``, ``(i-1, j)`` and ``(i-1, j+1)``; with the front index
``t = 2 i + j`` every one of them has a smaller ``t`` and every later neighbour a larger one, and the
patches of one front never overlap. Running the fronts in order of ``t``, the patches of a front as
independent units, every patch therefore sees exactly the region it sees in row-major order, and the
maps are the row-major maps. With ``side < 2 halo`` every patch is its own front (row-major order).
The fit does not wait for a whole front, though: a patch runs as soon as its earlier neighbours are done
(:func:`patch_waits`, :meth:`polarface.executors.Executor.map_dependent`), which gives the same regions
and maps without holding the workers at the fronts' barriers.

A unit (:class:`PatchUnit`) carries the unwrap store's path (the unit reads its samples there itself),
the patch's slices, the options and the small haloed state; :func:`run_patch_unit` returns what the
patch writes (:class:`PatchResult`) and changes nothing else, so a unit can be run again after its worker
died. Nothing in a patch's fit is random (``torch.manual_seed(config.seed)`` is set per unit all the
same); torch's thread count and denormal flushing are set per unit (:func:`torch_fit_settings`).

Reads: a patch should not decode again the chunks its neighbours decoded, so units read the unwrap store
through a chunk cache of ``config.unwrap_cache_mb`` (:mod:`polarface.texture.unwrap_store`). Inside
:func:`shared_unwrap` (the fit holds it around its fronts) the units of the fit's process share one
cached store object; a worker process of an executor (``processes``, Ray) keeps one cached store for the
units it runs next and opens it again when they read another store, or when the store on disk was
replaced. The maps do not depend on it (cached reads equal uncached ones).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import time
from collections.abc import Iterator, Sequence

import numpy as np
import torch

from polarface.inverse.polarimetric.config import PolarimetricConfig, maps_from_raw
from polarface.inverse.polarimetric.engines import resolve_engine
from polarface.inverse.polarimetric.init import apply_closed_form_starts
from polarface.inverse.polarimetric.model import SampleBatch
from polarface.inverse.polarimetric.optimise import optimise_patch
from polarface.inverse.polarimetric.problem import (
    PatchProblem,
    build_patch_fused_samples,
    build_patch_samples,
)
from polarface.inverse.polarimetric.refine import refine_patch_lobes
from polarface.texture import UnwrapStore

__all__ = [
    "STARTED_VARIABLES",
    "PatchResult",
    "PatchUnit",
    "haloed_slices",
    "patch_fronts",
    "patch_side",
    "patch_waits",
    "run_patch_unit",
    "shared_unwrap",
    "torch_fit_settings",
]

#: Raw variables whose closed-form starts a patch writes into its halo (texels not started yet).
STARTED_VARIABLES = ("rho_sss_bar", "rho_s", "eta", "alpha_s")

_FLUSH_DEPTH = [0]  # nesting depth of torch_fit_settings (the outermost one sets and clears flushing)

_SHARED: dict[str, UnwrapStore] = {}  # store path -> the cached store of the fit running (shared_unwrap)
_HELD: dict[str, tuple[tuple, UnwrapStore]] = {}  # "store": (identity, store) a worker keeps (_unit_store)


@contextlib.contextmanager
def shared_unwrap(path: str, cache_bytes: int) -> Iterator[UnwrapStore]:
    """While open, :func:`run_patch_unit` in this process reads the unwrap store at ``path`` through one
    read-only store object with a chunk cache of ``cache_bytes`` (released on exit; nested: the outer
    one's). The store must not be written meanwhile."""
    key = str(path)
    if key in _SHARED:
        yield _SHARED[key]
        return
    _SHARED[key] = UnwrapStore.open(path, cache_bytes=cache_bytes)
    try:
        yield _SHARED[key]
    finally:
        del _SHARED[key]


@contextlib.contextmanager
def torch_fit_settings(threads: int | None) -> Iterator[None]:
    """Torch settings of a fit, restored afterwards: ``threads`` intra-op threads (None: unchanged) and
    denormals flushed to zero (RMSprop's running averages of tiny gradients reach denormal floats, whose
    arithmetic is ~20x slower). Re-entrant: nested inside another, it leaves the flushing to the outer one.

    Raises:
        ValueError: ``threads < 1``.
    """
    if threads is not None and int(threads) < 1:
        raise ValueError(f"argument 'threads' must be >= 1; got {threads}")
    previous_threads = torch.get_num_threads()
    flushing = torch.set_flush_denormal(True) if _FLUSH_DEPTH[0] == 0 else False
    _FLUSH_DEPTH[0] += 1
    if threads is not None:
        torch.set_num_threads(int(threads))
    try:
        yield
    finally:
        _FLUSH_DEPTH[0] -= 1
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


def _grid_cells(patches: Sequence[tuple[slice, slice]], side: int, halo: int) -> list[tuple[int, int]]:
    """Each patch's cell ``(i, j)`` on the ``side`` grid, after checking the arguments (as
    :func:`patch_fronts`)."""
    if int(side) < 1 or int(halo) < 0:
        raise ValueError(f"arguments 'side' >= 1 and 'halo' >= 0 required; got {side}, {halo}")
    cells = []
    for index, (rows, cols) in enumerate(patches):
        if rows.start % side or cols.start % side:
            raise ValueError(f"argument 'patches': patch {index} ({rows}, {cols}) is not on the {side} grid")
        cells.append((rows.start // side, cols.start // side))
    return cells


def patch_side(counts: np.ndarray, config: PolarimetricConfig) -> int:
    """The patch side that holds about ``config.sample_budget`` samples with its halo, for ``counts``
    ``(Ht, Wt)`` fitting views per texel (:meth:`UnwrapStore.visible_count`)."""
    seen = counts[counts > 0]
    per_texel = float(seen.mean()) if seen.size else 1.0
    side = int(math.sqrt(config.sample_budget / max(per_texel, 1.0))) - 2 * config.halo
    return int(max(8, min(config.patch, side)))


def patch_fronts(patches: Sequence[tuple[slice, slice]], side: int, halo: int) -> list[list[int]]:
    """The wavefront schedule (module docstring): indices into ``patches`` grouped into fronts, fronts in
    the order they must run, indices ascending within a front.

    Args:
        patches: ``(rows, cols)`` of each patch in row-major order (``UnwrapStore.patches(side)``; patches
            without atlas texels may be missing); each starts on a multiple of ``side``.
        side: the patch side (texels); halo: the halo width (texels).

    Raises:
        ValueError: ``side < 1``, ``halo < 0``, or a patch that does not start on the ``side`` grid.
    """
    cells = _grid_cells(patches, side, halo)
    if side < 2 * halo:  # haloed regions of patches two apart overlap: row-major order, one by one
        return [[index] for index in range(len(patches))]
    fronts: dict[int, list[int]] = {}
    for index, (i, j) in enumerate(cells):
        fronts.setdefault(2 * i + j, []).append(index)
    return [fronts[t] for t in sorted(fronts)]


def patch_waits(patches: Sequence[tuple[slice, slice]], side: int, halo: int) -> list[list[int]]:
    """For each patch (index into ``patches``), the patches whose results its haloed region reads and
    that come before it: its earlier neighbours in row-major order that are in ``patches``
    (``(i, j-1)``, ``(i-1, j-1)``, ``(i-1, j)``, ``(i-1, j+1)``; module docstring); with ``side < 2 halo``
    the patch before it; with ``halo`` 0 none. Arguments and errors as :func:`patch_fronts`."""
    cells = _grid_cells(patches, side, halo)
    if not halo:
        return [[] for _ in patches]
    if side < 2 * halo:
        return [[index - 1] if index else [] for index in range(len(patches))]
    at = {cell: index for index, cell in enumerate(cells)}
    return [[at[cell] for cell in ((i, j - 1), (i - 1, j - 1), (i - 1, j), (i - 1, j + 1)) if cell in at]
            for i, j in cells]


@dataclasses.dataclass(frozen=True, eq=False)
class PatchUnit:
    """One patch of the static fit as an executor unit (module docstring).

    Attributes:
        unwrap: the unwrap store's path (:meth:`polarface.texture.UnwrapStore.open`), read by the unit.
        index: the patch's index in row-major order (``UnwrapStore.patches(side)``).
        rows, cols: the patch's interior (texture rows and columns).
        config: the fit's options (``halo``, optimiser, weights, ranges).
        scale: the observation scale, mean ``I_sss`` of the fitting views (> 0).
        device: torch device spec, resolved where the unit runs (``polarface.device.resolve_device``).
        engine: ``fused``, ``torch`` or ``auto`` (:func:`polarface.inverse.polarimetric.resolve_engine`).
        threads: torch intra-op threads during the unit (None: unchanged).
        raw: the haloed region's raw variables, name -> ``(h, w, c)`` float32 (``h, w``: the region of
            :func:`haloed_slices`).
        initialised: ``(h, w)`` bool texels of the region that have their closed-form starts.
    """

    unwrap: str
    index: int
    rows: slice
    cols: slice
    config: PolarimetricConfig
    scale: float
    device: str
    engine: str
    threads: int | None
    raw: dict[str, np.ndarray]
    initialised: np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class PatchResult:
    """What a patch writes (:func:`run_patch_unit`); the empty defaults: nothing visible, nothing written.

    Attributes:
        index: the patch's index (:attr:`PatchUnit.index`).
        interior: the fitted raw variables of the interior, name -> ``(rows, cols, c)``; None: nothing
            visible in the haloed region.
        started: ``(h, w)`` bool texels of the haloed region that got their closed-form starts (None: none).
        starts: :data:`STARTED_VARIABLES` -> ``(started.sum(), c)`` their starts (raw).
        curve: the patch's loss per optimiser evaluation (``optimise_patch``'s curve).
        samples: samples (texel x view) fitted.
        seen: ``(rows, cols)`` bool interior texels with samples (None: none).
        optimise_s, refine_s: seconds of the optimiser and of the lobe refinement.
        read_s, samples_s, starts_s: seconds of reading the store, of building the samples and of the
            closed-form starts (the fused engine's split; the reference batch's reading counts as
            building).
    """

    index: int
    interior: dict[str, np.ndarray] | None = None
    started: np.ndarray | None = None
    starts: dict[str, np.ndarray] | None = None
    curve: list[float] = dataclasses.field(default_factory=list)
    samples: int = 0
    seen: np.ndarray | None = None
    optimise_s: float = 0.0
    refine_s: float = 0.0
    read_s: float = 0.0
    samples_s: float = 0.0
    starts_s: float = 0.0


def run_patch_unit(unit: PatchUnit) -> PatchResult:
    """Fit one patch (:class:`PatchUnit`): closed-form starts of the region's texels not started yet, the
    optimiser, the optional lobe refinement; returns what the patch writes (:class:`PatchResult`).

    Raises:
        FileNotFoundError, ValueError: the unwrap store is missing or not one; ValueError: a bad device,
            engine or ``threads``.
    """
    from polarface.device import resolve_device

    device = resolve_device(unit.device)
    engine = resolve_engine(unit.engine, device)
    unwrap = _unit_store(unit)
    with torch_fit_settings(unit.threads):
        torch.manual_seed(unit.config.seed)
        return _fit_region(unwrap, unit, device, engine.fused_samples)


def _store_identity(path: str, cache_bytes: int) -> tuple:
    """What tells a store apart from one written again at the same path: the local folder's and its
    metadata file's inode, modification and status-change times (a copy keeps the modification time and
    may get a freed inode again, not the status-change time; a URL: its path only)."""
    stamps = []
    for candidate in (path, os.path.join(path, "zarr.json"), os.path.join(path, ".zattrs")):
        with contextlib.suppress(OSError):
            status = os.stat(candidate)
            stamps.append((status.st_ino, status.st_mtime_ns, status.st_ctime_ns))
    return (path, cache_bytes, tuple(stamps))


def _unit_store(unit: PatchUnit) -> UnwrapStore:
    """The store a unit reads (module docstring): the fit's shared one in the fit's process, else the one
    this worker process keeps, opened again for another store or a store replaced on disk."""
    path = str(unit.unwrap)
    if path in _SHARED:
        return _SHARED[path]
    cache_bytes = int(unit.config.unwrap_cache_mb) << 20
    identity = _store_identity(path, cache_bytes)
    held = _HELD.get("store")
    if held is None or held[0] != identity:
        _HELD.clear()  # the previous store's cache goes before the next one fills
        _HELD["store"] = (identity, UnwrapStore.open(path, cache_bytes=cache_bytes))
    return _HELD["store"][1]


def _fit_region(unwrap: UnwrapStore, unit: PatchUnit, device: torch.device, fused: bool) -> PatchResult:
    """:func:`run_patch_unit` on the open store (``fused``: the engine's fused samples)."""
    dtype, config = torch.float32, unit.config
    hrows, hcols, (ir, ic) = haloed_slices(unit.rows, unit.cols, config.halo, unwrap.resolution)
    views = unwrap.views
    fitting = [i for i, view in enumerate(views) if not view.held_out]
    # the fused engine fits, and starts, on its compact samples; the per-sample-and-light reference batch
    # is built only where something needs it (the torch engine, the lobe refinement)
    reference: SampleBatch | None = None
    split: dict[str, float] = {}
    if fused and config.refine_lobes_iterations <= 0:
        packed, geometry = build_patch_fused_samples(unwrap, hrows, hcols, fitting, views, dtype=dtype,
                                                     timings=split)
    else:
        tick = time.perf_counter()
        built = build_patch_samples(unwrap, hrows, hcols, fitting, views, dtype=dtype, device=device,
                                    fused=fused)
        reference, geometry, packed = built[0], built[1], (built[2] if fused else None)
        split["samples_s"] = time.perf_counter() - tick
    if packed is None and reference is None:
        return PatchResult(unit.index)
    problem = PatchProblem(None if fused else reference, geometry, config, unit.scale, dtype, device, packed)
    # copies: arrays a unit arrives with may be read-only (Ray's object store)
    patch_raw = {k: torch.as_tensor(np.array(v), dtype=dtype, device=device) for k, v in unit.raw.items()}
    todo = ~np.asarray(unit.initialised, bool)
    tick = time.perf_counter()
    if todo.any():
        starts_from = packed if packed is not None else reference
        apply_closed_form_starts(starts_from, patch_raw, todo, problem.normals, config, dtype, device)
    split["starts_s"] = time.perf_counter() - tick
    if packed is not None:
        sample_count, seen_texels = packed.count, np.flatnonzero(np.diff(packed.offsets))
    else:
        sample_count, seen_texels = reference.count, reference.texel.cpu().numpy()
    curve: list[float] = []
    tick = time.perf_counter()
    result = optimise_patch(problem, patch_raw, config, curve)
    optimise_s, refine_s = time.perf_counter() - tick, 0.0
    if config.refine_lobes_iterations > 0:  # Levenberg-Marquardt on the four lobe maps
        tick = time.perf_counter()
        with torch.no_grad():
            normal = problem.normals(maps_from_raw(result, config)["displacement_mm"][..., 0])
        result = refine_patch_lobes(reference, result, normal, problem.mask, config, unit.scale)
        refine_s = time.perf_counter() - tick
    seen = np.zeros(geometry.mask.shape, bool)
    seen.reshape(-1)[seen_texels] = True
    # halo texels not yet fitted keep their closed-form starts (a better start for the next patches)
    starts = {k: patch_raw[k].cpu().numpy()[todo] for k in STARTED_VARIABLES} if todo.any() else None
    return PatchResult(
        unit.index, {k: v[ir, ic].cpu().numpy() for k, v in result.items()}, todo if todo.any() else None,
        starts, curve, int(sample_count), seen[ir, ic], optimise_s, refine_s, split.get("read_s", 0.0),
        split.get("samples_s", 0.0), split["starts_s"],
    )  # fmt: skip
