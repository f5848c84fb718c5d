"""Throughput benchmark of the polarimetric stage: fused kernel, vectorised torch, eager per-texel baseline.

:func:`benchmark_problem` builds one demo-sized patch problem per engine of
:data:`~polarface.inverse.polarimetric.engines.POLARIMETRIC_ENGINES` without any file: a spherical-cap
texture patch (``side x side`` texels, head-sized, 1 m in front of :func:`polarface.capture.rig.paper_rig`)
seen by both polarimetric cameras over ``frames`` chair yaws (the demo preset: 24 frames = 48 views),
with observations rendered by the model itself. :func:`run_benchmark` times the workloads of
:data:`TIMED` on the whole patch:

* ``fused_objective``: one evaluation of the total loss and its gradient on the packed raw variables
  (:class:`polarface.inverse.polarimetric.step.FusedObjective`: numba forward, the fused kernel of
  :mod:`polarface.inverse.polarimetric.kernel`, numba regularisers and chain rule) — what the default
  L-BFGS fit calls about 1.05 times per iteration; its rate is the headline ``fused_kernel`` rate;
* ``fused_kernel_only``: the fused kernel alone
  (:func:`~polarface.inverse.polarimetric.fused.fused_loss_and_grad`, data loss and its gradient; the
  number benchmarks/bench_roofline.py sets against this CPU's bounds);
* ``fused_rmsprop_step``: whole RMSprop steps as ``--optimizer rmsprop`` runs them
  (:func:`~polarface.inverse.polarimetric.optimise.optimise_patch` with ``optimizer="rmsprop"``);
* ``torch_objective``: loss and autograd backward of the vectorised torch reference (what L-BFGS calls
  on non-CPU devices);

each for about ``seconds`` of wall time: a calibrated iteration count per repeat (after a warm-up that
includes the JIT compile), ``repeats`` repeats, and their median, min/max and interquartile range (a
shared machine makes single short timings swing by tens of percent). The baseline
(:mod:`polarface.inverse.polarimetric.bench_eager`) is the same losses
written the straightforward way (the style of the authors' release): a Python loop over texels, each
evaluating :func:`polarface.optics.render_polarimetric` for its views one light at a time, its own
backward and optimiser step (two steps per texel: it is ~1e3 times slower). Rates are texel-view
iterations per second: samples (texel x view) times iterations over wall seconds.
"""

from __future__ import annotations

import dataclasses
import math
import os
import resource
import time
from collections.abc import Sequence

import numba
import numpy as np
import torch

from polarface.inverse.polarimetric.bench_eager import eager_rate as eager_baseline_rate
from polarface.inverse.polarimetric.config import PolarimetricConfig, initial_raw
from polarface.inverse.polarimetric.engines import POLARIMETRIC_ENGINES
from polarface.inverse.polarimetric.fused import build_fused_samples, fused_loss_and_grad
from polarface.inverse.polarimetric.model import (
    SampleBatch,
    precompute_samples,
    render_samples,
)
from polarface.inverse.polarimetric.optimise import optimise_patch
from polarface.inverse.polarimetric.problem import PatchProblem
from polarface.inverse.polarimetric.step import FusedObjective, pack_raw
from polarface.texture import TexelGeometry, ViewSpec, build_views, texel_geometry

__all__ = ["PAPER_A100_RATE", "TIMED", "BenchmarkProblem", "benchmark_problem", "run_benchmark"]

#: Timed workloads (module docstring): name -> what one iteration is.
TIMED = {
    "fused_objective": "FusedObjective: loss + analytic gradient of the whole patch (one L-BFGS evaluation)",
    "fused_kernel_only": "fused_loss_and_grad: the data-loss kernel alone (forward + analytic gradient)",
    "fused_rmsprop_step": "optimise_patch(optimizer='rmsprop'): objective + RMSprop update, all numba",
    "torch_objective": "PatchProblem.loss + autograd backward of the torch reference",
}
#: The paper's rate on an A100: 150 epochs x 2048^2 texels x 200 frames in 180 min (texel-view its / s).
PAPER_A100_RATE = 150 * 2048 * 2048 * 200 / (180 * 60)


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
        n, device = batch.count, normals.device
        pred = render_samples(
            batch,
            normals[batch.texel],
            torch.full((n,), 1.42, dtype=dtype, device=device),
            torch.full((n,), 0.4, dtype=dtype, device=device),
            torch.full((n,), 0.9, dtype=dtype, device=device),
            torch.full((n,), 0.5, dtype=dtype, device=device),
            torch.full((n,), 0.25, dtype=dtype, device=device),
            torch.full((n, 3), 0.4, dtype=dtype, device=device),
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


def _timed_workloads(bench: BenchmarkProblem, device: torch.device) -> dict[str, tuple]:
    """Workload name -> ``(run(n), problem, torch threads)`` for each workload of :data:`TIMED` that runs
    on ``device``; ``run(n)`` does ``n`` iterations of it."""
    config = PolarimetricConfig()
    workloads: dict[str, tuple] = {}
    if POLARIMETRIC_ENGINES["fused"].supports(device):
        fused_problem = bench.problems["fused"]
        objective = FusedObjective(fused_problem, config, np.dtype(np.float32))
        packed = pack_raw(bench.raw).astype(np.float64)  # as the fused L-BFGS holds them
        grad = np.zeros(packed.shape)
        objective(packed, grad)  # fills objective.params for the kernel-only workload

        def fused_objective(n: int) -> None:
            for _ in range(n):
                objective(packed, grad)

        samples = objective.samples

        def fused_kernel(n: int) -> None:
            for _ in range(n):
                fused_loss_and_grad(samples, objective.params, objective.data_weights, objective.scale)

        def fused_rmsprop(n: int) -> None:
            rmsprop = dataclasses.replace(config, optimizer="rmsprop", iterations=n)
            optimise_patch(fused_problem, bench.raw, rmsprop)

        # as in the fit: the kernel's threads are numba's; torch (L-BFGS's update) runs on one thread
        workloads["fused_objective"] = (fused_objective, fused_problem, 1)
        workloads["fused_kernel_only"] = (fused_kernel, fused_problem, 1)
        workloads["fused_rmsprop_step"] = (fused_rmsprop, fused_problem, 1)
    torch_problem = bench.problems["torch"]
    leaves = {k: v.detach().clone().requires_grad_(True) for k, v in bench.raw.items()}

    def torch_objective(n: int) -> None:
        for _ in range(n):
            for leaf in leaves.values():
                leaf.grad = None
            total, _ = torch_problem.loss(leaves)
            total.backward()
        if device.type == "cuda":
            torch.cuda.synchronize()

    workloads["torch_objective"] = (torch_objective, torch_problem, torch.get_num_threads())
    return workloads


def _calibrated_iterations(run, seconds_per_repeat: float, min_iterations: int) -> int:
    """Iterations of ``run`` that take about ``seconds_per_repeat`` (at least ``min_iterations``), from
    doubling trial runs of up to about a quarter of it."""
    run(1)  # warm-up (JIT compile, caches)
    n, elapsed = 1, 0.0
    while True:
        tick = time.perf_counter()
        run(n)
        elapsed = time.perf_counter() - tick
        if elapsed >= 0.25 * seconds_per_repeat or n >= 1 << 20:
            break
        n *= 2
    return max(int(min_iterations), math.ceil(seconds_per_repeat * n / max(elapsed, 1e-9)))


def _repeat_rates(run, samples: int, seconds: float, repeats: int, min_iterations: int) -> dict:
    """Median and spread of the texel-view iteration rate of ``run`` over ``repeats`` timed repeats of
    about ``seconds / repeats`` each (:func:`_calibrated_iterations`)."""
    iterations = _calibrated_iterations(run, seconds / repeats, min_iterations)
    rates, wall, cpu = [], 0.0, 0.0
    for _ in range(repeats):
        cpu_tick, tick = time.process_time(), time.perf_counter()
        run(iterations)
        elapsed = time.perf_counter() - tick
        cpu += time.process_time() - cpu_tick
        wall += elapsed
        rates.append(samples * iterations / elapsed)
    q25, median, q75 = np.percentile(rates, [25, 50, 75])
    return {
        "median": float(median),
        "min": float(min(rates)),
        "max": float(max(rates)),
        "q25": float(q25),
        "q75": float(q75),
        "rates": [float(r) for r in rates],
        "repeats": int(repeats),
        "iterations_per_repeat": int(iterations),
        "wall_s": wall,
        "cpu_s": cpu,
        "cpu_per_wall": cpu / wall if wall > 0 else math.nan,
        # per CPU-second of this process (all its threads): steadier than wall rates on a shared machine
        "per_cpu_second": samples * iterations * repeats / cpu if cpu > 0 else math.nan,
    }


def _timed_rates(
    bench: BenchmarkProblem,
    device: torch.device,
    seconds: float,
    repeats: int,
    min_iterations: int,
    names: Sequence[str],
) -> dict[str, dict]:
    """Workload name -> :func:`_repeat_rates` (NaN rates for workloads that do not run on ``device`` or
    are not in ``names``)."""
    out = {}
    workloads = _timed_workloads(bench, device)
    for name in TIMED:
        if name not in workloads or name not in names:
            out[name] = {"median": math.nan, "min": math.nan, "max": math.nan, "wall_s": math.nan}
            continue
        run, problem, threads = workloads[name]
        previous = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            out[name] = _repeat_rates(run, problem.batch.count, seconds, repeats, min_iterations)
        finally:
            torch.set_num_threads(previous)
    return out


def run_benchmark(
    side: int = 48,
    frames: int = 24,
    iterations: int = 1,
    baseline_texels: int = 4,
    device: str | torch.device = "cpu",
    seconds: float = 3.0,
    repeats: int = 5,
    workloads: Sequence[str] | None = None,
) -> dict:
    """Time every workload of :data:`TIMED` and the eager baseline (module docstring); returns a
    JSON-able dict.

    Args:
        side, frames: the patch (:func:`benchmark_problem`).
        iterations: at least this many iterations per timed repeat.
        baseline_texels: texels of the eager baseline (2 iterations each).
        device: torch device of the torch workload (the fused ones run on the CPU only).
        seconds: timed wall seconds per workload, over all repeats (iteration counts are calibrated).
        repeats: timed repeats per workload (the rates' median and spread are reported).
        workloads: names of :data:`TIMED` to time (default: all; the others get NaN rates).

    Returns:
        ``fused_kernel_texel_view_iterations_per_s`` (median rate of ``fused_objective``: what the
        default L-BFGS fit evaluates per iteration), ``torch_vectorised_texel_view_iterations_per_s``
        (median of ``torch_objective``), ``eager_baseline_texel_view_iterations_per_s``, ``speedup``
        (fastest over eager), ``workloads`` (name -> median, min, max, q25, q75, per-repeat rates,
        iterations per repeat, wall and CPU seconds), ``load_average`` (1-minute, before and after),
        peak RSS and the run's sizes.
    """
    load_before = os.getloadavg()[0]
    started = time.perf_counter()
    bench = benchmark_problem(side, frames, device=device)
    setup_s = time.perf_counter() - started
    problem = bench.problems["torch"]
    names = list(TIMED) if workloads is None else list(workloads)
    unknown = [n for n in names if n not in TIMED]
    if unknown:
        raise ValueError(f"argument 'workloads' must name workloads of {list(TIMED)}; got {unknown}")
    rates = _timed_rates(bench, torch.device(device), float(seconds), int(repeats), int(iterations), names)
    fused, torch_rates = rates["fused_objective"], rates["torch_objective"]
    fused_rate, torch_rate = fused["median"], torch_rates["median"]
    best_rate = fused_rate if fused_rate == fused_rate else torch_rate
    eager_rate, eager_s = eager_baseline_rate(problem, bench.views, baseline_texels)
    return {
        "device": str(device),
        "threads": torch.get_num_threads(),
        "texels": int(problem.texel_count),
        "views": len(bench.views),
        "samples": problem.batch.count,
        "iterations": int(fused.get("iterations_per_repeat", iterations)),
        "numba_threads": numba.get_num_threads(),
        "fused_kernel_texel_view_iterations_per_s": fused_rate,
        "torch_vectorised_texel_view_iterations_per_s": torch_rate,
        "eager_baseline_texel_view_iterations_per_s": eager_rate,
        "speedup": best_rate / eager_rate if eager_rate > 0 else math.nan,
        "paper_a100_rate": PAPER_A100_RATE,
        "setup_s": setup_s,
        "fused_s": fused["wall_s"],
        "torch_s": torch_rates["wall_s"],
        "eager_s": eager_s,
        "seconds_per_workload": float(seconds),
        "repeats": int(repeats),
        "workloads": rates,
        "timed": dict(TIMED),
        "load_average": [load_before, os.getloadavg()[0]],
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }

