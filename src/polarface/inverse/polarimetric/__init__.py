"""Static polarimetric inverse rendering in texture space (paper Sec. 5.1-5.2).

:func:`fit_polarimetric` recovers the maps ``eta, alpha_s, alpha_ss, rho_s, rho_ss, rho_sss_bar`` and
the displacement ``H`` (mm) from an unwrapped capture (:mod:`polarface.texture`), patch by patch, with
the per-sample forward model of :mod:`~polarface.inverse.polarimetric.model` and the losses of
:mod:`~polarface.inverse.polarimetric.losses`. The loss of a patch is evaluated by one of the
:data:`POLARIMETRIC_ENGINES` (the fused numba kernel or the torch autograd reference).
The re-render of a view in texture space from parameter maps is :func:`polarface.render.render_view_texture`.

Modules: ``config`` (options, reparameterisation), ``model`` (per-sample forward model), ``losses``,
``init`` (closed-form starts), ``problem`` (a patch's samples and loss), ``fused``/``kernel``/
``_kernel_math``/``_height_backward``/``step`` (the numba engine), ``engines`` (registry), ``optimise``
(L-BFGS, or the first-order optimisers), ``refine`` (Levenberg-Marquardt on the lobe maps), ``fit`` (the
patch loop), ``variants`` (the model variants, :data:`MODEL_VARIANTS`), ``clusters`` (the clusters of
the ``hwang2022`` variant), ``bench`` (throughput benchmark),
``dynamic`` (the per-frame fit of a dynamic sequence,
:func:`fit_dynamic_frame`).

Maps follow ``SIM/ground_truth/maps`` conventions: ``eta, alpha_s, alpha_ss, rho_s, rho_ss,
displacement_mm`` as ``(Ht, Wt)`` float32 and ``rho_sss_bar`` as ``(Ht, Wt, 6)``.
"""

from polarface.inverse.polarimetric.bench import benchmark_problem, run_benchmark
from polarface.inverse.polarimetric.config import (
    PARAMETER_NAMES,
    PolarimetricConfig,
    device_fit_options,
    initial_raw,
    maps_from_raw,
    raw_from_maps,
)
from polarface.inverse.polarimetric.dynamic import DynamicConfig, fit_dynamic_frame
from polarface.inverse.polarimetric.dynamic_loss import (
    DYNAMIC_VARIABLES,
    DynamicPatchProblem,
    DynamicWeights,
    dynamic_regularisers,
)
from polarface.inverse.polarimetric.engines import POLARIMETRIC_ENGINES, PolarimetricEngine, resolve_engine
from polarface.inverse.polarimetric.fit import PolarimetricFit, fit_polarimetric
from polarface.inverse.polarimetric.fused import (
    FusedSamples,
    build_fused_samples,
    fused_data_loss,
    fused_loss_and_grad,
    pack_parameters,
)
from polarface.inverse.polarimetric.init import init_albedos, init_eta, nan_median_filter
from polarface.inverse.polarimetric.losses import (
    LossWeights,
    data_losses,
    laplacian_penalty,
    smoothness_penalty,
)
from polarface.inverse.polarimetric.model import (
    SampleBatch,
    SamplePrediction,
    precompute_samples,
    render_samples,
)
from polarface.inverse.polarimetric.optimise import optimise_patch
from polarface.inverse.polarimetric.problem import (
    PatchProblem,
    build_patch_fused_samples,
    build_patch_samples,
)
from polarface.inverse.polarimetric.refine import (
    LobeRefinement,
    refine_lobes,
    refine_patch_lobes,
    smoothness_hessian,
    weighted_residuals,
)
from polarface.inverse.polarimetric.uncertainty import UNCERTAINTY_PARAMETERS, FitDiagnostics, fit_diagnostics
from polarface.inverse.polarimetric.variants import (
    MODEL_VARIANTS,
    ModelVariant,
    model_fit_options,
    model_name,
)

__all__ = [
    "DYNAMIC_VARIABLES",
    "MODEL_VARIANTS",
    "PARAMETER_NAMES",
    "POLARIMETRIC_ENGINES",
    "UNCERTAINTY_PARAMETERS",
    "DynamicConfig",
    "DynamicPatchProblem",
    "DynamicWeights",
    "FitDiagnostics",
    "FusedSamples",
    "LobeRefinement",
    "LossWeights",
    "ModelVariant",
    "PatchProblem",
    "PolarimetricConfig",
    "PolarimetricEngine",
    "PolarimetricFit",
    "SampleBatch",
    "SamplePrediction",
    "benchmark_problem",
    "build_fused_samples",
    "build_patch_fused_samples",
    "build_patch_samples",
    "data_losses",
    "device_fit_options",
    "dynamic_regularisers",
    "fit_diagnostics",
    "fit_dynamic_frame",
    "fit_polarimetric",
    "fused_data_loss",
    "fused_loss_and_grad",
    "init_albedos",
    "init_eta",
    "initial_raw",
    "laplacian_penalty",
    "maps_from_raw",
    "model_fit_options",
    "model_name",
    "nan_median_filter",
    "optimise_patch",
    "pack_parameters",
    "precompute_samples",
    "raw_from_maps",
    "refine_lobes",
    "refine_patch_lobes",
    "render_samples",
    "resolve_engine",
    "run_benchmark",
    "smoothness_hessian",
    "smoothness_penalty",
    "weighted_residuals",
]
