"""The static polarimetric fit's patch loop as it was before the patches became executor units (the
row-major loop of ``polarface.inverse.polarimetric.fit`` up to commit 96424f7): the reference that the
wavefront schedule must reproduce bit for bit (importable: ``tests`` is on pytest's ``pythonpath``).

Patches run one after the other in row-major order and read and write one shared state in place (the
haloed region's tensors share memory with it), as the old loop did; fused engine on the CPU, float32. One
change since: the closed-form starts are those of the fused engine (on its fused samples), as in the fit;
the store is read uncached (the fit reads through a chunk cache).
"""

from __future__ import annotations

import numpy as np
import torch

from polarface.inverse.polarimetric import PolarimetricConfig, initial_raw
from polarface.inverse.polarimetric.config import fit_maps_from_raw
from polarface.inverse.polarimetric.fit import haloed_slices, torch_fit_settings
from polarface.inverse.polarimetric.init import apply_closed_form_starts
from polarface.inverse.polarimetric.optimise import optimise_patch
from polarface.inverse.polarimetric.patch_units import patch_side
from polarface.inverse.polarimetric.problem import PatchProblem, build_patch_samples
from polarface.texture import UnwrapStore

__all__ = ["row_major_fit", "sphere_unwrap"]


def sphere_unwrap(root, resolution: int, patch: int) -> UnwrapStore:
    """The synthetic sphere capture (4 frames) in ``root/sim``, unwrapped on its true geometry into
    ``root/unwrap.zarr`` with a ``resolution``-texel atlas and ``patch``-texel unwrap chunks."""
    from polarface.capture.store import CaptureStore
    from polarface.geometry.mesh import load_mesh
    from polarface.geometry.poses import load_poses
    from polarface.simulate.sphere_capture import SphereCaptureConfig, make_sphere_capture
    from polarface.texture import UnwrapConfig, unwrap_capture

    make_sphere_capture(root / "sim", SphereCaptureConfig(texture_resolution=resolution, frames=4))
    truth = root / "sim" / "ground_truth"
    return unwrap_capture(
        CaptureStore.open(root / "sim" / "static"), load_mesh(truth / "mesh_rest.obj"),
        load_poses(truth / "static" / "poses.json"), root / "unwrap.zarr",
        UnwrapConfig(texture_resolution=resolution, patch=patch), progress=False,
    )


def _fit_patch(unwrap, rows, cols, fitting, views, config, scale, raw, initialised, curve) -> None:
    """One patch of the old loop, in place on ``raw`` and ``initialised``."""
    dtype, device = torch.float32, torch.device("cpu")
    hrows, hcols, (ir, ic) = haloed_slices(rows, cols, config.halo, unwrap.resolution)
    batch, geometry, fused = build_patch_samples(unwrap, hrows, hcols, fitting, views, dtype=dtype,
                                                 device=device, fused=True)
    if batch is None:
        return
    problem = PatchProblem(batch, geometry, config, scale, dtype, device, fused)
    patch_raw = {k: torch.as_tensor(v[hrows, hcols], dtype=dtype, device=device) for k, v in raw.items()}
    todo = ~initialised[hrows, hcols]
    if todo.any():
        apply_closed_form_starts(fused, patch_raw, todo, problem.normals, config, dtype, device)
    problem.batch = None
    result = optimise_patch(problem, patch_raw, config, curve)
    for k, v in result.items():
        raw[k][rows, cols] = v[ir, ic].numpy()
    if todo.any():
        for k in ("rho_sss_bar", "rho_s", "eta", "alpha_s"):
            fresh = patch_raw[k].numpy()
            region = raw[k][hrows, hcols]
            region[todo] = fresh[todo]
            raw[k][rows, cols] = result[k][ir, ic].numpy()
        initialised[hrows, hcols] = True


def row_major_fit(unwrap: UnwrapStore, config: PolarimetricConfig
                  ) -> tuple[dict[str, np.ndarray], list[float]]:
    """``(maps, mean loss curve)`` of the row-major loop (one torch thread; without lobe refinement)."""
    assert config.refine_lobes_iterations == 0
    views = unwrap.views
    fitting = [i for i, v in enumerate(views) if not v.held_out]
    scale = unwrap.mean_i_sss(fitting)
    patches = list(unwrap.patches(patch_side(unwrap.visible_count(), config)))
    raw = initial_raw(unwrap.resolution, config)
    initialised = np.zeros(unwrap.resolution, bool)
    curve: list[float] = []
    with torch_fit_settings(1):
        torch.manual_seed(config.seed)
        for rows, cols in patches:
            _fit_patch(unwrap, rows, cols, fitting, views, config, scale, raw, initialised, curve)
        maps = fit_maps_from_raw(raw, config)
    return maps, [v / len(patches) for v in curve]
