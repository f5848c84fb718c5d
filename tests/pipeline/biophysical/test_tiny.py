"""End-to-end on the simulator's tiny preset: noise-free recovery and re-render at a training view."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from polarface.evaluate import evaluate_biophysical
from polarface.geometry.mesh import save_obj
from polarface.inverse.biophysical import BiophysicalConfig
from polarface.io import write_exr, write_png
from polarface.pipeline import run_biophysical_stage
from polarface.render.relight import render_result_view
from polarface.results import ResultAppearance
from polarface.simulate.pipeline import SimulationConfig, SimulationScene, render_frame
from polarface.simulate.sequences import static_poses


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The tiny scene's ground truth written as SIM/ground_truth and as a RESULT (perfect stage 1)."""
    scene = SimulationScene.build(SimulationConfig(preset="tiny", skin_type="II", noise=False))
    root = tmp_path_factory.mktemp("tiny")
    names = list(scene.calibration.channel_names)
    gt = root / "ground_truth" / "maps"
    for name, values in scene.maps.scalar_maps().items():
        write_exr(gt / f"{name}.exr", {"Y": values})
    write_exr(gt / "rho_sss_bar.exr", {n: scene.maps.rho_sss_bar[..., i] for i, n in enumerate(names)})
    write_png(gt / "mask.png", scene.maps.mask.astype(np.uint8) * 255)
    result = root / "result"
    (result / "maps").mkdir(parents=True)
    for name in ("eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss", "displacement_mm", "rho_sss_bar"):
        shutil.copy(gt / f"{name}.exr", result / "maps" / f"{name}.exr")
    shutil.copy(gt / "mask.png", result / "maps" / "mask.png")
    save_obj(result / "mesh.obj", scene.asset.mesh)
    scene.rig.save(result / "rig.json")
    summary = run_biophysical_stage(
        result, BiophysicalConfig(albedo_model="local", prior_weight=(0.0, 0.0, 0.0, 0.0)), progress=False
    )
    return scene, root, result, summary


@pytest.mark.slow
def test_noise_free_recovery_on_tiny(tiny):
    _, root, result, summary = tiny
    metrics = evaluate_biophysical(result, root)
    assert metrics["c_m"]["median_abs_error"] < 1e-4
    assert metrics["c_h_out"]["median_abs_error"] < 1e-4
    assert metrics["c_h_in"]["median_abs_error"] < 1e-4
    assert metrics["beta_m"]["median_abs_error"] < 1e-3
    assert metrics["rho_sss_bar_relative_rmse"] < 1e-3
    assert metrics["rerender_vs_gt_relative_rmse"] < 1e-3
    assert summary["rho_sss_bar_relative_rmse"] < 1e-3
    assert summary["out_of_gamut_texels"] == 0  # the simulator's skin is inside the model's gamut


@pytest.mark.slow
def test_render_matches_observation_at_training_view(tiny):
    """The reconstructed maps rendered at static frame 0 reproduce the simulator's noise-free images."""
    scene, _, result, _ = tiny
    pose = static_poses(scene)[0]
    frame = render_frame(scene, scene.asset.mesh.transformed(pose), scene.maps, scene.subsurface)
    camera = scene.rig.polarimetric_cameras()[0]
    observed = frame.views[camera.id]
    rendered = render_result_view(ResultAppearance.load(result), camera.id, pose)
    channels = [camera.colour_channels[c] for c in "RGB"]
    both = observed.mask & rendered.mask
    assert both.sum() > 0.95 * observed.mask.sum()
    for name in ("i0", "i90", "i45"):
        reference = observed.images[name][both]
        estimate = rendered.images[name][..., channels][both]
        relative = np.sqrt(np.mean((estimate - reference) ** 2)) / np.sqrt(np.mean(reference**2))
        assert relative < 0.02, (name, relative)
    # the total intensity alone (polarization=False, as the dynamic stage renders its frames): the same
    # pixels, s0 = I0 + I90 to float32 rounding, from the first row of the Mueller chain only
    total = render_result_view(ResultAppearance.load(result), camera.id, pose, polarization=False)
    assert set(total.images) == {"s0"} and np.array_equal(total.mask, rendered.mask)
    summed = rendered.images["i0"] + rendered.images["i90"]
    assert np.allclose(total.images["s0"], summed, rtol=1e-5, atol=1e-6 * float(summed.max()))
