"""Diffusion-kernel export: loader round trip, the renderer's profile and energy, clustering, bad input."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from polarface.export import ExportOptions, ExportSource, load_kernels
from polarface.export.kernels import cluster_chromophores, composite_profile_weights
from polarface.io import write_png
from polarface.pipeline import export_result
from polarface.results.appearance import load_sog
from polarface.skin import layer_optics, layer_totals, render_layered_subsurface, subsurface_albedo


@pytest.fixture(scope="module")
def kernels_export(tiny_export, tmp_path_factory):
    """``(RESULT, kernels folder, record)`` of the tiny result's kernel export."""
    _, result = tiny_export
    out = tmp_path_factory.mktemp("kernels_export")
    summary = export_result(result, out, ExportOptions(formats=("kernels",)))
    return result, out / "kernels", summary["formats"]["kernels"]


def _spectral_inputs(result):
    payload = json.loads((result / "maps" / "sog.json").read_text())
    wavelengths = np.asarray(payload["wavelengths_nm"])
    calibration = ExportSource.open(result).rig.spectral.to_calibration().resampled(wavelengths)
    return payload, wavelengths, calibration


def test_loader_round_trip_and_every_masked_texel_has_a_cluster(kernels_export):
    result, folder, record = kernels_export
    kernels = load_kernels(folder / "kernels.npz")
    header = json.loads((folder / "kernels.json").read_text())
    assert header["format"] == "polarface-kernels" and record["clusters"] == len(header["clusters"])
    clusters, channels, gaussians = kernels.weights.shape
    assert (clusters, channels, gaussians) == (8, 6, 9)
    assert kernels.channel_names == tuple(header["channel_names"])
    np.testing.assert_allclose(kernels.variances_mm2, header["variances_mm2"])
    for k, entry in enumerate(header["clusters"]):
        for c, name in enumerate(kernels.channel_names):
            np.testing.assert_allclose(kernels.weights[k, c], entry["weights"][name])
        assert entry["texels"] == kernels.texel_counts[k]
    source = ExportSource.open(result)
    mask = source.mask
    assert kernels.cluster_map.dtype == np.int16 and kernels.cluster_map.shape == mask.shape
    assert (kernels.cluster_map[mask] >= 0).all() and (kernels.cluster_map[~mask] == -1).all()
    np.testing.assert_array_equal(np.bincount(kernels.cluster_map[mask]), kernels.texel_counts)
    chromophores = np.stack([source.scalar_map(n)[mask] for n in kernels.chromophore_names], -1)
    for k in range(clusters):  # centres are their members' means
        members = chromophores[kernels.cluster_map[mask] == k].astype(np.float64)
        np.testing.assert_allclose(kernels.centres[k], members.mean(0), rtol=1e-6, atol=1e-9)


def test_weights_integrate_to_the_skin_models_albedo(kernels_export):
    result, folder, record = kernels_export
    kernels = load_kernels(folder)
    _, wavelengths, calibration = _spectral_inputs(result)
    grid = torch.from_numpy(wavelengths)
    for k in range(len(kernels.centres)):
        params = [torch.tensor(float(v), dtype=torch.float64) for v in kernels.centres[k]]
        albedo = calibration.integrate(subsurface_albedo(*params, grid)).numpy()
        np.testing.assert_allclose(kernels.albedo[k], albedo, rtol=1e-9)
    assert record["max_fit_relative_error"] < 0.01


def test_kernel_reproduces_the_renderers_impulse_response(kernels_export):
    """An impulse through polarface's heterogeneous renderer with the centre's (homogeneous) totals."""
    result, folder, _ = kernels_export
    kernels = load_kernels(folder)
    payload, wavelengths, calibration = _spectral_inputs(result)
    shapes = load_sog(result / "maps" / "sog.json")
    centre = kernels.centres[0]
    size, texel = 241, 0.05  # mm per texel; +-6 mm
    params = [torch.tensor(float(v), dtype=torch.float64) for v in centre]
    totals = layer_totals(*layer_optics(*params, torch.from_numpy(wavelengths)))
    maps = tuple(t[:, None, None].expand(len(wavelengths), size, size).contiguous() for t in totals)
    impulse = torch.zeros(len(wavelengths), size, size, dtype=torch.float64)
    impulse[:, size // 2, size // 2] = 1.0
    spectral = render_layered_subsurface(impulse, maps, shapes, texel)
    rendered = calibration.integrate(spectral.permute(1, 2, 0)).numpy()  # (size, size, 6)
    np.testing.assert_allclose(rendered.sum((0, 1)), kernels.albedo[0], rtol=1e-4)
    exact_v, exact_w = composite_profile_weights(
        centre, shapes, wavelengths, calibration.weights.numpy(), np.asarray(payload["variances_mm2"])
    )
    radii_texels = np.array([20, 40, 80])
    r = radii_texels * texel
    along_row = rendered[size // 2, size // 2 + radii_texels].T / texel**2  # (6, R) mm^-2

    def composite(radii):
        return exact_w @ (np.exp(-radii[None] ** 2 / (2 * exact_v[:, None])) / (2 * np.pi * exact_v[:, None]))

    np.testing.assert_allclose(along_row, composite(r), rtol=0.02)
    near = np.array([0.25, 0.5, 1.0])  # the 9-Gaussian kernel where most energy lies
    np.testing.assert_allclose(kernels.profile(0, near), composite(near), rtol=0.03)


def test_clustering_is_deterministic_and_finds_separated_groups():
    rng = np.random.default_rng(3)
    centres = np.array([[0.02, 0.1, 0.01, 0.05], [0.2, 0.5, 0.05, 0.1], [0.05, 0.8, 0.2, 0.25]])
    sizes = (500, 300, 200)
    values = np.concatenate([c + 0.002 * rng.standard_normal((n, 4)) for c, n in zip(centres, sizes)])
    labels, found = cluster_chromophores(values, 3, seed=0)
    again, _ = cluster_chromophores(values, 3, seed=0)
    np.testing.assert_array_equal(labels, again)
    np.testing.assert_allclose(found, centres, atol=2e-3)  # ordered by size: 500, 300, 200
    np.testing.assert_array_equal(np.bincount(labels), [500, 300, 200])
    with pytest.raises(ValueError, match="'clusters'"):
        cluster_chromophores(values, 0)


def _minimal_copy(result, target):
    skipped = ("unwrap.zarr", "checkpoints", "previews", "frames", "tracking", "geometry")
    shutil.copytree(result, target, ignore=shutil.ignore_patterns(*skipped))
    return target


def test_malformed_sog_and_empty_mask_are_refused(tiny_export, tmp_path):
    _, result = tiny_export
    bad_sog = _minimal_copy(result, tmp_path / "sog")
    payload = json.loads((bad_sog / "maps" / "sog.json").read_text())
    payload["layers"]["t_out_b"] = [[1.0, 2.0]]
    (bad_sog / "maps" / "sog.json").write_text(json.dumps(payload))
    with pytest.raises(ValueError, match=r"sog\.json"):
        export_result(bad_sog, tmp_path / "out1", ExportOptions(formats=("kernels",)))
    empty = _minimal_copy(result, tmp_path / "empty")
    shape = ExportSource.open(empty).mask.shape
    write_png(empty / "maps" / "mask.png", np.zeros(shape, np.uint8))
    with pytest.raises(ValueError, match=r"mask\.png' has no valid texel"):
        export_result(empty, tmp_path / "out2", ExportOptions(formats=("kernels",)))
