"""Throughput benchmark of the polarimetric stage: fused kernel, vectorised torch, eager per-texel baseline.

:func:`benchmark_problem` builds one demo-sized patch problem per engine of
:data:`~polarface.inverse.polarimetric.engines.POLARIMETRIC_ENGINES` without any file: a spherical-cap
texture patch (``side x side`` texels, head-sized, 1 m in front of :func:`polarface.capture.rig.paper_rig`)
seen by both polarimetric cameras over ``frames`` chair yaws (the demo preset: 24 frames = 48 views),
with observations rendered by the model itself. :func:`run_benchmark` times

* each engine that runs on the device (the fused kernel, :mod:`polarface.inverse.polarimetric.kernel`,
  numba, analytic gradients, and the vectorised torch autograd reference): one optimiser iteration
  (forward, backward, RMSprop step) of :func:`polarface.inverse.polarimetric.optimise.optimise_patch`
  on the whole patch each;
* the baseline: the same losses written the straightforward way (the style of the authors' release):
  a Python loop over texels, each evaluating :func:`polarface.optics.render_polarimetric` for its views
  one light at a time, its own backward and optimiser step;

and reports texel-view iterations per second for each, the speed-up of the fastest over the baseline
and the peak RSS.
"""

from __future__ import annotations

import dataclasses
import math
import resource
import time

import numba
import numpy as np
import torch

from polarface.inverse.polarimetric.config import PolarimetricConfig, initial_raw
from polarface.inverse.polarimetric.engines import POLARIMETRIC_ENGINES
from polarface.inverse.polarimetric.fused import build_fused_samples
from polarface.inverse.polarimetric.losses import data_losses
from polarface.inverse.polarimetric.model import (
    SampleBatch,
    SamplePrediction,
    precompute_samples,
    render_samples,
)
from polarface.inverse.polarimetric.optimise import optimise_patch
from polarface.inverse.polarimetric.problem import PatchProblem
from polarface.texture import TexelGeometry, ViewSpec, build_views, texel_geometry

__all__ = ["BenchmarkProblem", "benchmark_problem", "run_benchmark"]


@dataclasses.dataclass
class BenchmarkProblem:
    """The benchmark patch (module docstring).

    Attributes:
        problems: engine name (:data:`POLARIMETRIC_ENGINES`) -> its :class:`PatchProblem` (same samples,
            observations rendered by the model itself).
        raw: the initial raw variables (name -> ``(side, side, c)`` tensors).
        views: the ``2 frames`` views.
    """

    problems: dict[str, PatchProblem]
    raw: dict[str, torch.Tensor]
    views: list[ViewSpec]


def _cap_samples(side: int, frames: int):
    """Geometry of the cap's ``side x side`` texture, its views and the front-facing samples
    ``(view, texel, position)`` with their lit masks (all lights lit)."""
    from polarface.capture.rig import paper_rig
    from polarface.geometry.uv_raster import rasterize_uv
    from polarface.simulate.sphere_capture import sphere_cap_mesh, sphere_placement

    mesh = sphere_cap_mesh(80.0, 60.0, segments=64)
    raster = rasterize_uv(mesh, side)
    geometry: TexelGeometry = texel_geometry(raster)
    rig = paper_rig(width=612, height=512)
    yaws = np.radians(np.linspace(-30.0, 30.0, frames))
    poses = np.stack([sphere_placement(float(y)) for y in yaws])
    views = build_views(rig, list(range(frames)), poses)
    rows, cols = np.nonzero(geometry.mask)
    texel = rows * side + cols
    pos = geometry.position[rows, cols].astype(np.float64)
    normal = geometry.normal[rows, cols].astype(np.float64)
    samples = []
    for index, view in enumerate(views):
        facing = ((np.asarray(view.camera_center) - pos) * normal).sum(-1) > 0
        samples.append((np.full(int(facing.sum()), index), texel[facing], pos[facing]))
    v_idx = np.concatenate([s[0] for s in samples])
    t_idx = np.concatenate([s[1] for s in samples])
    p = np.concatenate([s[2] for s in samples])
    lit = np.ones((len(v_idx), len(rig.lights)), bool)
    return geometry, views, v_idx, t_idx, p, lit


def _model_observations(batch: SampleBatch, normals: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``(S, 3, 3)`` observations of the model itself for uniform skin-like parameters."""
    with torch.no_grad():
        n = batch.count
        pred = render_samples(
            batch,
            normals[batch.texel],
            torch.full((n,), 1.42, dtype=dtype),
            torch.full((n,), 0.4, dtype=dtype),
            torch.full((n,), 0.9, dtype=dtype),
            torch.full((n,), 0.5, dtype=dtype),
            torch.full((n,), 0.25, dtype=dtype),
            torch.full((n, 3), 0.4, dtype=dtype),
        )
        return torch.stack([pred.i_sss, pred.i_zeta, pred.i_s], dim=1)


def benchmark_problem(
    side: int = 48, frames: int = 24, dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu"
) -> BenchmarkProblem:
    """A patch of ``side^2`` texels seen in ``2 frames`` views (module docstring), one
    :class:`PatchProblem` per engine of :data:`POLARIMETRIC_ENGINES`."""
    geometry, views, v_idx, t_idx, p, lit = _cap_samples(side, frames)
    pick = lambda attr: np.array([getattr(v, attr) for v in views])[v_idx]  # noqa: E731
    batch = precompute_samples(
        p,
        t_idx,
        v_idx,
        pick("camera_center"),
        pick("camera_up"),
        pick("reference_up"),
        pick("light_positions"),
        pick("light_intensity"),
        pick("channels"),
        lit,
        np.zeros((len(v_idx), 3, 3)),
        dtype=dtype,
        device=device,
    )
    config = PolarimetricConfig()
    unscaled = PatchProblem(batch, geometry, config, 1.0, dtype, torch.device(device))
    raw = {
        k: torch.as_tensor(v, dtype=dtype, device=device)
        for k, v in initial_raw((side, side), config).items()
    }
    with torch.no_grad():
        normals = unscaled.normals(torch.zeros((side, side), dtype=dtype, device=device))
    observed = _model_observations(batch, normals, dtype)
    scale = float(observed[:, 0].mean())
    batch = type(batch)(
        *(observed if f == "observed" else getattr(batch, f) for f in batch.__dataclass_fields__)
    )
    table = lambda attr: np.array([getattr(v, attr) for v in views])  # noqa: E731
    fused = build_fused_samples(
        geometry.position.reshape(-1, 3),
        t_idx,
        v_idx,
        lit,
        observed.cpu().numpy(),
        table("camera_center"),
        table("camera_up"),
        table("reference_up"),
        table("light_positions"),
        table("light_intensity"),
        table("channels"),
        dtype=np.float64 if dtype == torch.float64 else np.float32,
    )
    dev = torch.device(device)
    problems = {
        name: PatchProblem(
            batch, geometry, config, scale, dtype, dev, fused if engine.fused_samples else None
        )
        for name, engine in POLARIMETRIC_ENGINES.items()
    }
    return BenchmarkProblem(problems, raw, views)


def _eager_texel_step(samples: list[dict], params: dict[str, torch.Tensor], optimizer, scale: float) -> None:
    """One iteration of the baseline for one texel: per view, per light calls of render_polarimetric."""
    from polarface.optics.image_formation import render_polarimetric

    optimizer.zero_grad()
    eta = 1.05 + 1.45 * torch.sigmoid(params["eta"])
    alpha_s = 0.02 + 1.48 * torch.sigmoid(params["alpha_s"])
    alpha_ss = alpha_s + (1.5 - alpha_s) * torch.sigmoid(params["alpha_ss"])
    rho_s, rho_ss = 2 * torch.sigmoid(params["rho_s"]), 2 * torch.sigmoid(params["rho_ss"])
    rho = torch.sigmoid(params["rho_sss_bar"])
    normal = params["normal"] / params["normal"].norm()
    total = 0.0
    for sample in samples:
        stokes = None
        for k in range(sample["lights"].shape[0]):
            images = render_polarimetric(
                normal,
                sample["position"],
                sample["centre"],
                sample["up"],
                sample["lights"][k : k + 1],
                sample["intensity"][k : k + 1],
                eta,
                alpha_s,
                alpha_ss,
                rho_s,
                rho_ss,
                rho[sample["channels"]],
            )
            stokes = images.stokes if stokes is None else stokes + images.stokes
        s0, s1, s2 = stokes[..., 0], stokes[..., 1], stokes[..., 2]
        prediction = SamplePrediction(
            i_sss=(s0 - s1)[None], i_zeta=(-s2)[None], i_s=s1[None], specular_s1=torch.zeros_like(s1)[None]
        )
        losses = data_losses(prediction, sample["observed"][None], scale)
        total = total + losses["sss"] + losses["s"] + losses["phi"] + 0.002 * losses["psi"]
    total.backward()
    optimizer.step()


def _engine_rate(
    problem: PatchProblem, raw: dict[str, torch.Tensor], iterations: int, device: torch.device
) -> tuple[float, float]:
    """``(texel-view iterations per second, seconds)`` of ``iterations`` optimiser steps on ``problem``."""
    optimise_patch(problem, raw, PolarimetricConfig(iterations=1))  # warm-up (and JIT compile)
    tick = time.perf_counter()
    optimise_patch(problem, raw, PolarimetricConfig(iterations=int(iterations), warmup=1))
    if device.type == "cuda":
        torch.cuda.synchronize()
    seconds = time.perf_counter() - tick
    return problem.batch.count * iterations / seconds, seconds


def _engine_rates(bench: BenchmarkProblem, iterations: int, device: torch.device) -> dict[str, tuple]:
    """Engine name -> ``(rate, seconds)`` (NaN for engines that do not run on ``device``)."""
    rates = {}
    for name, engine in POLARIMETRIC_ENGINES.items():
        if not engine.supports(device):
            rates[name] = (math.nan, math.nan)
            continue
        previous = torch.get_num_threads()
        if engine.fused_samples:
            # as in the fit: the kernel's threads are numba's; torch's per-texel glue runs on one thread
            torch.set_num_threads(1)
        try:
            rates[name] = _engine_rate(bench.problems[name], bench.raw, iterations, device)
        finally:
            torch.set_num_threads(previous)
    return rates


def _eager_texel_inputs(problem: PatchProblem, views: list[ViewSpec], texel: int) -> tuple[list[dict], dict]:
    """The baseline's per-view inputs and its leaf parameters for one texel of ``problem``."""
    batch = problem.batch
    chosen = torch.nonzero(batch.texel == texel)[:, 0]
    samples = []
    for s in chosen.tolist():
        view = views[int(batch.view[s])]
        samples.append(
            {
                "centre": torch.tensor(view.camera_center, dtype=torch.float32),
                "up": torch.tensor(view.camera_up, dtype=torch.float32),
                "lights": torch.tensor(view.light_positions, dtype=torch.float32),
                "intensity": torch.tensor(view.light_intensity, dtype=torch.float32),
                "channels": torch.tensor(view.channels),
                "observed": batch.observed[s],
            }
        )
    row, col = divmod(int(texel), problem.shape[1])
    position = torch.as_tensor(problem.positions[row, col], dtype=torch.float32)
    for sample in samples:
        sample["position"] = position
    params = {
        "eta": torch.tensor(0.0, requires_grad=True),
        "alpha_s": torch.tensor(0.0, requires_grad=True),
        "alpha_ss": torch.tensor(0.0, requires_grad=True),
        "rho_s": torch.tensor(0.0, requires_grad=True),
        "rho_ss": torch.tensor(0.0, requires_grad=True),
        "rho_sss_bar": torch.zeros(6, requires_grad=True),
        "normal": problem.frame[2][row, col].clone().requires_grad_(True),
    }
    return samples, params


def _eager_rate(problem: PatchProblem, views: list[ViewSpec], baseline_texels: int) -> tuple[float, float]:
    """``(texel-view iterations per second, seconds)`` of the eager baseline on the first
    ``baseline_texels`` texels of ``problem`` (the rate does not depend on how many)."""
    texels = problem.batch.texel.unique()[: int(baseline_texels)]
    work, eager_s = 0, 0.0
    for texel in texels:
        samples, params = _eager_texel_inputs(problem, views, int(texel))
        optimizer = torch.optim.RMSprop(list(params.values()), lr=1e-3)
        tick = time.perf_counter()
        for _ in range(2):
            _eager_texel_step(samples, params, optimizer, problem.scale)
        eager_s += time.perf_counter() - tick
        work += 2 * len(samples)
    return (work / eager_s if eager_s > 0 else math.nan), eager_s


def run_benchmark(
    side: int = 48,
    frames: int = 24,
    iterations: int = 5,
    baseline_texels: int = 4,
    device: str | torch.device = "cpu",
) -> dict:
    """Time every engine and the eager baseline (module docstring); returns a JSON-able dict."""
    started = time.perf_counter()
    bench = benchmark_problem(side, frames, device=device)
    setup_s = time.perf_counter() - started
    problem = bench.problems["torch"]
    rates = _engine_rates(bench, iterations, torch.device(device))
    (fused_rate, fused_s), (torch_rate, torch_s) = rates["fused"], rates["torch"]
    best_rate = fused_rate if fused_rate == fused_rate else torch_rate
    eager_rate, eager_s = _eager_rate(problem, bench.views, baseline_texels)
    return {
        "device": str(device),
        "threads": torch.get_num_threads(),
        "texels": int(problem.texel_count),
        "views": len(bench.views),
        "samples": problem.batch.count,
        "iterations": int(iterations),
        "numba_threads": numba.get_num_threads(),
        "fused_kernel_texel_view_iterations_per_s": fused_rate,
        "torch_vectorised_texel_view_iterations_per_s": torch_rate,
        "eager_baseline_texel_view_iterations_per_s": eager_rate,
        "speedup": best_rate / eager_rate if eager_rate > 0 else math.nan,
        "paper_a100_rate": 150 * 2048 * 2048 * 200 / (180 * 60),
        "setup_s": setup_s,
        "fused_s": fused_s,
        "torch_s": torch_s,
        "eager_s": eager_s,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }
