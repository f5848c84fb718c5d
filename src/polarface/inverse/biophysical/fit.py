"""Biophysical inverse: chromophore maps and layer diffusion profiles from the six-channel ``rho_sss_bar``.

Paper Sec. 5.3 and supplement "Optimization of Biophysically-based Parameters Details". Physics and
optimisation only (no file I/O; the RESULT-folder stage is :mod:`polarface.pipeline.biophysical.stage`).

Stages (:func:`fit_biophysical`):

1. **Coarse** - the maps are area-averaged ``coarse_factor`` times; per texel the local (blur-free)
   totals model of :func:`~polarface.inverse.biophysical.model.local_channel_albedo` (15 wavelengths
   -> 6 channels through the rig's calibration) is fitted to ``rho_sss_bar`` by a batched, box-bounded
   Levenberg-Marquardt from several starts (the paper uses gradient descent; LM on four unknowns per
   texel converges in tens of iterations instead of thousands). At coarse resolution the blur between
   texels is negligible (supplement: "as the distance of the neighboring pixel becomes larger, we can
   ignore the spatial blurring").
2. **Shapes** - normalised SoG weights of the five layer profiles are fitted at the median texel's
   parameters (:func:`polarface.skin.heterogeneous.fit_layer_shapes`; nine Gaussians, variances
   ``4^j (0.01 mm)^2``).
3. **Fine** - at full resolution, warm-started from the upsampled coarse maps. With
   ``albedo_model="local"`` (the input is a blur-free albedo such as the simulator's ground truth) the
   local model is refined per texel. With ``albedo_model="blurred"`` (the input comes from a
   polarimetric fit of diffusing skin) the heterogeneous layered rendering with separable SoG blurs
   (supplement Eq. simple_sss) is matched to ``rho_sss_bar`` by *residual correction*: the local
   targets are moved by the rendering residual, ``t <- t + (rho_obs - render(p))``, and the
   parameters re-fitted to the targets by LM (a Gauss-Newton step whose Jacobian approximates the
   normalised blur by the identity; it converges where the blur's transfer is in (0, 1], i.e. it is
   a regularised deconvolution whose iteration count bounds the noise gain). Shapes and parameters
   then alternate (coordinate descent, ``shape_rounds``).
4. **Gamut screen** (between the local refinement and the blurred stage) - the distance of each
   texel's input to the skin model's gamut (:func:`gamut_distance` at the best local fit; texels the
   warm start leaves far get a multi-start fit, which also repairs non-converged warm starts). Texels
   beyond ``gamut_tolerance`` are *out of gamut*: a polarimetric fit stuck at ``rho ~ 1`` or channel
   ratios no chromophore mix produces. They are input errors the model cannot and should not
   reproduce, so (a) the coarse maps that warm-start and regularise the fine stage are re-fitted from
   the in-gamut texels only, and (b) the blurred stage matches their projection onto the gamut
   instead of the raw value (an unreachable residual would otherwise grow the correction targets
   without bound and light their neighbours through the blur). They keep their projected chromophores
   and stay in every metric: ``residual_rmse`` is over all valid texels, ``residual_rmse_in_gamut``
   and ``gamut_floor_rmse`` (the input's own distance to the gamut) say how much of it is the input's.

All tensors channels-last: ``rho_sss_bar`` ``(H, W, 6)`` in [0, 1]; parameters ``(H, W, 4)`` in
:data:`~polarface.inverse.biophysical.model.PARAMETER_ORDER` (volume fractions); mask ``(H, W)`` bool.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Literal

import torch

from polarface._validation import as_float_tensor, check_range
from polarface.inverse.biophysical.local_fit import fit_local_parameters, gamut_screen
from polarface.inverse.biophysical.model import blurred_channel_albedo, local_channel_albedo
from polarface.inverse.biophysical.resample import downsample_masked, upsampled_coarse
from polarface.inverse.biophysical.totals_table import TotalsTable
from polarface.inverse.biophysical.warm_start import BiophysicalStart, start_parameters
from polarface.skin import SkinLayerConstants, layer_optics_unchecked
from polarface.skin.heterogeneous import ProfileShapes, fit_layer_shapes
from polarface.skin.sog import default_radial_grid

__all__ = ["BiophysicalConfig", "BiophysicalFit", "fit_biophysical", "median_shapes"]


@dataclasses.dataclass(frozen=True)
class BiophysicalConfig:
    """Settings of the biophysical stage (defaults reproduce the paper's model, Sec. 5.3).

    Attributes:
        albedo_model: ``"blurred"`` - the input ``rho_sss_bar`` is what a local polarimetric fit of
            diffusing skin sees (fine stage renders Eq. simple_sss); ``"local"`` - the input is a
            blur-free local albedo (e.g. simulator ground truth; fine stage uses the local model).
        coarse_factor: downsampling factor of the coarse stage (1 = none).
        coarse_iterations: LM iterations per start at coarse resolution.
        starts: starting points of the coarse fit (a fixed design inside the parameter box).
        fine_iterations: LM iterations of the full-resolution local refinement.
        correction_iterations: residual-correction iterations per shape round (blurred model).
        correction_lm_iterations: LM iterations after each correction.
        shape_rounds: rounds of the coordinate descent shapes <-> parameters (blurred model).
        use_stretch: honour the per-texel UV stretch in the blurs (slower; exact for skewed atlases).
        channel_floor: residuals are divided by ``rho_sss_bar + channel_floor`` (relative weighting).
        prior_weight: per-parameter weights of a pull of the full-resolution fit towards the upsampled
            coarse maps (``PARAMETER_ORDER``; zeros = none, the paper's behaviour). Noisy inputs leave
            ``beta_m`` and ``C_h_in`` weakly determined; the default ``(0, 1, 1, 0)`` trades a little
            sharpness of those two maps for much less noise (measured in docs/biophysical.md).
        gamut_tolerance: largest per-texel distance of the input to the skin model's gamut that is
            treated as measurement noise: the channel-RMS of ``(model - rho) / (rho + channel_floor)``
            at the best local fit (multi-start). Texels beyond it are *out of gamut* - no chromophore
            combination produces them (e.g. a polarimetric fit saturated at ``rho ~ 1`` or with
            channel ratios no skin has); the fine stage then uses their projection onto the gamut
            (the best local fit) instead of the raw value, so their unreachable residual neither
            drives the blurred residual correction nor biases the coarse prior of their neighbours.
            They stay in every reported metric; ``inf`` disables the screen. Default 0.05: an ideal
            polarimetric input (the simulator's diffused albedo) lies within 0.008 of the gamut at
            every texel of the demo preset, 1 % channel noise within ~0.02 (docs/biophysical.md).
        constants: skin layer constants of the forward model.
    """

    albedo_model: Literal["blurred", "local"] = "blurred"
    coarse_factor: int = 8
    coarse_iterations: int = 40
    starts: int = 6
    fine_iterations: int = 10
    correction_iterations: int = 3
    correction_lm_iterations: int = 4
    shape_rounds: int = 1
    use_stretch: bool = False
    channel_floor: float = 0.02
    prior_weight: tuple[float, float, float, float] = (0.0, 1.0, 1.0, 0.0)
    gamut_tolerance: float = 0.05
    constants: SkinLayerConstants = dataclasses.field(default_factory=SkinLayerConstants)

    def __post_init__(self) -> None:
        if self.albedo_model not in ("blurred", "local"):
            raise ValueError(f"albedo_model must be 'blurred' or 'local'; got {self.albedo_model!r}")
        for name in ("coarse_factor", "coarse_iterations", "starts", "shape_rounds"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1; got {getattr(self, name)}")
        for name in ("fine_iterations", "correction_iterations", "correction_lm_iterations"):
            if int(getattr(self, name)) < 0:
                raise ValueError(f"{name} must be >= 0; got {getattr(self, name)}")
        if len(self.prior_weight) != 4 or any(not (w >= 0) for w in self.prior_weight):
            raise ValueError(f"prior_weight must be 4 values >= 0; got {self.prior_weight}")
        if not self.channel_floor > 0:
            raise ValueError(f"channel_floor must be > 0; got {self.channel_floor}")
        if not self.gamut_tolerance > 0:  # also rejects NaN; inf disables the screen
            raise ValueError(f"gamut_tolerance must be > 0; got {self.gamut_tolerance}")


@dataclasses.dataclass(frozen=True, eq=False)
class BiophysicalFit:
    """Result of :func:`fit_biophysical`.

    Attributes:
        parameters: ``(H, W, 4)`` float32 volume fractions (``PARAMETER_ORDER``), 0 outside the mask.
        shapes: :class:`ProfileShapes` with ``(L, 9)`` normalised SoG weights per layer.
        rendered: ``(H, W, 6)`` float32 re-rendered ``rho_sss_bar`` under the configured model.
        spectral: ``(L, H, W)`` float32 rendered subsurface albedo per wavelength (same model).
        residual_rmse: relative RMSE of ``rendered`` against the input over **all** valid texels
            (``||rendered - rho|| / ||rho||`` over texels and channels).
        timings_s: seconds per stage.
        in_gamut: ``(H, W)`` bool, valid texels whose input lies within ``gamut_tolerance`` of the
            skin model's gamut (False outside the mask).
        gamut_distance: ``(H, W)`` float32 distance of the input to the gamut (channel-RMS of
            ``(model - rho) / (rho + channel_floor)`` at the best local fit), 0 outside the mask.
        residual_rmse_in_gamut: as ``residual_rmse`` over the in-gamut texels only.
        gamut_floor_rmse: relative RMSE of the best per-texel local fit (the projection onto the gamut)
            against the input over all valid texels: what no chromophore map can beat under the
            local model; the part of ``residual_rmse`` that belongs to the input.
    """

    parameters: torch.Tensor
    shapes: ProfileShapes
    rendered: torch.Tensor
    spectral: torch.Tensor
    residual_rmse: float
    timings_s: dict[str, float]
    in_gamut: torch.Tensor | None = None
    gamut_distance: torch.Tensor | None = None
    residual_rmse_in_gamut: float = float("nan")
    gamut_floor_rmse: float = float("nan")


def median_shapes(
    parameters: torch.Tensor, mask: torch.Tensor, table: TotalsTable
) -> tuple[ProfileShapes, torch.Tensor]:
    """SoG shapes ``(L, 9)`` of the five layer profiles at the median valid texel's parameters.

    Returns ``(shapes, median (4,))``.
    """
    valid = parameters[mask.bool()].detach().double().cpu()
    median = valid.median(dim=0).values if valid.shape[0] else torch.tensor([0.05, 0.1, 0.03, 0.05]).double()
    grid = table.wavelengths_nm
    optics = layer_optics_unchecked(*(median[i].reshape(1) for i in range(4)), grid, table.constants)
    shapes = fit_layer_shapes(optics, table.constants, r_mm=default_radial_grid(count=801))
    shapes = ProfileShapes(*(w[0] for w in shapes[:5]), relative_error=shapes.relative_error[:, 0])
    return shapes, median


def fit_biophysical(
    rho_sss_bar: torch.Tensor,
    mask: torch.Tensor,
    table: TotalsTable,
    channel_weights: torch.Tensor,
    texel_size_mm: float,
    config: BiophysicalConfig = BiophysicalConfig(),
    *,
    stretch: torch.Tensor | None = None,
    progress: Callable[[str], None] | None = None,
    start: BiophysicalStart | None = None,
) -> BiophysicalFit:
    """Recover chromophore maps and SoG shapes from ``rho_sss_bar`` (module docstring).

    Args:
        rho_sss_bar: ``(H, W, 6)`` six-channel subsurface albedo in [0, 1] (channel order of the
            calibration ``channel_weights`` rows).
        mask: ``(H, W)`` bool valid texels.
        table: :class:`TotalsTable` on the calibration's wavelength grid (nm).
        channel_weights: ``(6, L)`` white-normalised channel weights.
        texel_size_mm: median texel size in mm (> 0).
        config: :class:`BiophysicalConfig`.
        stretch: optional ``(H, W, 2)`` per-texel size / ``texel_size_mm`` (used if ``config.use_stretch``).
        progress: optional callback receiving a stage name after each step.
        start: a previous fit on the same atlas (:class:`BiophysicalStart`: a dynamic frame's static
            result); None fits from scratch. With it the coarse search is skipped and the fit starts
            from, and is regularised towards, the previous maps (:mod:`.warm_start`).

    Raises:
        ValueError: bad shapes, values outside [0, 1], NaN/inf, no valid texel, a ``start`` on
            another atlas.
    """
    rho, mask_b = _checked_inputs(rho_sss_bar, mask, channel_weights, texel_size_mm)
    timings: dict[str, float] = {}
    notify = progress or (lambda _name: None)
    weights = channel_weights.to(torch.float32)

    started = time.perf_counter()
    coarse = None
    if start is None:
        coarse_rho, coarse_mask = downsample_masked(rho, mask_b, config.coarse_factor)
        coarse = torch.zeros(*coarse_mask.shape, 4, device=rho.device)
        coarse[coarse_mask] = _local_fit(coarse_rho[coarse_mask], table, weights, config,
                                         config.coarse_iterations)
        prior = upsampled_coarse(coarse, coarse_mask, mask_b)
    else:
        prior = start_parameters(start, mask_b)
    timings["coarse_s"] = time.perf_counter() - started
    notify("coarse")

    started = time.perf_counter()
    local_target = rho[mask_b].clamp(1e-4, 0.999)
    params_valid = _local_fit(local_target, table, weights, config, config.fine_iterations, prior, prior)
    timings["fine_local_s"] = time.perf_counter() - started
    notify("fine-local")

    started = time.perf_counter()
    screened = _screened_fit(rho, mask_b, local_target, prior, params_valid, coarse, table, weights, config)
    # the blurred corrections start from scratch at the local fit, warm at the previous fit's fixed point
    warm_blurred = start is not None and config.albedo_model == "blurred"
    params = torch.zeros(*mask_b.shape, 4, device=rho.device)
    params[mask_b] = prior if warm_blurred else screened.params_valid
    timings["gamut_s"] = time.perf_counter() - started
    notify("gamut")

    blur_stretch = stretch if config.use_stretch else None
    shapes = None if start is None else start.shapes
    started = time.perf_counter()
    if config.albedo_model == "blurred":
        target = local_channel_albedo(prior, table, weights).clamp(1e-4, 0.999) if warm_blurred else None
        _blurred_stage(params, mask_b, screened, table, weights, texel_size_mm, config, blur_stretch, notify,
                       target=target, fixed_shapes=shapes)
    timings["fine_blurred_s"] = time.perf_counter() - started

    started = time.perf_counter()
    if shapes is None:
        shapes, _ = median_shapes(params, mask_b, table)  # the shapes of the final parameters
    with torch.no_grad():
        rendered, spectral = _render(
            params, mask_b, table, weights, shapes, texel_size_mm, config, blur_stretch
        )
    return _assemble(rho, mask_b, params, shapes, rendered, spectral, screened, timings, started)


def _checked_inputs(
    rho_sss_bar: torch.Tensor, mask: torch.Tensor, channel_weights: torch.Tensor, texel_size_mm: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(rho (H, W, C) float32, mask (H, W) bool)`` of :func:`fit_biophysical` after its checks."""
    rho = as_float_tensor(rho_sss_bar, "rho_sss_bar", dtype=torch.float32)
    if rho.ndim != 3 or rho.shape[-1] != channel_weights.shape[0]:
        raise ValueError(
            f"argument 'rho_sss_bar' must be (H, W, {channel_weights.shape[0]}); got {tuple(rho.shape)}"
        )
    mask_b = torch.as_tensor(mask).bool().to(rho.device)
    if mask_b.shape != rho.shape[:2]:
        raise ValueError(f"argument 'mask' must be {tuple(rho.shape[:2])}; got {tuple(mask_b.shape)}")
    if not bool(mask_b.any()):
        raise ValueError("argument 'mask' has no valid texel")
    check_range(rho[mask_b], "rho_sss_bar", 0.0, 1.0)
    if not (texel_size_mm > 0):
        raise ValueError(f"argument 'texel_size_mm' must be > 0; got {texel_size_mm}")
    return rho, mask_b


@dataclasses.dataclass
class _Screened:
    """The local fit after the gamut screen, over the N valid texels: parameters ``(N, 4)``, the
    observation the blurred stage matches ``(N, C)`` (out-of-gamut texels: their projection), its
    clamped local target, the prior ``(N, 4)``, ``out_of_gamut (N,)`` bool, the gamut ``distance (N,)``
    and the ``projection (N, C)`` of the input onto the gamut."""

    params_valid: torch.Tensor
    observed: torch.Tensor
    local_target: torch.Tensor
    start: torch.Tensor
    out_of_gamut: torch.Tensor
    distance: torch.Tensor
    projection: torch.Tensor


def _screened_fit(
    rho, mask_b, local_target, start, params_valid, coarse, table, weights, config
) -> _Screened:
    """Gamut screen: texels the warm-started fit leaves far from the input get a multi-start fit; those
    still beyond the tolerance are out of gamut and are replaced by their projection (config doc)."""
    params_valid, distance, projection, refitted = gamut_screen(
        local_target, params_valid, table, weights, config
    )
    out_of_gamut = distance > config.gamut_tolerance
    observed = rho[mask_b]
    prior = start
    if bool(out_of_gamut.any()):
        observed = torch.where(out_of_gamut[:, None], projection, observed)
        local_target = observed.clamp(1e-4, 0.999)
        if coarse is not None:  # a warm start's prior (the previous maps) stays
            start = _in_gamut_coarse_prior(rho, mask_b, out_of_gamut, coarse, table, weights, config, start)
    # Refine (with the prior) the texels whose target, prior or parameters changed; the others would
    # solve the same problem again.
    todo = refitted | out_of_gamut | ((start - prior).abs().amax(-1) > 1e-7)
    if bool(todo.any()):
        params_valid = params_valid.clone()
        warm = params_valid[todo]
        params_valid[todo] = _local_fit(
            local_target[todo], table, weights, config, config.fine_iterations, warm, start[todo]
        )
    return _Screened(params_valid, observed, local_target, start, out_of_gamut, distance, projection)


def _in_gamut_coarse_prior(rho, mask_b, out_of_gamut, coarse, table, weights, config, start) -> torch.Tensor:
    """The coarse maps (warm start and prior ``(N, 4)``) re-fitted from the in-gamut texels only: an
    out-of-gamut value is no measurement of the region's skin, not even after projection (which sits on
    the gamut's edge, e.g. the whitest skin for a saturated fit). With no in-gamut texel at all the
    first coarse maps (``start``) are kept."""
    reliable = mask_b.clone()
    reliable[mask_b] = ~out_of_gamut
    coarse_rho, coarse_mask = downsample_masked(rho, reliable, config.coarse_factor)
    if not bool(coarse_mask.any()):
        return start
    refitted = torch.zeros_like(coarse)
    refitted[coarse_mask] = _local_fit(
        coarse_rho[coarse_mask], table, weights, config, config.coarse_iterations, coarse[coarse_mask]
    )
    return upsampled_coarse(refitted, coarse_mask, mask_b)


def _blurred_stage(params, mask_b, screened, table, weights, texel_size_mm, config, stretch, notify, *,
                   target=None, fixed_shapes=None) -> None:
    """Residual correction of the blurred model (module docstring, stage 3), in place on ``params``;
    ``target`` ``(N, C)``: the first local targets (default: the input's), ``fixed_shapes``: SoG shapes
    (default: re-fitted at the median texel every round)."""
    target = screened.local_target.clone() if target is None else target
    for _ in range(config.shape_rounds):
        shapes = fixed_shapes if fixed_shapes is not None else median_shapes(params, mask_b, table)[0]
        for _ in range(config.correction_iterations):
            with torch.no_grad():
                rendered = blurred_channel_albedo(
                    params, table, weights, shapes, texel_size_mm, mask_b, stretch=stretch
                )
            target = (target + screened.observed - rendered[mask_b]).clamp(1e-4, 0.999)
            params[mask_b] = _local_fit(
                target, table, weights, config, config.correction_lm_iterations, params[mask_b],
                screened.start,
            )
        notify("fine-blurred")


def _assemble(rho, mask_b, params, shapes, rendered, spectral, screened, timings, started) -> BiophysicalFit:
    """The :class:`BiophysicalFit` with its gamut maps and residuals (``started``: the render's start)."""
    in_gamut = torch.zeros_like(mask_b)
    in_gamut[mask_b] = ~screened.out_of_gamut
    distance_map = torch.zeros(mask_b.shape, dtype=torch.float32, device=rho.device)
    distance_map[mask_b] = screened.distance.float()
    floor = _relative_rmse(screened.projection, rho[mask_b])
    residual = _relative_rmse(rendered[mask_b], rho[mask_b])
    residual_in = _relative_rmse(rendered[in_gamut], rho[in_gamut]) if bool(in_gamut.any()) else float("nan")
    params = params * mask_b[..., None]
    timings["shapes_render_s"] = time.perf_counter() - started
    return BiophysicalFit(
        params,
        shapes,
        rendered * mask_b[..., None],
        spectral,
        residual,
        timings,
        in_gamut=in_gamut,
        gamut_distance=distance_map,
        residual_rmse_in_gamut=residual_in,
        gamut_floor_rmse=floor,
    )


def _relative_rmse(estimate: torch.Tensor, reference: torch.Tensor) -> float:
    """``||estimate - reference|| / ||reference||`` over all entries (float)."""
    diff = (estimate - reference).double()
    return float(diff.pow(2).mean().sqrt() / reference.double().pow(2).mean().sqrt().clamp_min(1e-12))


def _local_fit(target, table, weights, config, iterations, start=None, prior=None) -> torch.Tensor:
    """The parameters ``(N, 4)`` of :func:`fit_local_parameters` with ``config``'s starts (used without
    a warm ``start``), channel floor and prior weight (used with a ``prior``)."""
    params, _ = fit_local_parameters(
        target,
        table,
        weights,
        start=start,
        starts=config.starts,
        iterations=iterations,
        channel_floor=config.channel_floor,
        prior=prior,
        prior_weight=config.prior_weight,
    )
    return params


def _render(params, mask_b, table, weights, shapes, texel_size_mm, config, stretch):
    if config.albedo_model == "blurred":
        return blurred_channel_albedo(
            params, table, weights, shapes, texel_size_mm, mask_b, stretch=stretch, return_spectral=True
        )
    spectral = table.total_reflectance(params) * mask_b[..., None]
    channels = spectral @ weights.T.to(spectral)
    return channels, spectral.permute(2, 0, 1)
