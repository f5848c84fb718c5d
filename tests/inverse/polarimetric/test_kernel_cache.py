"""The fused kernel computes the same bits in a process that compiled it and in one that loaded it from
numba's on-disk cache (issue 47).

numba optimises a ``prange`` body twice when it links it into the kernel; the process that compiled the
kernel runs the body optimised once, a process that loads the cache the body optimised twice. With
``reassoc`` among the fast-math flags the second optimisation re-associated sums differently, so the
first reconstruction after installing polarface (or after ``kernel.py`` changed) and every later one gave
different maps (a 3-patch fit of the tiny preset: 3456 eta texels differed, by up to 2e-5), and so did a
driver that compiled the kernel and Ray workers that loaded it. Each process here starts with its own
empty or filled cache folder (``NUMBA_CACHE_DIR``), so the test compiles the float32 kernel once (minutes
of CPU): slow.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from polarface.capture.rig import paper_rig
from polarface.inverse.polarimetric import build_fused_samples
from polarface.simulate.sphere_capture import sphere_placement
from polarface.texture import build_views

_EVALUATE = textwrap.dedent(
    """
    import json, sys
    import numpy as np
    from polarface.inverse.polarimetric.fused import FusedSamples, fused_loss_and_grad
    from polarface.inverse.polarimetric.kernel import compiled_kernel

    folder = sys.argv[1]
    with np.load(f"{folder}/inputs.npz") as saved:
        arrays = {k: saved[k] for k in saved.files}
    params, scale = arrays.pop("params"), float(arrays.pop("scale"))
    loss, grad, terms = fused_loss_and_grad(FusedSamples(**arrays), params, (1.0, 1.0, 1.0, 0.002), scale)
    np.savez(f"{folder}/{sys.argv[2]}.npz", loss=loss, grad=grad, terms=terms)
    stats = compiled_kernel(params.dtype).stats
    print(json.dumps({"hits": sum(stats.cache_hits.values()), "misses": sum(stats.cache_misses.values())}))
    """
)


def _inputs(folder: Path, texels: int = 300, frames: int = 4) -> None:
    """Random float32 samples of ``texels`` texels seen by both polarimetric cameras of ``frames`` frames,
    and parameters, saved to ``folder/inputs.npz``."""
    rng = np.random.default_rng(0)
    rig = paper_rig(width=256, height=212)
    poses = np.stack([sphere_placement(float(y)) for y in np.radians(np.linspace(-30, 30, frames))])
    views = build_views(rig, list(range(frames)), poses)
    table = {a: np.array([getattr(v, a) for v in views], np.float64) for a in (
        "camera_center", "camera_up", "reference_up", "light_positions", "light_intensity")}  # fmt: skip
    directions = rng.normal(size=(texels, 3))
    directions[:, 2] = np.abs(directions[:, 2]) + 0.8
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    texel, view = (a.ravel() for a in np.meshgrid(np.arange(texels), np.arange(len(views)), indexing="ij"))
    lit = rng.random((texel.size, table["light_positions"].shape[1])) < 0.85
    observed = rng.uniform(0.05, 1.0, (texel.size, 3, 3)) * np.array([1.0, 0.1, 0.3])[None, :, None]
    samples = build_fused_samples(
        80.0 * directions, texel, view, lit, observed, table["camera_center"], table["camera_up"],
        table["reference_up"], table["light_positions"], table["light_intensity"],
        np.array([v.channels for v in views]), dtype=np.float32,
    )  # fmt: skip
    normal = directions + 0.3 * rng.normal(size=(texels, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    columns = [normal] + [rng.uniform(low, high, (texels, count)) for low, high, count in (
        (1.2, 1.9, 1), (0.15, 0.6, 1), (0.7, 1.1, 1), (0.1, 0.8, 2), (0.1, 0.9, 6))]  # fmt: skip
    params = np.concatenate(columns, axis=1).astype(np.float32)  # GRAD_LAYOUT order
    np.savez(folder / "inputs.npz", params=params, scale=0.5,
             **{name: getattr(samples, name) for name in samples.__dataclass_fields__})


def _evaluate(folder: Path, name: str) -> dict[str, int]:
    """Run the kernel in a new process whose numba cache is ``folder/cache``; its cache hits and misses."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(folder / "cache")}
    done = subprocess.run([sys.executable, "-c", _EVALUATE, str(folder), name], env=env, check=True,
                          capture_output=True, text=True, timeout=1500)
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_a_compiled_and_a_cached_kernel_give_the_same_bits(tmp_path):
    _inputs(tmp_path)
    assert _evaluate(tmp_path, "compiled") == {"hits": 0, "misses": 1}
    assert _evaluate(tmp_path, "cached") == {"hits": 1, "misses": 0}
    with np.load(tmp_path / "compiled.npz") as compiled, np.load(tmp_path / "cached.npz") as cached:
        assert float(np.abs(compiled["grad"]).max()) > 0
        for name in ("loss", "grad", "terms"):
            np.testing.assert_array_equal(compiled[name], cached[name], err_msg=name)
