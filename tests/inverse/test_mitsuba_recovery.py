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

from mitsuba_capture import family_a, write_mitsuba_capture
from mitsuba_reference import validate_against_polarface
from polarface.evaluate import evaluate
from polarface.io import read_exr, read_png
from polarface.pipeline import reconstruct, resolve_reconstruct_inputs

TEXTURE_RESOLUTION = 128
CONFIG = family_a(texture_resolution=TEXTURE_RESOLUTION)


def _recover(capture, tmp_path_factory, **fit_options):
    """``(maps, mask, metrics)`` of the known-geometry reconstruction of ``capture`` (~15 s)."""
    gt = capture / "ground_truth"
    inputs = resolve_reconstruct_inputs(
        capture / "static",
        mesh=gt / "mesh_rest.obj",
        poses=gt / "static" / "poses.json",
        texture_resolution=TEXTURE_RESOLUTION,
    )
    result = tmp_path_factory.mktemp("mitsuba_result") / "result"
    reconstruct(inputs, result, device="cpu", threads=1, progress=False, fit_options=fit_options)
    maps = {name: read_exr(result / "maps" / f"{name}.exr")["Y"] for name in ("eta", "rho_ss")}
    mask = read_png(result / "maps" / "mask.png") > 0
    mask = mask if mask.ndim == 2 else mask[..., 0]
    metrics = evaluate(result, capture, groups=["polarimetric"])["polarimetric"]
    return maps, mask, metrics


@pytest.fixture(scope="module")
def mitsuba_capture(tmp_path_factory):
    """The family-A capture rendered by Mitsuba (about 45 s of rendering on one core)."""
    root = tmp_path_factory.mktemp("mitsuba") / "capture"
    write_mitsuba_capture(root, CONFIG)
    return root


@pytest.fixture(scope="module")
def recovered(mitsuba_capture, tmp_path_factory):
    """Default (two-lobe) recovery on the Mitsuba capture."""
    return _recover(mitsuba_capture, tmp_path_factory)


@pytest.fixture(scope="module")
def recovered_one_lobe(mitsuba_capture, tmp_path_factory):
    """Recovery with ``lobes="one"`` (rho_ss = 0, the model pplastic renders)."""
    return _recover(mitsuba_capture, tmp_path_factory, lobes="one")


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
def test_one_lobe_recovers_the_specular_lobe(recovered_one_lobe):
    """Issue 16 targets on a capture with rho_ss = 0, fitted with the model it was rendered with
    (``lobes="one"``): alpha_s median |error| <= 0.05, rho_s median relative error <= 15 %, rho_ss
    median <= 0.03; rho_sss_bar <= 3 %. Measured: 0.024, 12.4 %, 0, 1.4 %.

    eta: the tiny capture's 256 x 212 images give each texel a footprint of several surface points
    whose Stokes vectors average to a lower degree of polarization than the point model predicts (2.2 %
    lower at the truth, against 0.3 % at the demo's resolution; docs/mitsuba_captures.md), so eta comes
    out low by about 0.025 here (the polarface control alike); the issue's 0.002 holds at the demo's
    resolution (docs/mitsuba_captures.md). Bound: 0.035 (a Fresnel or frame error moves it by > 0.1).
    """
    maps, mask, metrics = recovered_one_lobe
    assert metrics["alpha_s"]["median_abs_error"] <= 0.05, metrics["alpha_s"]
    assert metrics["rho_s"]["median_relative_error"] <= 0.15, metrics["rho_s"]
    assert float(np.median(maps["rho_ss"][mask])) <= 0.03, metrics["rho_ss"]
    assert metrics["rho_sss_bar"]["median_relative_error"] <= 0.03, metrics["rho_sss_bar"]
    bias = float(np.median(maps["eta"][mask])) - CONFIG.eta
    assert abs(bias) <= 0.035, (bias, metrics["eta"])


@pytest.mark.slow
def test_recovery_does_not_depend_on_the_renderer(recovered, recovered_control):
    """The Mitsuba capture and the polarface control of the same scene give the same recovery: what the
    inverse gets wrong is its own, not a convention shared with polarface's renderer.

    Measured (default L-BFGS, two lobes): eta bias -0.041 (Mitsuba) vs -0.039 (control), rho_sss_bar
    median relative error 0.0170 vs 0.0169, rho_ss median 0.212 vs 0.212. Bounds: 0.005 on
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
