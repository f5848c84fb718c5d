"""Per-frame (dynamic) polarimetric fit (paper supplement, "Dynamic Inverse Rendering Details").

A dynamic frame is seen by few views (typically the two polarimetric cameras of one frame: one sees
channels 0-2, the other 3-5), too few to separate all the static unknowns. With the refractive index
and both roughnesses fixed from the static result, :func:`fit_dynamic_frame` optimises per texel
``rho_s^t, rho_ss^t, rho_sss_bar^t`` (6 channels) and the displacement ``H^t`` (mm) of the frame,
minimising the loss of :mod:`polarface.inverse.polarimetric.dynamic_loss` (the static stage's data
terms and the temporal and spatial regulariser ``L_reg~`` towards the static maps).

Reparameterisation (ranges from the static :class:`~polarface.inverse.polarimetric.config.PolarimetricConfig`)
and patch processing with halos are those of :mod:`polarface.inverse.polarimetric.fit`, with each patch
cropped to the texels within ``DynamicConfig.seen_margin`` of a texel a fitting view sees
(:func:`frame_patches`; a frame's views see ~16 % of the atlas); the optimiser
is torch's RMSprop (or Adam) with the static stage's learning-rate schedule
(:func:`~polarface.inverse.polarimetric.optimise.learning_rate_schedule`); only the raw variables of
``rho_s, rho_ss, rho_sss_bar, displacement_mm`` are leaves, eta and the roughnesses are constants.

Measured on the simulator's demo dynamic frames (ground-truth frame mesh, the true static maps as the
static result; defaults, 2 shared CPU cores): ~1e5 samples and 6-7 s per frame; median relative
error of rho_sss_bar 2.3 % inside the result mask (the static start: 0 %; the objective's minimum under
noise); in the pressed forehead patch, whose albedo the static maps miss, the error falls from 8.4 % to
1.2 % (frame 0) and the mean change of the albedo is recovered (0.0184 fitted and true).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping

import numpy as np
import torch
from scipy import ndimage
from tqdm import tqdm

from polarface.inverse.polarimetric.config import (
    PARAMETER_NAMES,
    PolarimetricConfig,
    fit_maps_from_raw,
    initial_raw,
    raw_from_maps,
)
from polarface.inverse.polarimetric.dynamic_loss import (
    DYNAMIC_VARIABLES,
    FIXED_VARIABLES,
    DynamicPatchProblem,
    DynamicWeights,
)
from polarface.inverse.polarimetric.dynamic_step import optimise_dynamic_patch_fused
from polarface.inverse.polarimetric.engines import PolarimetricEngine, resolve_engine
from polarface.inverse.polarimetric.fit import (
    PolarimetricFit,
    fit_coverage,
    haloed_slices,
    torch_fit_settings,
)
from polarface.inverse.polarimetric.optimise import learning_rate_schedule, optimise_patch
from polarface.inverse.polarimetric.patch_units import patch_side
from polarface.inverse.polarimetric.problem import (
    PatchProblem,
    build_patch_fused_samples,
    build_patch_samples,
)
from polarface.texture import UnwrapStore

__all__ = ["DynamicConfig", "fit_dynamic_frame", "frame_patches"]

@dataclasses.dataclass(frozen=True)
class DynamicConfig:
    """Options of the per-frame fit.

    Attributes:
        weights: :class:`DynamicWeights`.
        optimizer, lr, iterations, lr_final_fraction, warmup: as in
            :class:`~polarface.inverse.polarimetric.config.PolarimetricConfig` (fewer iterations than the
            static stage: a frame starts from the static or the previous frame's maps).
        patch: largest patch side (texels; a frame has ~2 samples per texel, so patches can be larger
            than the static 64); halo: halo width (texels, >= 2); sample_budget: most samples per patch.
        min_views: fewest views that must see a texel for it to enter the result mask.
        boundary_margin: erosion (texels) of the region seen by ``min_views`` views.
        seen_margin: texels (Chebyshev distance) kept around the texels that at least one fitting view
            sees; each patch of the atlas grid is cropped to the bounding box of its texels within
            that distance (patches with none are skipped), so the fit spends no work on the large part
            of the atlas a frame's few views do not see (:func:`frame_patches`). Texels outside keep
            their start values. Unseen texels have no data term; they take part only through the H
            Laplacian's coupling (2 texels) and the normals' finite differences (1 texel), and each
            patch adds its ``halo`` of free texels beyond the margin. ``None``: the whole atlas grid
            (the behaviour before this option). Measured on the demo preset in docs/dynamic.md.
        seed: torch seed.
    """

    weights: DynamicWeights = dataclasses.field(default_factory=DynamicWeights)
    optimizer: str = "rmsprop"
    lr: float = 0.03
    iterations: int = 100
    lr_final_fraction: float = 0.1
    warmup: int = 10
    patch: int = 256
    halo: int = 4
    sample_budget: int = 300_000
    min_views: int = 2
    boundary_margin: int = 1
    seen_margin: int | None = 8
    seed: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.weights, DynamicWeights):
            raise ValueError(
                f"argument 'weights' must be a DynamicWeights; got {type(self.weights).__name__}"
            )
        margin = self.seen_margin
        if margin is not None and (isinstance(margin, bool) or not isinstance(margin, int | np.integer)
                                   or margin < 0):
            raise ValueError(f"argument 'seen_margin' must be None or an integer >= 0; got {margin!r}")
        self.optimiser_config(PolarimetricConfig())  # validates the shared fields, naming them

    def optimiser_config(self, static_config: PolarimetricConfig) -> PolarimetricConfig:
        """``static_config`` (for its reparameterisation ranges) with this config's optimiser and patch
        options."""
        shared = ("optimizer", "lr", "iterations", "lr_final_fraction", "warmup", "patch", "halo",
                  "sample_budget", "min_views", "boundary_margin", "seed")  # fmt: skip
        return dataclasses.replace(
            static_config, refine_lobes_iterations=0, **{name: getattr(self, name) for name in shared}
        )


def frame_patches(
    patches: list[tuple[slice, slice]], seen: np.ndarray, margin: int | None
) -> list[tuple[tuple[slice, slice], tuple[slice, slice]]]:
    """The patches a frame's fit optimises (:attr:`DynamicConfig.seen_margin`).

    Args:
        patches: ``(rows, cols)`` slices of the atlas grid (``UnwrapStore.patches(side)``, row-major).
        seen: ``(Ht, Wt)`` bool texels seen by at least one fitting view.
        margin: texels (Chebyshev distance) kept around ``seen``; None: every patch as it is.

    Returns:
        ``(cropped, patch)`` pairs in the order of ``patches``: each patch cropped to the bounding box of
        its texels within ``margin`` of a seen texel (``(rows, cols)`` slices), with the patch itself;
        patches without such a texel are left out. Where that region covers a patch's whole extent,
        ``cropped`` equals the patch.

    Raises:
        ValueError: ``seen`` not a 2-D bool array; ``margin`` negative.
    """
    if margin is None:
        return [(patch, patch) for patch in patches]
    seen = np.asarray(seen)
    if seen.ndim != 2 or seen.dtype != bool:
        raise ValueError(f"argument 'seen' must be a 2-D bool array; got {seen.dtype} {seen.shape}")
    if int(margin) < 0:
        raise ValueError(f"argument 'margin' must be >= 0; got {margin}")
    region = ndimage.maximum_filter(seen, size=2 * int(margin) + 1, mode="constant", cval=False)
    out = []
    for rows, cols in patches:
        block = region[rows, cols]
        kept_rows, kept_cols = np.flatnonzero(block.any(axis=1)), np.flatnonzero(block.any(axis=0))
        if kept_rows.size:
            cropped = (slice(rows.start + int(kept_rows[0]), rows.start + int(kept_rows[-1]) + 1),
                       slice(cols.start + int(kept_cols[0]), cols.start + int(kept_cols[-1]) + 1))
            out.append((cropped, (rows, cols)))
    return out


def _checked_maps(
    maps: Mapping[str, np.ndarray], argument: str, resolution: tuple[int, int], mask: np.ndarray
) -> dict[str, np.ndarray]:
    """``maps`` as float64 ``(Ht, Wt, c)`` arrays; ValueError naming ``argument`` and the map."""
    missing = [name for name in PARAMETER_NAMES if name not in maps]
    if missing:
        raise ValueError(f"argument '{argument}' lacks the maps {missing} (needs {list(PARAMETER_NAMES)})")
    out = {}
    for name in PARAMETER_NAMES:
        value = np.asarray(maps[name], dtype=np.float64)
        want = (*resolution, 6) if name == "rho_sss_bar" else resolution
        if value.shape != want:
            raise ValueError(
                f"argument '{argument}' map '{name}' has shape {value.shape}; the unwrap store needs {want}"
            )
        if not np.isfinite(value[mask]).all():
            raise ValueError(f"argument '{argument}' map '{name}' holds NaN/inf inside 'static_mask'")
        out[name] = value if value.ndim == 3 else value[..., None]
    return out


def _raw_maps(maps: Mapping[str, np.ndarray], config: PolarimetricConfig) -> dict[str, np.ndarray]:
    """Raw variables (float32 ``(Ht, Wt, c)``) of ``maps``; non-finite texels (outside the static mask)
    take the static stage's initial values."""
    fallback = initial_raw(maps["eta"].shape[:2], config)
    raw = raw_from_maps(
        {k: np.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0) for k, v in maps.items()}, config
    )
    out = {}
    for name, value in raw.items():
        bad = ~np.isfinite(maps[name])
        out[name] = np.where(bad, fallback[name], value).astype(np.float32)
    return out


@dataclasses.dataclass
class _FrameState:
    """Raw variables (name -> ``(Ht, Wt, c)`` float32): ``start`` (being optimised), ``static`` (the fixed
    maps and the temporal references); running totals: loss curve (sums over patches), samples,
    optimiser seconds and work (samples x iterations)."""

    start: dict[str, np.ndarray]
    static: dict[str, np.ndarray]
    curve: list[float] = dataclasses.field(default_factory=list)
    samples: int = 0
    optimise_s: float = 0.0
    work: float = 0.0


def _fit_patch(
    unwrap: UnwrapStore,
    rows: slice,
    cols: slice,
    fitting: list[int],
    engine: PolarimetricEngine,
    config: PolarimetricConfig,
    weights: DynamicWeights,
    scale: float,
    device: torch.device,
    state: _FrameState,
    texel_count: int,
) -> None:
    """Fit one patch (interior ``rows x cols`` plus a halo) and write its interior into ``state.start``;
    ``texel_count``: the loss's normaliser (:class:`DynamicPatchProblem`)."""
    dtype = torch.float32
    hrows, hcols, interior = haloed_slices(rows, cols, config.halo, unwrap.resolution)
    if engine.fused_samples:  # the fused samples alone (no per-sample-and-light reference batch)
        fused, geometry = build_patch_fused_samples(unwrap, hrows, hcols, fitting, unwrap.views, dtype=dtype)
        batch = None
        if fused is None:
            return
        count = fused.count
    else:
        batch, geometry = build_patch_samples(unwrap, hrows, hcols, fitting, unwrap.views, dtype=dtype,
                                              device=device)[:2]
        fused = None
        if batch is None:
            return
        count = batch.count
    problem = PatchProblem(batch, geometry, config, scale, dtype, device, fused)
    tensor = lambda a: torch.as_tensor(a[hrows, hcols], dtype=dtype, device=device)  # noqa: E731
    patch = DynamicPatchProblem(
        problem,
        {k: tensor(state.static[k]) for k in FIXED_VARIABLES},
        {k: tensor(state.static[k]) for k in DYNAMIC_VARIABLES},
        weights,
        texel_count,
    )
    tick = time.perf_counter()
    start = {k: tensor(state.start[k]) for k in DYNAMIC_VARIABLES}
    if fused is not None and device.type == "cpu" and config.optimizer == "rmsprop":  # steps in numba
        schedule = learning_rate_schedule(config)
        result = optimise_dynamic_patch_fused(patch, start, config, schedule, state.curve)
    else:
        result = optimise_patch(patch, start, config, state.curve, fused_steps=False,
                                variables=DYNAMIC_VARIABLES)
    state.optimise_s += time.perf_counter() - tick
    state.samples += count
    state.work += count * int(config.iterations)
    for name, value in result.items():
        state.start[name][rows, cols] = value[interior].cpu().numpy()


def fit_dynamic_frame(
    unwrap: UnwrapStore,
    static_maps: Mapping[str, np.ndarray],
    static_mask: np.ndarray,
    config: DynamicConfig | None = None,
    *,
    static_config: PolarimetricConfig | None = None,
    start_maps: Mapping[str, np.ndarray] | None = None,
    device: torch.device | str = "cpu",
    progress: bool = False,
    engine: str = "auto",
    threads: int | None = 1,
) -> PolarimetricFit:
    """Fit one dynamic frame's ``rho_s, rho_ss, rho_sss_bar`` and displacement (module docstring).

    Args:
        unwrap: the frame's complete :class:`UnwrapStore` (its fitting views; texel geometry = the frame's
            tracked mesh, same UV atlas and resolution as the static result).
        static_maps: the static result's maps, :data:`PARAMETER_NAMES` -> ``(Ht, Wt)`` (``rho_sss_bar``
            ``(Ht, Wt, 6)``; H in mm); values outside ``static_mask`` may be NaN.
        static_mask: ``(Ht, Wt)`` bool texels the static result reconstructed.
        config: :class:`DynamicConfig`.
        static_config: the static stage's configuration; its reparameterisation ranges (``eta_range``,
            ``alpha_range``, ``rho_max``, ``h_scale_mm``) are used.
        start_maps: start of the optimisation (e.g. the previous frame's maps, same layout as
            ``static_maps``); default the static maps.
        device, engine, threads: as in :func:`~polarface.inverse.polarimetric.fit.fit_polarimetric`.
        progress: tqdm bar over patches.

    Returns:
        :class:`~polarface.inverse.polarimetric.fit.PolarimetricFit`: all maps (float32; eta, alpha_s,
        alpha_ss are float32 copies of the static ones), mask = ``static_mask`` & texels seen by
        ``config.min_views`` views (that region eroded by ``config.boundary_margin``), the loss curve
        (mean per patch), timings ``optimise_s`` and ``fit_s`` (s), throughput (sample iterations/s)
        and the per-texel view count.

    Raises:
        ValueError: incomplete unwrap store or one without a fitting view or visible texel; maps missing,
            mis-shaped or non-finite inside the mask (naming ``static_maps``/``start_maps``);
            ``static_mask`` of the wrong shape; bad ``threads`` or ``engine``.
    """
    config = config or DynamicConfig()
    chosen = resolve_engine(engine, device)
    if not unwrap.complete:
        raise ValueError(f"argument 'unwrap': store '{unwrap.path}' is incomplete; rerun the unwrapping")
    mask = np.asarray(static_mask)
    if mask.shape != unwrap.resolution or mask.dtype != bool:
        raise ValueError(
            f"argument 'static_mask' must be bool {unwrap.resolution}; got {mask.dtype} {mask.shape}"
        )
    static = _checked_maps(static_maps, "static_maps", unwrap.resolution, mask)
    start = static if start_maps is None else _checked_maps(start_maps, "start_maps", unwrap.resolution, mask)
    optimiser_config = config.optimiser_config(static_config or PolarimetricConfig())
    with torch_fit_settings(threads):
        torch.manual_seed(config.seed)
        fit = _fit_frame(
            unwrap, static, start, optimiser_config, config.weights, config.seen_margin, torch.device(device),
            chosen, progress,
        )
    fit.mask &= mask
    for name in FIXED_VARIABLES:
        fit.maps[name] = np.array(static_maps[name], dtype=np.float32)
    return fit


def _fit_frame(
    unwrap: UnwrapStore,
    static: dict[str, np.ndarray],
    start: dict[str, np.ndarray],
    config: PolarimetricConfig,
    weights: DynamicWeights,
    seen_margin: int | None,
    device: torch.device,
    engine: PolarimetricEngine,
    progress: bool,
) -> PolarimetricFit:
    """The patch loop of :func:`fit_dynamic_frame` on checked float64 maps."""
    started = time.perf_counter()
    fitting = [i for i, v in enumerate(unwrap.views) if not v.held_out]
    if not fitting:
        raise ValueError("argument 'unwrap': every view is held out (no fitting view)")
    scale = unwrap.mean_i_sss(fitting)
    if not scale > 0:
        raise ValueError("argument 'unwrap': no texel is visible in any fitting view")
    counts = unwrap.visible_count()
    mask_seen, view_count = fit_coverage(unwrap, counts, config)
    state = _FrameState(_raw_maps(start, config), _raw_maps(static, config))
    grid = list(unwrap.patches(patch_side(counts, config)))
    patches = frame_patches(grid, view_count > 0, seen_margin)
    atlas = np.asarray(unwrap.root["texel/mask"][...])
    for (rows, cols), patch in tqdm(patches, desc="dynamic fit", unit="patch", disable=not progress):
        # the loss keeps the uncropped patch's normaliser (dynamic_loss module docstring)
        halo_rows, halo_cols, _ = haloed_slices(*patch, config.halo, unwrap.resolution)
        texel_count = max(int(atlas[halo_rows, halo_cols].sum()), 1)
        _fit_patch(unwrap, rows, cols, fitting, engine, config, weights, scale, device, state, texel_count)
    out = fit_maps_from_raw(state.start, config)
    throughput = state.work / state.optimise_s if state.optimise_s > 0 else 0.0
    timings = {"fit_s": time.perf_counter() - started, "optimise_s": state.optimise_s}
    return PolarimetricFit(
        out, mask_seen, [v / max(len(patches), 1) for v in state.curve], timings, throughput, state.samples,
        len(patches), view_count=view_count.astype(np.int32),
    )  # fmt: skip
