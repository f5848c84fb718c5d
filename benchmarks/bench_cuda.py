"""The torch engine on a GPU: ``python benchmarks/bench_cuda.py [--device cuda] [--sides 48 128 192 256]``.

Prints, for the ``polarface bench`` patch (:func:`polarface.inverse.polarimetric.benchmark_problem`,
``side^2`` texels seen in ``2 frames`` views, 8 LED modules):

* **parity**: the torch engine's loss and autograd gradient (``PatchProblem.loss`` and its backward, at
  the benchmark's initial raw variables plus a seeded perturbation) on ``--device`` in float64 and
  float32 against the CPU in float64: relative loss difference and relative L2 norm of the gradient
  difference over all variables; the CPU's own float32 difference next to them. Checks: float64 within
  1e-9 (loss) and 1e-7 (gradient), float32 within 20x the CPU's float32 difference (floors 1e-5, 1e-4);
  the command exits 1 when one fails.
* **rate against patch size**: texel-view iterations per second of one loss + backward evaluation
  (``polarface bench``'s ``torch_objective`` workload: median of ``--repeats`` calibrated repeats of
  about ``--seconds`` each), and on CUDA the peak memory torch allocated and that per sample: the
  measurements behind
  :func:`polarface.inverse.polarimetric.device_fit_options` (docs/performance.md, "The CUDA path").
* the fit options a reconstruction takes on this device (``device_fit_options``).

With ``--device cpu`` it runs the same workloads on the CPU (the torch reference, not the fused kernel:
``polarface bench`` times that one).
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import torch

from polarface.inverse.polarimetric import benchmark_problem, device_fit_options, run_benchmark
from polarface.inverse.polarimetric.config import PolarimetricConfig, initial_raw


def _raw_variables(side: int, seed: int) -> dict[str, np.ndarray]:
    """The benchmark's initial raw variables with a seeded perturbation (float64)."""
    rng = np.random.default_rng(seed)
    raw = initial_raw((side, side), PolarimetricConfig())
    spread = {"displacement_mm": 0.05}  # a smaller one for the heights: they move the normals
    return {
        k: v.astype(np.float64) + spread.get(k, 0.3) * rng.standard_normal(v.shape) for k, v in raw.items()
    }


def _loss_and_grad(problem, raw: dict[str, np.ndarray], dtype: torch.dtype, device: torch.device):
    leaves = {k: torch.as_tensor(v, dtype=dtype, device=device).requires_grad_(True) for k, v in raw.items()}
    total, _ = problem.loss(leaves)
    total.backward()
    grads = {k: v.grad.detach().to("cpu", torch.float64).numpy() for k, v in leaves.items()}
    return float(total.detach().cpu().double()), grads


def parity(device: torch.device, side: int, frames: int, seed: int) -> dict:
    """Loss and gradient differences against the CPU in float64 (module docstring)."""
    raw = _raw_variables(side, seed)

    def evaluate(on: torch.device, dtype: torch.dtype):
        problem = benchmark_problem(side, frames, dtype=dtype, device=on).problems["torch"]
        return _loss_and_grad(problem, raw, dtype, on)

    ref_loss, ref_grad = evaluate(torch.device("cpu"), torch.float64)
    norm = math.sqrt(sum(float((g**2).sum()) for g in ref_grad.values()))
    cases = {"cpu_float32": (torch.device("cpu"), torch.float32)}
    if device.type != "cpu":
        cases[f"{device.type}_float64"] = (device, torch.float64)
        cases[f"{device.type}_float32"] = (device, torch.float32)
    report = {"reference_loss": ref_loss}
    for name, (on, dtype) in cases.items():
        loss, grad = evaluate(on, dtype)
        diff = math.sqrt(sum(float(((grad[k] - ref_grad[k]) ** 2).sum()) for k in ref_grad))
        report[name] = {
            "loss_rel_diff": abs(loss - ref_loss) / abs(ref_loss), "grad_rel_l2_diff": diff / norm
        }
    checks = {}
    if device.type != "cpu":
        f64, f32 = report[f"{device.type}_float64"], report[f"{device.type}_float32"]
        c32 = report["cpu_float32"]
        checks = {
            "float64_loss": f64["loss_rel_diff"] < 1e-9,
            "float64_grad": f64["grad_rel_l2_diff"] < 1e-7,
            "float32_loss": f32["loss_rel_diff"] < max(20 * c32["loss_rel_diff"], 1e-5),
            "float32_grad": f32["grad_rel_l2_diff"] < max(20 * c32["grad_rel_l2_diff"], 1e-4),
        }
    report["checks"] = checks
    return report


def rate(device: torch.device, side: int, frames: int, seconds: float, repeats: int) -> dict:
    """``polarface bench``'s ``torch_objective`` workload (one float32 loss + backward of the torch
    engine) on a ``side^2`` patch: texel-view iterations/s, and on CUDA the peak memory torch allocated
    during the benchmark (problem set-up included) and that per sample."""
    cuda = device.type == "cuda"
    if cuda:
        torch.cuda.reset_peak_memory_stats(device)
    bench = run_benchmark(
        side, frames, baseline_texels=0, device=device, seconds=seconds * repeats, repeats=repeats,
        workloads=["torch_objective"],
    )
    peak = torch.cuda.max_memory_allocated(device) if cuda else None
    timed, samples = bench["workloads"]["torch_objective"], int(bench["samples"])
    return {
        "side": side,
        "samples": samples,
        **{k: timed[k] for k in ("median", "min", "max", "iterations_per_repeat")},
        "peak_allocated_bytes": peak,
        "bytes_per_sample": peak / samples if peak else None,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda", help="torch device (default cuda)")
    parser.add_argument(
        "--sides", type=int, nargs="+", default=[48, 128, 192, 256], help="patch sides (texels)"
    )
    parser.add_argument("--frames", type=int, default=24, help="frames of the benchmark rig (2 views each)")
    parser.add_argument("--parity-side", type=int, default=48, help="patch side of the parity check")
    parser.add_argument("--seconds", type=float, default=1.0, help="seconds per timed repeat")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    args = parser.parse_args()
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        parser.error("argument '--device': CUDA was requested but torch.cuda.is_available() is False")
    report = {
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "torch": torch.__version__,
        "parity": parity(device, args.parity_side, args.frames, args.seed),
        "rates": [rate(device, s, args.frames, args.seconds, args.repeats) for s in args.sides],
        "device_fit_options": device_fit_options(device),
    }
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(f"bench_cuda: {report['device_name']} ({report['device']}), torch {report['torch']}")
        for name, value in report["parity"].items():
            if isinstance(value, dict) and "loss_rel_diff" in value:
                print(f"  parity {name:14s} vs cpu float64: loss {value['loss_rel_diff']:.2e}, "
                      f"gradient (relative L2) {value['grad_rel_l2_diff']:.2e}")
        print(f"  parity checks: {report['parity']['checks'] or 'none (cpu)'}")
        print("  side    samples  texel-view it/s: median (min-max)    peak allocated  bytes/sample")
        for r in report["rates"]:
            peak = "-", "-"
            if r["peak_allocated_bytes"]:
                peak = f"{r['peak_allocated_bytes'] / 2**20:.0f} MiB", f"{r['bytes_per_sample']:.0f}"
            spread = f"{r['median']:.3e} ({r['min']:.3e}-{r['max']:.3e})"
            print(f"  {r['side']:4d}  {r['samples']:9d}  {spread}  {peak[0]:>14s}  {peak[1]:>12s}")
        print(f"  fit options on this device: {report['device_fit_options'] or 'the defaults'}")
    if not all(report["parity"]["checks"].values()):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
