"""Roofline of the fused polarimetric kernel on this CPU: ``python benchmarks/bench_roofline.py``.

Measures

* the CPU's compute peak: numba loops (``parallel=True``, all numba threads, ``fastmath``) over a
  vector that stays in L1, each element carried through a chain of 16 dependent ``v = v * a + b``
  (one fused multiply-add = 2 flops; LLVM vectorises across elements and interleaves the
  independent elements to hide the FMA latency), in float32 and float64; also the throughput of
  division and square root (the kernel's other arithmetic) the same way;
* the memory bandwidth: STREAM-like copy ``a = b`` and triad ``a = b + s c`` on float64 arrays of
  ``--stream-mb`` MB each (>> the 32 MB L3), all threads; bytes counted as STREAM does (2 resp. 3
  arrays x 8 bytes per element, no write-allocate);
* the fused kernel's work per texel-view iteration (one sample: a texel seen in one view, forward and
  analytic gradient over all K lights), counted by *instrumenting* kernel.py's own code: its phase
  functions (:mod:`polarface.inverse.polarimetric.kernel`, :mod:`polarface.inverse.polarimetric._kernel_math`)
  are re-bound, as ``kernel._compile`` does for numba, to a namespace whose float type ``F`` and
  ``math.sqrt`` build a dataflow graph instead of numbers, and run on one real sample of the benchmark
  patch. Each graph node is one add/sub/mul/div/sqrt; equal nodes inside one vectorised loop body
  (per phase, per light) are merged (as LLVM's CSE does), and only nodes that reach the kernel's
  outputs are counted (as its dead-code elimination does). Not counted: min/max, compares and selects,
  negations, the gather/scatter copies. (Check: the traced sample's loss equals the compiled kernel's
  on a one-sample patch to 1e-16 relative, so the trace runs the kernel's own arithmetic.) Bytes: the
  compulsory traffic per sample (:class:`~polarface.inverse.polarimetric.fused.FusedSamples`: view
  index, light bitmask, 9 observations) plus the per-texel parameters, position, gradient and loss
  shared by its views;
* the kernel's achieved rate (``polarface bench``'s ``fused_kernel_only`` and ``fused_objective``
  workloads: calibrated seconds, median of repeats);

and prints the roofline statement: arithmetic intensity, the kernel's fraction of the compute bound
(achieved flops / FMA peak of its float type) and of the memory bound (achieved bytes / triad
bandwidth), and which bound applies.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
import types

import numba
import numpy as np
import torch
from numba import prange

from polarface.inverse.polarimetric import kernel as kernel_module
from polarface.inverse.polarimetric import run_benchmark
from polarface.inverse.polarimetric.bench import benchmark_problem
from polarface.inverse.polarimetric.config import PolarimetricConfig
from polarface.inverse.polarimetric.step import FusedObjective, pack_raw

_CHAIN = 16  # dependent operations per element and pass


@numba.njit(parallel=True, fastmath=True, cache=True)
def _fma_loop(x, passes, a, b):
    """``x[t]`` (one row per thread) through ``passes x 16`` multiply-adds ``v = v a + b`` in 8
    independent chains per vector element (fast-math: fused to FMA)."""
    for t in prange(x.shape[0]):
        row = x[t]
        n = row.shape[0] // 8
        for _ in range(passes):
            for j in range(n):
                v0, v1, v2, v3 = row[j], row[j + n], row[j + 2 * n], row[j + 3 * n]
                v4, v5, v6, v7 = row[j + 4 * n], row[j + 5 * n], row[j + 6 * n], row[j + 7 * n]
                for _k in range(_CHAIN):
                    v0 = v0 * a + b
                    v1 = v1 * a + b
                    v2 = v2 * a + b
                    v3 = v3 * a + b
                    v4 = v4 * a + b
                    v5 = v5 * a + b
                    v6 = v6 * a + b
                    v7 = v7 * a + b
                row[j], row[j + n], row[j + 2 * n], row[j + 3 * n] = v0, v1, v2, v3
                row[j + 4 * n], row[j + 5 * n], row[j + 6 * n], row[j + 7 * n] = v4, v5, v6, v7


@numba.njit(parallel=True, fastmath=False, cache=True)
def _div_loop(x, passes, a, b):
    """As :func:`_fma_loop` with divisions ``v = a / v`` (IEEE: no reciprocal approximation)."""
    for t in prange(x.shape[0]):
        row = x[t]
        n = row.shape[0] // 8
        for _ in range(passes):
            for j in range(n):
                v0, v1, v2, v3 = row[j], row[j + n], row[j + 2 * n], row[j + 3 * n]
                v4, v5, v6, v7 = row[j + 4 * n], row[j + 5 * n], row[j + 6 * n], row[j + 7 * n]
                for _k in range(_CHAIN):
                    v0 = a / v0
                    v1 = a / v1
                    v2 = a / v2
                    v3 = a / v3
                    v4 = a / v4
                    v5 = a / v5
                    v6 = a / v6
                    v7 = a / v7
                row[j], row[j + n], row[j + 2 * n], row[j + 3 * n] = v0, v1, v2, v3
                row[j + 4 * n], row[j + 5 * n], row[j + 6 * n], row[j + 7 * n] = v4, v5, v6, v7


@numba.njit(parallel=True, fastmath=False, cache=True)
def _sqrt_loop(x, passes, a, b):
    """As :func:`_fma_loop` with square roots ``v = sqrt(v)`` (IEEE)."""
    for t in prange(x.shape[0]):
        row = x[t]
        n = row.shape[0] // 8
        for _ in range(passes):
            for j in range(n):
                v0, v1, v2, v3 = row[j], row[j + n], row[j + 2 * n], row[j + 3 * n]
                v4, v5, v6, v7 = row[j + 4 * n], row[j + 5 * n], row[j + 6 * n], row[j + 7 * n]
                for _k in range(_CHAIN):
                    v0 = math.sqrt(v0)
                    v1 = math.sqrt(v1)
                    v2 = math.sqrt(v2)
                    v3 = math.sqrt(v3)
                    v4 = math.sqrt(v4)
                    v5 = math.sqrt(v5)
                    v6 = math.sqrt(v6)
                    v7 = math.sqrt(v7)
                row[j], row[j + n], row[j + 2 * n], row[j + 3 * n] = v0, v1, v2, v3
                row[j + 4 * n], row[j + 5 * n], row[j + 6 * n], row[j + 7 * n] = v4, v5, v6, v7


@numba.njit(parallel=True, cache=True)
def _copy(a, b):
    for i in prange(a.shape[0]):
        a[i] = b[i]


@numba.njit(parallel=True, cache=True)
def _triad(a, b, c, s):
    for i in prange(a.shape[0]):
        a[i] = b[i] + s * c[i]


def _best_seconds(run, repeats: int) -> float:
    run()  # warm-up (compile)
    best = math.inf
    for _ in range(repeats):
        tick = time.perf_counter()
        run()
        best = min(best, time.perf_counter() - tick)
    return best


def measure_peaks(repeats: int, stream_mb: float) -> dict:
    """Peak rates of this CPU with the current numba threads (module docstring): flop/s, op/s, bytes/s."""
    threads = numba.get_num_threads()
    out: dict = {"threads": threads}
    lanes, passes = 1024, 2000  # 1024 elements x 4-8 bytes per thread: in L1
    for dtype in (np.float32, np.float64):
        name = np.dtype(dtype).name
        for kind, loop, ops_per_chain_step, start, a, steps in (
            ("fma_flops", _fma_loop, 2, 0.5, 0.999, passes),
            ("div_per_s", _div_loop, 1, 1.5, 2.0, passes // 8),
            ("sqrt_per_s", _sqrt_loop, 1, 1.5, 0.0, passes // 8),
        ):
            x = np.full((threads, lanes), start, dtype=dtype)
            args = (x, steps, dtype(a), dtype(0.0005))
            seconds = _best_seconds(lambda: loop(*args), repeats)  # noqa: B023
            out[f"{kind}_{name}"] = ops_per_chain_step * _CHAIN * threads * lanes * steps / seconds
    n = int(stream_mb * 2**20 / 8)
    a, b, c = np.zeros(n), np.ones(n), np.full(n, 2.0)
    out["copy_bytes_per_s"] = 2 * 8 * n / _best_seconds(lambda: _copy(a, b), repeats)
    out["triad_bytes_per_s"] = 3 * 8 * n / _best_seconds(lambda: _triad(a, b, c, 3.0), repeats)
    out["stream_mb_per_array"] = stream_mb
    return out


class _Node:
    """A traced float: its value and its node in :class:`_Graph` (default: the constant ``value``)."""

    __slots__ = ("node", "value")
    graph: _Graph

    def __init__(self, value, node=None):
        self.value = float(value)
        self.node = _Node.graph.node("const", self.value) if node is None else node

    @classmethod
    def input(cls, value) -> _Node:
        """A kernel input (its own node, never merged with another)."""
        return cls(value, cls.graph.node("input", len(cls.graph.ops)))

    def _op(self, op, other, swap=False):
        other = other if isinstance(other, _Node) else _Node(other)
        a, b = (other, self) if swap else (self, other)
        value = {"add": a.value + b.value, "sub": a.value - b.value, "mul": a.value * b.value}.get(op)
        if op == "div":
            value = a.value / b.value if b.value != 0 else math.copysign(math.inf, a.value)
        return _Node(value, _Node.graph.node(op, a.node, b.node))

    def __add__(self, o):
        return self._op("add", o)

    def __radd__(self, o):
        return self._op("add", o, True)

    def __sub__(self, o):
        return self._op("sub", o)

    def __rsub__(self, o):
        return self._op("sub", o, True)

    def __mul__(self, o):
        return self._op("mul", o)

    def __rmul__(self, o):
        return self._op("mul", o, True)

    def __truediv__(self, o):
        return self._op("div", o)

    def __rtruediv__(self, o):
        return self._op("div", o, True)

    def __neg__(self):  # a sign flip: not counted as a flop (folds into FNMADD / a subtraction)
        return _Node(-self.value, _Node.graph.node("neg", self.node))

    def __lt__(self, o):
        return self.value < float(o)

    def __le__(self, o):
        return self.value <= float(o)

    def __gt__(self, o):
        return self.value > float(o)

    def __ge__(self, o):
        return self.value >= float(o)

    def __float__(self):
        return self.value


class _Graph:
    """Hash-consed dataflow graph: equal ``(op, inputs)`` inside one scope share a node (CSE)."""

    def __init__(self):
        self.ops: list[tuple] = []
        self.scope: dict = {}

    def node(self, op, a, b=None):
        key = (op, a, b)
        if key not in self.scope:
            self.ops.append(key)
            self.scope[key] = len(self.ops) - 1
        return self.scope[key]

    def new_scope(self):
        self.scope = {}

    def live_counts(self, outputs) -> dict[str, int]:
        """Operations of each kind that reach ``outputs`` (node ids)."""
        seen, stack = set(), list(outputs)
        while stack:
            n = stack.pop()
            if n in seen:
                continue
            seen.add(n)
            op, a, b = self.ops[n]
            if op not in ("const", "input"):
                stack += [m for m in (a, b) if m is not None]
        counts = {"add": 0, "sub": 0, "mul": 0, "div": 0, "sqrt": 0, "neg": 0}
        for n in seen:
            op = self.ops[n][0]
            if op in counts:
                counts[op] += 1
        return counts


class _Work:
    """``work[row, i]`` for one sample (the kernel's SoA scratch array)."""

    def __init__(self):
        self.rows: dict[int, object] = {}

    def __getitem__(self, key):
        return self.rows[key[0]]

    def __setitem__(self, key, value):
        self.rows[key[0]] = value


def _traced_phases():
    """kernel.py's phase functions re-bound to traced floats (as ``kernel._compile`` binds them)."""
    graph = _Graph()
    _Node.graph = graph
    shim = types.SimpleNamespace(sqrt=lambda x: _Node(math.sqrt(x.value), graph.node("sqrt", x.node)))
    namespace = dict(vars(kernel_module))
    namespace["F"] = lambda x: x if isinstance(x, _Node) else _Node(x)
    namespace["math"] = shim
    for name in (
        "fresnel", "ggx", "g1_over_cos", "cos2_sin2", "double_angle", "light_terms", "_geometry",
        "_texel", "_exit_terms", "_view_terms", "_load_light", "_zero_rows", "_current_light",
        "_forward_lights", "_channel", "_losses", "_reverse_lights",
    ):  # fmt: skip
        source = getattr(kernel_module, name)
        namespace[name] = types.FunctionType(source.__code__, namespace, name)
    load_light = namespace["_load_light"]

    def scoped_load_light(work, count, k):  # each light: a new pass of the vectorised loop body
        graph.new_scope()
        load_light(work, count, k)

    namespace["_load_light"] = scoped_load_light
    return graph, namespace


def count_kernel_work(side: int = 16, frames: int = 4) -> dict:
    """Flops of one texel-view iteration of the fused kernel (module docstring), on the first sample of
    a small benchmark patch, and the compulsory bytes per sample and per texel (float32 fit)."""
    bench = benchmark_problem(side, frames)
    problem = bench.problems["fused"]
    objective = FusedObjective(problem, PolarimetricConfig(), np.dtype(np.float64))
    objective(pack_raw(bench.raw).astype(np.float64), np.zeros(pack_raw(bench.raw).shape))
    samples, params = objective.samples, objective.params
    texel = int(np.searchsorted(samples.offsets, 0, side="right") - 1)
    s, v = int(samples.offsets[texel]), int(samples.sample_view[0])
    k_count = samples.light_pos.shape[2]
    graph, ns = _traced_phases()
    leaf = _Node.input
    work = _Work()
    k = kernel_module
    for c in range(3):  # the gather: inputs
        work[k._PX + c, 0] = leaf(samples.position[texel, c])
        work[k._OX + c, 0] = leaf(samples.view_center[v, c])
        work[k._UX + c, 0] = leaf(samples.view_up[v, c])
        work[k._RX + c, 0] = leaf(samples.view_ref_up[v, c])
        work[k._NX + c, 0] = leaf(params[texel, c])
    scalars = ((k._EN, k._ETA), (k._AS1, k._AS), (k._ASS1, k._ASS), (k._RS1, k._RS), (k._RSS1, k._RSS))
    for row, column in scalars:
        work[row, 0] = leaf(params[texel, column])
    for j in range(3):
        work[k._RHOC + j, 0] = leaf(params[texel, k._RHO + samples.view_channels[v, j]])
        for q in range(3):
            work[k._OBS + 3 * j + q, 0] = leaf(samples.observed[s, q, j])
    for light in range(k_count):
        base = k._LIGHTS + 7 * light
        for c in range(3):
            work[base + c, 0] = leaf(samples.light_pos[v, c, light])
            work[base + 3 + c, 0] = leaf(samples.light_intensity[v, c, light])
        work[base + 6, 0] = leaf(1.0)
    tiny = leaf(float(np.finfo(np.float32).eps) ** 4)
    scale = problem.scale
    constants = tuple(leaf(x) for x in (*objective.data_weights, 1.0 / scale, 0.05 * scale))
    # one CSE scope per vectorised loop body (kernel._kernel's phases): the view terms, each light of
    # the forward loop, the losses and the reverse loop (which reads what the forward loop kept), the
    # scatter
    graph.new_scope()
    ns["_view_terms"](work, 1, tiny)
    saved = _Work()  # the values each light's forward pass keeps for the reverse pass
    ns["_forward_lights"](work, saved, 1, k_count, tiny)
    graph.new_scope()
    ns["_losses"](work, 1, constants, tiny)
    ns["_reverse_lights"](work, saved, 1, k_count)
    graph.new_scope()
    outputs = _scatter(work)
    counts = graph.live_counts(outputs)
    flops = sum(counts.values())
    itemsize = 4  # the float32 fit
    return {
        "lights": int(k_count),
        "ops": counts,
        "flops_per_texel_view": flops,
        "bytes_per_sample_float32": 4 + 8 + 9 * itemsize,  # view index, light bitmask, observations
        # parameters, position, gradient, loss, CSR offset
        "bytes_per_texel_float32": (14 + 3 + 14 + 1) * itemsize + 8,
    }


def _scatter(work) -> list:
    """Node ids of the kernel's scatter phase outputs (its arithmetic traced too)."""
    k = kernel_module
    row = lambda r: work[r, 0]  # noqa: E731
    g_cos_o = (row(k._GCOSO) + row(k._LACC + 4)) * row(k._COSO_IN)
    out = []
    for c in range(3):
        g = row(k._LACC + 1 + c) + g_cos_o * row(k._OX + c) + row(k._GAO) * row(k._AOX + c)
        out.append(g + row(k._GBO) * row(k._POX + c))
    out.append(row(k._GETA) + row(k._LACC))
    out += [row(k._LACC + q) for q in range(5, 9)]
    out += [row(k._GRHO + j) for j in range(3)] + [row(k._LOSS)] + [row(k._TERMS + q) for q in range(4)]
    # accumulation into the texel's float64 sums: one add per output
    return [(x + _Node.input(0.0)).node for x in out]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=10, help="repeats of each peak loop (best kept)")
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="numba and torch threads for the peaks and the kernel (default 1: one core, the steadiest "
        "comparison on a shared machine; the machine's peak is about cores x that)",
    )
    parser.add_argument("--stream-mb", type=float, default=512.0, help="MB per STREAM array (default 512)")
    parser.add_argument("--seconds", type=float, default=3.0, help="polarface bench seconds per workload")
    parser.add_argument("--json", action="store_true", help="print JSON only")
    args = parser.parse_args()
    load_before = os.getloadavg()[0]
    numba.set_num_threads(args.threads)
    torch.set_num_threads(args.threads)
    work = count_kernel_work()
    peaks = measure_peaks(args.repeats, args.stream_mb)
    bench = run_benchmark(
        seconds=args.seconds, baseline_texels=1, workloads=("fused_objective", "fused_kernel_only")
    )
    kernel_rate = bench["workloads"]["fused_kernel_only"]["median"]
    objective_rate = bench["workloads"]["fused_objective"]["median"]
    views_per_texel = bench["samples"] / bench["texels"]
    flops = work["flops_per_texel_view"]
    nbytes = work["bytes_per_sample_float32"] + work["bytes_per_texel_float32"] / views_per_texel
    work["views_per_texel"] = views_per_texel
    work["bytes_per_texel_view_float32"] = nbytes
    compute_bound = peaks["fma_flops_float32"] / flops
    ops = work["ops"]
    # the instruction mix, each class at its own measured throughput, not overlapped: add/sub/mul as if
    # all fused to FMAs at peak, plus the IEEE divisions and square roots
    mix_seconds = (
        (flops - ops["div"] - ops["sqrt"]) / peaks["fma_flops_float32"]
        + ops["div"] / peaks["div_per_s_float32"]
        + ops["sqrt"] / peaks["sqrt_per_s_float32"]
    )
    memory_bound = peaks["triad_bytes_per_s"] / nbytes
    result = {
        "peaks": peaks,
        "kernel_work": work,
        "arithmetic_intensity_flop_per_byte": flops / nbytes,
        "ridge_point_flop_per_byte": peaks["fma_flops_float32"] / peaks["triad_bytes_per_s"],
        "compute_bound_texel_view_per_s": compute_bound,
        "memory_bound_texel_view_per_s": memory_bound,
        "instruction_mix_bound_texel_view_per_s": 1.0 / mix_seconds,
        "bound": "compute" if compute_bound < memory_bound else "memory",
        "kernel_texel_view_per_s": kernel_rate,
        "objective_texel_view_per_s": objective_rate,
        "kernel_gflops": kernel_rate * flops / 1e9,
        "kernel_fraction_of_compute_bound": kernel_rate / compute_bound,
        "kernel_fraction_of_memory_bound": kernel_rate / memory_bound,
        "kernel_fraction_of_instruction_mix_bound": kernel_rate * mix_seconds,
        "objective_fraction_of_compute_bound": objective_rate / compute_bound,
        "bench_spread": {
            n: [w["min"], w["max"]] for n, w in bench["workloads"].items() if w["min"] == w["min"]
        },
        "load_average": [load_before, os.getloadavg()[0]],
    }
    if args.json:
        print(json.dumps(result, indent=2))
        return
    print(
        f"threads {peaks['threads']} (numba and torch) of {os.cpu_count()} cores, load average "
        f"{load_before:.2f} -> {result['load_average'][1]:.2f}"
    )
    print(
        f"peak FMA       {peaks['fma_flops_float32'] / 1e9:.1f} GFLOP/s float32, "
        f"{peaks['fma_flops_float64'] / 1e9:.1f} float64"
    )
    print(
        f"divide / sqrt  {peaks['div_per_s_float32'] / 1e9:.2f} / {peaks['sqrt_per_s_float32'] / 1e9:.2f} "
        "G/s float32"
    )
    print(
        f"memory         copy {peaks['copy_bytes_per_s'] / 1e9:.1f} GB/s, triad "
        f"{peaks['triad_bytes_per_s'] / 1e9:.1f} GB/s"
    )
    print(
        f"kernel work    {flops} flops per texel-view iteration ({work['lights']} lights; add {ops['add']}, "
        f"sub {ops['sub']}, mul {ops['mul']}, div {ops['div']}, sqrt {ops['sqrt']}), "
        f"{nbytes:.1f} bytes -> {flops / nbytes:.0f} flop/byte "
        f"(ridge point {result['ridge_point_flop_per_byte']:.1f})"
    )
    print(
        f"bounds         compute {compute_bound:.3e}, memory {memory_bound:.3e} texel-view iterations/s: "
        f"{result['bound']} bound"
    )
    print(
        f"kernel         {kernel_rate:.3e} texel-view iterations/s = {result['kernel_gflops']:.1f} GFLOP/s = "
        f"{100 * result['kernel_fraction_of_compute_bound']:.1f} % of the compute bound, "
        f"{100 * result['kernel_fraction_of_memory_bound']:.2f} % of the memory bound"
    )
    print(
        f"mix bound      {1.0 / mix_seconds:.3e} texel-view iterations/s (FMA peak for add/sub/mul, measured "
        f"divide and sqrt rates, not overlapped): kernel at "
        f"{100 * result['kernel_fraction_of_instruction_mix_bound']:.1f} %"
    )
    print(
        f"objective      {objective_rate:.3e} texel-view iterations/s (kernel + numba glue) = "
        f"{100 * result['objective_fraction_of_compute_bound']:.1f} % of the compute bound"
    )


if __name__ == "__main__":
    main()
