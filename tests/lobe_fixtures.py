"""Random fragments, lights and visibility for the lobe tests (tests/optics/test_lobes.py,
tests/render/test_lobe_kernel.py)."""

from __future__ import annotations

import numpy as np
import torch


def lobe_fragments(dtype, count=600, seed=0):
    """``(geometry, params, lights (5, 3), visible (N, 5), start Stokes (N, 3, 4))`` of ``count`` random
    fragments about 1 m in front of a camera at the origin, some facing away from lights or camera."""
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=(count, 3)) + np.array([0.0, 0.0, -1.2])  # some face away from lights/camera
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    position = rng.uniform(-60, 60, size=(count, 3)) + np.array([0.0, 0.0, 1000.0])
    column = lambda low, high: torch.from_numpy(rng.uniform(low, high, (count, 1))).to(dtype)  # noqa: E731
    params = {"eta": column(1.3, 1.5), "alpha_s": column(0.1, 0.5), "alpha_ss": column(0.2, 0.9),
              "rho_s": column(0.0, 1.0), "rho_ss": column(0.0, 1.0)}
    lights = rng.uniform(-400, 400, size=(5, 3)) * np.array([1.0, 1.0, 0.0]) + np.array([0.0, 0.0, 50.0])
    visible = rng.random((count, 5)) < 0.8
    start = torch.from_numpy(rng.random((count, 3, 4))).to(dtype)
    geometry = {
        "normal": torch.from_numpy(normal).to(dtype),
        "position": torch.from_numpy(position).to(dtype),
        "camera_center": torch.zeros(3, dtype=dtype),
        "camera_up": torch.tensor([0.0, -1.0, 0.0], dtype=dtype),
    }
    return geometry, params, lights, visible, start
