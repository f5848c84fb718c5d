"""Configuration and reparameterisation of the static polarimetric stage.

``PolarimetricConfig`` holds the optimiser options and the loss weights (paper defaults);
:func:`maps_from_raw` / :func:`raw_from_maps` map between the unconstrained optimisation variables and
the physical maps (ranges in :mod:`polarface.inverse.polarimetric.fit`'s docstring).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from polarface.inverse.polarimetric.losses import LossWeights
from polarface.optics.pbssrdf import SURFACE_PARAMETER_NAMES

__all__ = [
    "CLUSTERABLE",
    "NO_LOBE_RAW",
    "PARAMETER_NAMES",
    "PolarimetricConfig",
    "device_fit_options",
    "fit_maps_from_raw",
    "initial_raw",
    "maps_from_raw",
    "raw_from_maps",
]

#: Patch side and sample budget on a CUDA device (:func:`device_fit_options`); the budget shrinks on
#: a GPU with less memory, at :data:`CUDA_BYTES_PER_SAMPLE` and a :data:`CUDA_MEMORY_FRACTION` of it.
CUDA_PATCH, CUDA_SAMPLE_BUDGET = 256, 2_000_000
#: GPU memory the torch engine's loss and gradient take per sample (``benchmarks/bench_cuda.py`` on an
#: H200: 3 619-4 474 bytes from 2.4e6 down to 8.3e4 samples; docs/performance.md, "The CUDA path").
CUDA_BYTES_PER_SAMPLE = 4000
CUDA_MEMORY_FRACTION = 0.4

#: Output maps (``rho_sss_bar`` has 6 channels, the others one).
PARAMETER_NAMES = (*SURFACE_PARAMETER_NAMES, "rho_sss_bar", "displacement_mm")
#: The maps ``PolarimetricConfig.clustered`` and ``held`` may name (the surface reflection's).
CLUSTERABLE = tuple(SURFACE_PARAMETER_NAMES)


@dataclasses.dataclass(frozen=True)
class PolarimetricConfig:
    """Options of the static polarimetric stage (defaults: paper weights; optimiser settings validated
    on the simulator, see docs/reconstruct.md).

    Attributes:
        weights: :class:`LossWeights`.
        optimizer: ``lbfgs`` (default: converges the lobe maps and with them eta,
            :mod:`polarface.inverse.polarimetric.optimise`), ``rmsprop`` (the paper's, 150 iterations; what
            :func:`polarface.pipeline.reconstruct.stages` uses with stereo geometry, docs/reconstruct.md) or
            ``adam``; iterations: optimiser iterations per patch;
            lr: learning rate on the raw variables, lr_final_fraction: cosine decay to this fraction of
            lr, warmup: linear learning-rate warm-up steps (rmsprop and adam only).
        patch: largest patch side (texels); halo: halo width (texels, >= 2 for the 5x5 window);
        sample_budget: most samples (texel x view) held per patch.
        unwrap_cache_mb: decoded unwrap-store chunks kept per process while the patches are fitted (MiB;
            0: none), so a haloed patch does not decode again what its neighbours decoded. A memory
            knob only: cached reads equal uncached ones, the maps do not depend on it. The cache fills
            up to this size whatever the number of views (docs/performance.md, "Memory against the
            number of views").
        eta_range, alpha_range: reparameterisation ranges; rho_max: largest lobe albedo;
        h_scale_mm: H per unit of its raw variable.
        init_eta, init_alpha_s, init_alpha_ss, init_rho_ss: initial values.
        init_eta_search: start eta per texel from a grid search of the DoP relation
            (:func:`polarface.inverse.polarimetric.init.init_eta`).
        min_views: fewest fitting views that must see a texel for it to count as reconstructed (the
            result mask): texels seen in 1-3 views (grazing, mostly at the atlas border) cannot
            separate the 13 unknowns (their errors per view count: docs/reconstruct.md, "Reliability").
        boundary_margin: texels within this many texels (4-neighbour steps) of the edge of the region
            seen by ``min_views`` views are fitted but left out of the result mask. That edge runs where the
            surface turns away from or behind something for most views (eye sockets, nostrils, lips,
            ears, the sides of the head): its texels are seen at grazing angles next to occlusion edges,
            and their 5x5 smoothness, H Laplacian and normals from H reach texels no data constrains
            (measured effect: docs/reconstruct.md, "Reliability"); 0 keeps them.
        seed: torch seed (deterministic runs).
        refine_lobes_iterations: Levenberg-Marquardt iterations on the four lobe maps after each
            patch's optimisation (:func:`polarface.inverse.polarimetric.refine.refine_patch_lobes`; 0,
            the default, disables it). After the default L-BFGS it moves along the lobes' degenerate
            direction (two lobes of similar width sharing the energy) and worsens eta; kept for
            experiments (docs/reconstruct.md, "Two lobes or one").
        refine_lobes_damping: its initial Marquardt damping (relative to the Gauss-Newton diagonal).
        lobes: ``two`` (the paper's specular + single-scattering lobes) or ``one`` (rho_ss fixed at 0,
            alpha_ss unused: for materials without the second lobe, or when the split does not matter;
            with the rig's noise and a few dozen views the data do not determine the split, so this
            is a modelling choice: docs/reconstruct.md, "Two lobes or one").
        homogeneous: maps held to one value over the face (``eta``, ``alpha_s``): the fit runs twice,
            first with them free per texel, then with each fixed at its median over the first fit's
            mask (:func:`polarface.inverse.polarimetric.fit_polarimetric`; the model variants of
            :mod:`polarface.inverse.polarimetric.variants`, docs/validation.md).
        fixed_eta, fixed_alpha_s: hold eta or alpha_s at this value at every texel (not optimised; the
            second pass of ``homogeneous``, or a value the user knows); None: fitted per texel.
        clustered: surface maps (of :data:`CLUSTERABLE`) shared by the texels of each of ``clusters``
            clusters of the diffuse albedo, fitted by alternating passes (the ``hwang2022`` variant:
            :func:`polarface.inverse.polarimetric.fit_polarimetric`, docs/validation.md).
        clusters: number of clusters of ``clustered``.
        cluster_rounds: alternations of the index pass and the specular pass of ``clustered``.
        held: maps the optimiser and the closed-form starts leave at their starting values, per texel
            (the passes of ``clustered`` start them at their cluster values).
    """

    weights: LossWeights = dataclasses.field(default_factory=LossWeights)
    optimizer: str = "lbfgs"
    lr: float = 0.03
    iterations: int = 400
    lr_final_fraction: float = 0.1
    warmup: int = 20
    patch: int = 64
    halo: int = 4
    sample_budget: int = 300_000
    unwrap_cache_mb: int = 256
    eta_range: tuple[float, float] = (1.05, 2.5)
    alpha_range: tuple[float, float] = (0.02, 1.5)
    rho_max: float = 2.0
    h_scale_mm: float = 0.05
    init_eta: float = 1.5
    init_alpha_s: float = 0.4
    init_alpha_ss: float = 0.8
    init_rho_ss: float = 0.2
    init_eta_search: bool = True
    min_views: int = 4
    boundary_margin: int = 1
    seed: int = 0
    refine_lobes_iterations: int = 0
    refine_lobes_damping: float = 1e-3
    lobes: str = "two"
    homogeneous: tuple[str, ...] = ()
    fixed_eta: float | None = None
    fixed_alpha_s: float | None = None
    clustered: tuple[str, ...] = ()
    clusters: int = 8
    cluster_rounds: int = 1
    held: tuple[str, ...] = ()

    @property
    def frozen_variables(self) -> tuple[str, ...]:
        """Raw variables the optimiser leaves at their initial values (``lobes == "one"``: the second
        lobe's, with rho_ss ~ 1e-13; ``fixed_eta`` / ``fixed_alpha_s``: that map; ``held``)."""
        lobe = ("alpha_ss", "rho_ss") if self.lobes == "one" else ()
        fixed = tuple(name for name, value in self.fixed_values.items() if value is not None)
        return tuple(dict.fromkeys((*lobe, *fixed, *self.held)))

    @property
    def fixed_values(self) -> dict[str, float | None]:
        """``{"eta": fixed_eta, "alpha_s": fixed_alpha_s}``."""
        return {"eta": self.fixed_eta, "alpha_s": self.fixed_alpha_s}

    def __post_init__(self) -> None:
        if self.optimizer not in ("lbfgs", "rmsprop", "adam"):
            raise ValueError(
                f"argument 'optimizer' must be 'lbfgs', 'rmsprop' or 'adam'; got {self.optimizer!r}"
            )
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ValueError(f"argument 'lr' must be > 0; got {self.lr}")
        if int(self.iterations) < 1:
            raise ValueError(f"argument 'iterations' must be >= 1; got {self.iterations}")
        if not 0 < self.lr_final_fraction <= 1:
            raise ValueError(f"argument 'lr_final_fraction' must be in (0, 1]; got {self.lr_final_fraction}")
        if int(self.patch) < 4 or int(self.halo) < 2:
            raise ValueError(
                f"arguments 'patch' >= 4 and 'halo' >= 2 required; got {self.patch}, {self.halo}"
            )
        if int(self.sample_budget) < 1000:
            raise ValueError(f"argument 'sample_budget' must be >= 1000; got {self.sample_budget}")
        if int(self.unwrap_cache_mb) < 0:
            raise ValueError(f"argument 'unwrap_cache_mb' must be >= 0; got {self.unwrap_cache_mb}")
        lo, hi = self.eta_range
        if not 1.0 < lo < self.init_eta < hi:
            raise ValueError(
                f"arguments 'eta_range' {self.eta_range} / 'init_eta' {self.init_eta}: "
                "need 1 < lo < init < hi"
            )
        lo, hi = self.alpha_range
        if not 0.0 < lo < self.init_alpha_s < self.init_alpha_ss < hi:
            raise ValueError(
                "arguments 'alpha_range'/'init_alpha_s'/'init_alpha_ss': "
                "need 0 < lo < alpha_s < alpha_ss < hi"
            )
        if not 0 < self.init_rho_ss < self.rho_max:
            raise ValueError(f"argument 'init_rho_ss' must lie in (0, rho_max); got {self.init_rho_ss}")
        if int(self.min_views) < 1:
            raise ValueError(f"argument 'min_views' must be >= 1; got {self.min_views}")
        if int(self.boundary_margin) < 0:
            raise ValueError(f"argument 'boundary_margin' must be >= 0; got {self.boundary_margin}")
        if int(self.refine_lobes_iterations) < 0:
            raise ValueError(
                f"argument 'refine_lobes_iterations' must be >= 0; got {self.refine_lobes_iterations}"
            )
        if not (self.refine_lobes_damping > 0 and math.isfinite(self.refine_lobes_damping)):
            raise ValueError(f"argument 'refine_lobes_damping' must be > 0; got {self.refine_lobes_damping}")
        if self.lobes not in ("two", "one"):
            raise ValueError(f"argument 'lobes' must be 'two' or 'one'; got {self.lobes!r}")
        if self.lobes == "one" and int(self.refine_lobes_iterations) > 0:
            raise ValueError("argument 'refine_lobes_iterations' must be 0 with lobes='one'")
        if not self.h_scale_mm > 0:
            raise ValueError(f"argument 'h_scale_mm' must be > 0; got {self.h_scale_mm}")
        self._check_homogeneous()
        self._check_clustered()

    def _check_clustered(self) -> None:
        for name in ("clustered", "held"):
            maps = tuple(getattr(self, name))
            object.__setattr__(self, name, maps)  # a JSON list back as the tuple it was
            if not set(maps) <= set(CLUSTERABLE) or len(set(maps)) != len(maps):
                raise ValueError(f"argument '{name}' must list distinct maps of {CLUSTERABLE}; got {maps!r}")
        if int(self.clusters) < 1 or int(self.cluster_rounds) < 0:
            raise ValueError(f"arguments 'clusters' >= 1 and 'cluster_rounds' >= 0 required; got "
                             f"{self.clusters}, {self.cluster_rounds}")
        if self.clustered and self.homogeneous:
            raise ValueError("arguments 'clustered' and 'homogeneous': a fit shares maps over clusters or "
                             "over the face, not both")
        if ({"alpha_s", "alpha_ss", "rho_ss"} & {*self.clustered, *self.held}
                and int(self.refine_lobes_iterations) > 0):
            raise ValueError("argument 'refine_lobes_iterations' must be 0 with clustered or held lobes")

    def _check_homogeneous(self) -> None:
        homogeneous = tuple(self.homogeneous)
        object.__setattr__(self, "homogeneous", homogeneous)  # a JSON list back as the tuple it was
        if not set(homogeneous) <= {"eta", "alpha_s"} or len(set(homogeneous)) != len(homogeneous):
            raise ValueError(f"argument 'homogeneous' must list distinct maps of ('eta', 'alpha_s'); "
                             f"got {self.homogeneous!r}")
        for name, value, (lo, hi) in (("eta", self.fixed_eta, self.eta_range),
                                      ("alpha_s", self.fixed_alpha_s, self.alpha_range)):
            if value is None:
                continue
            if not lo < value < hi:  # NaN fails too
                raise ValueError(f"argument 'fixed_{name}' must lie in ({lo}, {hi}); got {value}")
            if name in homogeneous:
                raise ValueError(f"arguments 'homogeneous' and 'fixed_{name}': {name} is either fitted "
                                 "homogeneous or fixed, not both")
        if self.fixed_alpha_s is not None and int(self.refine_lobes_iterations) > 0:
            raise ValueError("argument 'refine_lobes_iterations' must be 0 with a fixed alpha_s")


#: Raw rho_ss of an absent second lobe (rho_ss = rho_max sigmoid(-30) ~ 2e-13).
NO_LOBE_RAW = -30.0


def _logit(p: np.ndarray | float) -> np.ndarray:
    p = np.clip(np.asarray(p, dtype=np.float64), 1e-6, 1 - 1e-6)
    return np.log(p / (1 - p))


def maps_from_raw(raw: dict[str, torch.Tensor], config: PolarimetricConfig) -> dict[str, torch.Tensor]:
    """Physical maps from raw variables (``(..., 1)`` or ``(..., 6)`` each; differentiable)."""
    e_lo, e_hi = config.eta_range
    a_lo, a_hi = config.alpha_range
    alpha_s = a_lo + (a_hi - a_lo) * torch.sigmoid(raw["alpha_s"])
    return {
        "eta": e_lo + (e_hi - e_lo) * torch.sigmoid(raw["eta"]),
        "alpha_s": alpha_s,
        "alpha_ss": alpha_s + (a_hi - alpha_s) * torch.sigmoid(raw["alpha_ss"]),
        "rho_s": config.rho_max * torch.sigmoid(raw["rho_s"]),
        "rho_ss": config.rho_max * torch.sigmoid(raw["rho_ss"]),
        "rho_sss_bar": torch.sigmoid(raw["rho_sss_bar"]),
        "displacement_mm": config.h_scale_mm * raw["displacement_mm"],
    }


def raw_from_maps(maps: dict[str, np.ndarray], config: PolarimetricConfig) -> dict[str, np.ndarray]:
    """Inverse of :func:`maps_from_raw` (numpy, values clipped into the open ranges)."""
    e_lo, e_hi = config.eta_range
    a_lo, a_hi = config.alpha_range
    alpha_s = np.clip(maps["alpha_s"], a_lo + 1e-6, a_hi - 1e-6)
    return {
        "eta": _logit((maps["eta"] - e_lo) / (e_hi - e_lo)),
        "alpha_s": _logit((alpha_s - a_lo) / (a_hi - a_lo)),
        "alpha_ss": _logit((maps["alpha_ss"] - alpha_s) / (a_hi - alpha_s)),
        "rho_s": _logit(maps["rho_s"] / config.rho_max),
        "rho_ss": _logit(maps["rho_ss"] / config.rho_max),
        "rho_sss_bar": _logit(maps["rho_sss_bar"]),
        "displacement_mm": np.asarray(maps["displacement_mm"], dtype=np.float64) / config.h_scale_mm,
    }


def fit_maps_from_raw(raw: dict[str, np.ndarray], config: PolarimetricConfig) -> dict[str, np.ndarray]:
    """The physical maps of a fit (:func:`maps_from_raw` of numpy raw variables, in float64): name ->
    ``(Ht, Wt)`` float32, ``rho_sss_bar`` ``(Ht, Wt, 6)`` (the layout of ``PolarimetricFit.maps``)."""
    with torch.no_grad():
        maps = maps_from_raw(
            {k: torch.from_numpy(np.asarray(v, dtype=np.float64)) for k, v in raw.items()}, config
        )
    out = {}
    for k, v in maps.items():
        array = v.numpy().astype(np.float32)
        out[k] = array if k == "rho_sss_bar" else array[..., 0]
    return out


def initial_raw(resolution: tuple[int, int], config: PolarimetricConfig) -> dict[str, np.ndarray]:
    """Raw variables of the initial maps (``(Ht, Wt, C)`` float32; albedos refined per patch)."""
    height, width = resolution
    ones = np.ones((height, width, 1))
    eta = config.init_eta if config.fixed_eta is None else config.fixed_eta
    alpha_s = config.init_alpha_s if config.fixed_alpha_s is None else config.fixed_alpha_s
    maps = {
        "eta": eta * ones,
        "alpha_s": alpha_s * ones,
        "alpha_ss": config.init_alpha_ss * ones,
        "rho_s": 0.3 * ones,
        "rho_ss": config.init_rho_ss * ones,
        "rho_sss_bar": 0.4 * np.ones((height, width, 6)),
        "displacement_mm": 0.0 * ones,
    }
    raw = {k: v.astype(np.float32) for k, v in raw_from_maps(maps, config).items()}
    if config.lobes == "one":
        raw["rho_ss"][:] = NO_LOBE_RAW
    return raw


def device_fit_options(
    device: torch.device | str, memory_bytes: int | None = None, units_per_gpu: int = 1
) -> dict[str, int]:
    """:class:`PolarimetricConfig` options for fitting on ``device`` where the user set none: larger
    patches on a CUDA device (``patch`` :data:`CUDA_PATCH`, ``sample_budget`` :data:`CUDA_SAMPLE_BUDGET`
    or what :data:`CUDA_MEMORY_FRACTION` of its memory holds, shared by ``units_per_gpu`` patches fitted
    on it at once), none on the CPU.

    The defaults (64-texel patches, 3e5 samples) suit the CPU's fused kernel, whose rate does not grow
    with the patch. The torch engine on a GPU is bound by kernel launches at that size: on an H200 it
    evaluates 4.5e6 texel-view iterations/s on a 48 x 48 patch, 2.7e7 on 128 x 128 and 3.6e7 from
    about 1.3e6 samples on (``benchmarks/bench_cuda.py``); the tiny preset's static
    polarimetric stage takes 158 s in 16 patches and 16 s in one (docs/performance.md, "The CUDA path").

    Args:
        device: a torch device or its name (``"cuda"``, ``"cuda:1"``, ``"cpu"``).
        memory_bytes: the GPU's memory (None: asked of torch for a CUDA device).
        units_per_gpu: patches fitted on one GPU at the same time (worker processes sharing it).

    Raises:
        ValueError: ``memory_bytes`` or ``units_per_gpu`` < 1.
    """
    device = torch.device(device)
    if device.type != "cuda":
        return {}
    if memory_bytes is None:
        memory_bytes = torch.cuda.get_device_properties(device).total_memory
    if int(memory_bytes) < 1:
        raise ValueError(f"argument 'memory_bytes' must be >= 1; got {memory_bytes}")
    if int(units_per_gpu) < 1:
        raise ValueError(f"argument 'units_per_gpu' must be >= 1; got {units_per_gpu}")
    fits = int(CUDA_MEMORY_FRACTION * int(memory_bytes) / int(units_per_gpu) / CUDA_BYTES_PER_SAMPLE)
    return {"patch": CUDA_PATCH, "sample_budget": max(min(CUDA_SAMPLE_BUDGET, fits), 1000)}
