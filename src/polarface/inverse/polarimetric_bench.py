"""Throughput benchmark of the polarimetric stage: fused kernel, vectorised torch, eager per-texel baseline.

:func:`benchmark_problem` builds one demo-sized patch problem without any file: a spherical-cap
texture patch (``side x side`` texels, head-sized, 1 m in front of :func:`polarface.capture.rig.paper_rig`)
seen by both polarimetric cameras over ``frames`` chair yaws (the demo preset: 24 frames = 48 views),
with observations rendered by the model itself. :func:`run_benchmark` times

* the fused kernel (:mod:`polarface.inverse.polarimetric_kernel`, numba, analytic gradients) and the
  vectorised torch autograd reference: one optimiser iteration (forward, backward, RMSprop step) of
  :func:`polarface.inverse.polarimetric_fit.optimise_patch` on the whole patch each;
* the baseline: the same losses written the straightforward way (the style of the authors' release):
  a Python loop over texels, each evaluating :func:`polarface.optics.render_polarimetric` for its views
  one light at a time, its own backward and optimiser step;

and reports texel-view iterations per second for each, the speed-up of the fastest over the baseline
and the peak RSS.
"""

from __future__ import annotations

import math
import resource
import time

import numba
import numpy as np
import torch

from polarface.inverse.polarimetric_fit import PolarimetricConfig, _PatchProblem, initial_raw, optimise_patch
from polarface.inverse.polarimetric_fused import build_fused_samples
from polarface.inverse.polarimetric_losses import data_losses
from polarface.inverse.polarimetric_model import SamplePrediction, precompute_samples, render_samples
from polarface.texture import TexelGeometry, build_views, texel_geometry

__all__ = ["benchmark_problem", "run_benchmark"]


def benchmark_problem(
    side: int = 48, frames: int = 24, dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu"
):
    """``(problem, fused_problem, raw, views)``: a patch of ``side^2`` texels and ``2 frames`` views
    (module docstring); ``problem`` evaluates the data loss with the vectorised torch reference,
    ``fused_problem`` with the fused numba kernel (same samples)."""
    from polarface.capture.rig import paper_rig
    from polarface.geometry.uv_raster import rasterize_uv
    from polarface.simulate.sphere_capture import sphere_cap_mesh
    from polarface.simulate.sphere_capture import sphere_placement as _placement

    mesh = sphere_cap_mesh(80.0, 60.0, segments=64)
    raster = rasterize_uv(mesh, side)
    geometry: TexelGeometry = texel_geometry(raster)
    rig = paper_rig(width=612, height=512)
    yaws = np.radians(np.linspace(-30.0, 30.0, frames))
    poses = np.stack([_placement(float(y)) for y in yaws])
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
    pick = lambda attr: np.array([getattr(v, attr) for v in views])[v_idx]  # noqa: E731
    lit = np.ones((len(v_idx), len(rig.lights)), bool)
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
    problem = _PatchProblem(batch, geometry, config, 1.0, dtype, torch.device(device))
    raw = {
        k: torch.as_tensor(v, dtype=dtype, device=device)
        for k, v in initial_raw((side, side), config).items()
    }
    with torch.no_grad():
        normals = problem.normals(torch.zeros((side, side), dtype=dtype, device=device))
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
        observed = torch.stack([pred.i_sss, pred.i_zeta, pred.i_s], dim=1)
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
    problem = _PatchProblem(batch, geometry, config, scale, dtype, torch.device(device))
    fused_problem = _PatchProblem(batch, geometry, config, scale, dtype, torch.device(device), fused)
    return problem, fused_problem, raw, views


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


def run_benchmark(
    side: int = 48,
    frames: int = 24,
    iterations: int = 5,
    baseline_texels: int = 4,
    device: str | torch.device = "cpu",
) -> dict:
    """Time both implementations (module docstring); returns a JSON-able dict."""
    started = time.perf_counter()
    problem, fused_problem, raw, views = benchmark_problem(side, frames, device=device)
    setup_s = time.perf_counter() - started
    batch = problem.batch

    def rate(candidate: _PatchProblem) -> tuple[float, float]:
        optimise_patch(candidate, raw, PolarimetricConfig(iterations=1))  # warm-up (and JIT compile)
        tick = time.perf_counter()
        optimise_patch(candidate, raw, PolarimetricConfig(iterations=int(iterations), warmup=1))
        if torch.device(device).type == "cuda":
            torch.cuda.synchronize()
        seconds = time.perf_counter() - tick
        return batch.count * iterations / seconds, seconds

    torch_rate, torch_s = rate(problem)
    fused_rate, fused_s = (math.nan, math.nan)
    if torch.device(device).type == "cpu":
        # as in the fit: the kernel's threads are numba's; torch's per-texel glue runs on one thread
        previous = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            fused_rate, fused_s = rate(fused_problem)
        finally:
            torch.set_num_threads(previous)
    best_rate = fused_rate if fused_rate == fused_rate else torch_rate
    # baseline on a few texels (the rate does not depend on how many)
    texels = batch.texel.unique()[: int(baseline_texels)]
    work, eager_s = 0, 0.0
    for texel in texels:
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
        optimizer = torch.optim.RMSprop(list(params.values()), lr=1e-3)
        tick = time.perf_counter()
        for _ in range(2):
            _eager_texel_step(samples, params, optimizer, problem.scale)
        eager_s += time.perf_counter() - tick
        work += 2 * len(samples)
    eager_rate = work / eager_s if eager_s > 0 else math.nan
    return {
        "device": str(device),
        "threads": torch.get_num_threads(),
        "texels": int(problem.texel_count),
        "views": len(views),
        "samples": batch.count,
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
