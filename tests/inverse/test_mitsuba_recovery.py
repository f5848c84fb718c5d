"""Recovery on a capture whose radiance comes from Mitsuba 3, not from polarface (docs/mitsuba_captures.md).

The simulator and the inverse stage share polarface's optics, so a mistake in both would pass every
simulator round trip. Here Mitsuba's ``pplastic`` (the paper's model with ``rho_ss = 0``) renders a
tiny static capture of the simulator's head and rig (family A: textured ``rho_s`` and six-channel
``rho_sss_bar``, constant eta 1.44 and alpha_s 0.35; 4 frames, 256 x 212 px, 128^2 atlas, noise-free
apart from 12-bit quantisation), which goes through the real pipeline (capture store with demosaicing,
known-geometry ``reconstruct``, ``evaluate``).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mitsuba_capture import family_a, validate_against_polarface, write_mitsuba_capture
from polarface.io import read_exr, read_png
from polarface.pipeline import reconstruct, resolve_reconstruct_inputs
from polarface.pipeline.evaluate import evaluate

TEXTURE_RESOLUTION = 128
CONFIG = family_a(texture_resolution=TEXTURE_RESOLUTION)


def _recover(capture, tmp_path_factory):
    """``(maps, mask, metrics)`` of the default known-geometry reconstruction of ``capture`` (~7 s)."""
    gt = capture / "ground_truth"
    inputs = resolve_reconstruct_inputs(
        capture / "static",
        mesh=gt / "mesh_rest.obj",
        poses=gt / "static" / "poses.json",
        texture_resolution=TEXTURE_RESOLUTION,
    )
    result = tmp_path_factory.mktemp("mitsuba_result") / "result"
    reconstruct(inputs, result, device="cpu", threads=1, progress=False)
    maps = {name: read_exr(result / "maps" / f"{name}.exr")["Y"] for name in ("eta", "alpha_s", "rho_ss")}
    mask = read_png(result / "maps" / "mask.png") > 0
    mask = mask if mask.ndim == 2 else mask[..., 0]
    return maps, mask, evaluate(result, capture, groups=["polarimetric"])["polarimetric"]


@pytest.fixture(scope="module")
def recovered(tmp_path_factory):
    """Recovery on the family-A capture rendered by Mitsuba (about 35 s of rendering on one core)."""
    root = tmp_path_factory.mktemp("mitsuba") / "capture"
    write_mitsuba_capture(root, CONFIG)
    return _recover(root, tmp_path_factory)


@pytest.fixture(scope="module")
def recovered_control(tmp_path_factory):
    """Recovery on the identical scene rendered by polarface's image formation (the control)."""
    root = tmp_path_factory.mktemp("control") / "capture"
    write_mitsuba_capture(root, dataclasses.replace(CONFIG, renderer="polarface"))
    return _recover(root, tmp_path_factory)


@pytest.mark.slow
def test_mitsuba_frame_matches_polarface_image_formation():
    """Frame 0 from Mitsuba equals polarface's image formation evaluated at the same hit points.

    Measured (tiny preset, both cameras, four analyzers): median relative difference 6e-7 (float32),
    relative L2 3.7e-3 and 0.4 % of the values above 1e-3. The large differences sit entirely on the
    ~0.5 % of pixels where Mitsuba's and Embree's shadow rays disagree at grazing shadow edges (over the
    other pixels the relative L2 is 1.8e-6 and the largest relative difference 4.4e-4). Bounds: 10x the
    float32 median, 1 % of values, relative L2 1e-2.
    """
    report = validate_against_polarface(CONFIG)
    local = report["local"]
    assert local["mask_mismatch"] == 0
    assert local["median_relative"] < 1e-5, report
    assert local["fraction_above_1e-3"] < 0.01, report
    assert local["relative_l2"] < 1e-2, report


@pytest.mark.slow
def test_family_a_eta_is_unbiased(recovered):
    """Issue target: |median eta bias| <= 0.002 on a noise-free capture (truth: 1.44 everywhere)."""
    maps, mask, metrics = recovered
    bias = float(np.median(maps["eta"][mask])) - CONFIG.eta
    assert abs(bias) <= 0.002, (bias, metrics["eta"])
    assert metrics["eta"]["median_abs_error"] <= 0.02, metrics["eta"]


@pytest.mark.slow
def test_family_a_lobes_and_albedo(recovered):
    """Issue targets: alpha_s median |error| <= 0.05, rho_s median relative error <= 15 %, rho_ss
    median <= 0.03 (truth 0: pplastic has no single-scattering lobe); rho_sss_bar median relative
    error <= 3 %."""
    maps, mask, metrics = recovered
    assert metrics["alpha_s"]["median_abs_error"] <= 0.05, metrics["alpha_s"]
    assert metrics["rho_s"]["median_relative_error"] <= 0.15, metrics["rho_s"]
    assert float(np.median(maps["rho_ss"][mask])) <= 0.03, metrics["rho_ss"]
    assert metrics["rho_sss_bar"]["median_relative_error"] <= 0.03, metrics["rho_sss_bar"]


@pytest.mark.slow
def test_recovery_does_not_depend_on_the_renderer(recovered, recovered_control):
    """The Mitsuba capture and the polarface control of the same scene give the same recovery: what the
    inverse gets wrong is its own, not a convention shared with polarface's renderer.

    Measured with the optimiser of this commit: eta bias -0.0275 (Mitsuba) vs -0.0264 (control),
    rho_sss_bar median relative error 0.0152 vs 0.0149, rho_ss median 0.224 vs 0.220. Bounds: 0.005 on
    the eta bias, 0.005 on the albedo error, 0.02 on the rho_ss median (a few times the measured gaps,
    far below the errors a frame or Fresnel convention mistake causes: a swapped analyzer pair or an
    exit Fresnel factor off by T+ moves eta by > 0.1).
    """
    (maps, mask, metrics), (maps_c, mask_c, metrics_c) = recovered, recovered_control
    bias = float(np.median(maps["eta"][mask])) - float(np.median(maps_c["eta"][mask_c]))
    assert abs(bias) <= 0.005, bias
    albedo = (
        metrics["rho_sss_bar"]["median_relative_error"] - metrics_c["rho_sss_bar"]["median_relative_error"]
    )
    assert abs(albedo) <= 0.005, albedo
    rho_ss = float(np.median(maps["rho_ss"][mask])) - float(np.median(maps_c["rho_ss"][mask_c]))
    assert abs(rho_ss) <= 0.02, rho_ss
