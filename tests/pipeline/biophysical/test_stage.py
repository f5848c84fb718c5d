"""Tests of the biophysical stage on RESULT folders, its evaluation, report section and CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from disk_fixtures import plane_mesh
from polarface.capture.rig import paper_rig
from polarface.cli import main
from polarface.evaluate import evaluate_biophysical
from polarface.geometry.mesh import save_obj
from polarface.inverse.biophysical import (
    BiophysicalConfig,
    TotalsTable,
    local_channel_albedo,
    per_texel_relative_residual,
)
from polarface.io import read_exr, read_png, write_exr, write_png
from polarface.pipeline import run_biophysical_stage
from polarface.report import HtmlPage, biophysical_section
from polarface.results import load_sog

RESOLUTION = 32


def truth_maps(resolution: int = RESOLUTION) -> dict[str, np.ndarray]:
    y, x = np.meshgrid(np.linspace(0, 1, resolution), np.linspace(0, 1, resolution), indexing="ij")
    return {
        "c_m": (0.03 + 0.06 * x).astype(np.float32),
        "beta_m": (0.05 + 0.15 * y).astype(np.float32),
        "c_h_in": (0.02 + 0.03 * x * y).astype(np.float32),
        "c_h_out": (0.03 + 0.08 * (1 - x) * y).astype(np.float32),
    }


def make_result(root: Path, *, spectral: bool = True, rho_scale: float = 1.0) -> Path:
    """A RESULT folder of a plane with known chromophores (local rho_sss_bar) and a GT folder beside it."""
    rig = paper_rig(width=96, height=80)
    calibration = rig.spectral.to_calibration()
    maps = truth_maps()
    params = torch.from_numpy(
        np.stack([maps[k] for k in ("c_m", "beta_m", "c_h_in", "c_h_out")], -1)
    ).double()
    rho = local_channel_albedo(params, TotalsTable(calibration.wavelengths_nm), calibration.weights).numpy()
    rho = (rho * rho_scale).astype(np.float32)
    names = list(calibration.channel_names)
    mask = np.ones((RESOLUTION, RESOLUTION), np.uint8) * 255
    for folder in (root / "result" / "maps", root / "gt" / "maps"):
        write_exr(folder / "rho_sss_bar.exr", {n: rho[..., i] for i, n in enumerate(names)})
        write_png(folder / "mask.png", mask)
    for name, values in maps.items():
        write_exr(root / "gt" / "maps" / f"{name}.exr", {"Y": values})
    polarimetric = {
        "eta": 1.42,
        "alpha_s": 0.5,
        "alpha_ss": 0.95,
        "rho_s": 0.5,
        "rho_ss": 0.25,
        "displacement_mm": 0.0,
    }
    for name, value in polarimetric.items():
        write_exr(
            root / "result" / "maps" / f"{name}.exr",
            {"Y": np.full((RESOLUTION, RESOLUTION), value, np.float32)},
        )
    save_obj(root / "result" / "mesh.obj", plane_mesh())
    if not spectral:
        rig = rig.model_copy(update={"spectral": None})
    rig.save(root / "result" / "rig.json")
    return root / "result"


@pytest.fixture(scope="module")
def fitted_result(tmp_path_factory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("bio_stage")
    result = make_result(root)
    summary = run_biophysical_stage(
        result,
        BiophysicalConfig(albedo_model="local", coarse_factor=4, prior_weight=(0.0, 0.0, 0.0, 0.0)),
        progress=False,
    )
    return result, summary


def test_stage_writes_outputs(fitted_result):
    result, summary = fitted_result
    for name in ("c_m", "beta_m", "c_h_in", "c_h_out", "rho_sss_bar_rendered", "subsurface_spectral"):
        assert (result / "maps" / f"{name}.exr").is_file()
    for name in ("c_m", "chromophores", "subsurface_srgb", "rho_sss_bar_residual", "in_gamut"):
        assert (result / "previews" / f"{name}.png").is_file()
    # the panel is the four chromophore previews side by side, pixel for pixel
    maps = [read_png(result / "previews" / f"{name}.png") for name in ("c_m", "beta_m", "c_h_in", "c_h_out")]
    panel = read_png(result / "previews" / "chromophores.png")
    np.testing.assert_array_equal(panel, np.concatenate(maps, axis=1))
    residual = read_exr(result / "maps" / "rho_sss_bar_residual.exr")
    assert set(residual) == {"relative", "gamut_distance"} and residual["relative"].shape == (32, 32)
    assert float(residual["gamut_distance"].max()) < 1e-3
    assert bool((read_png(result / "maps" / "in_gamut.png") > 127).all())
    data = json.loads((result / "result.json").read_text())
    assert data["stages"]["biophysical"]["albedo_model"] == "local"
    assert summary["out_of_gamut_texels"] == 0 and summary["texels"] == RESOLUTION * RESOLUTION
    assert summary["gamut_floor_relative_rmse"] < 1e-4
    assert summary["torch_threads"] == 1  # the default for CPU fits


def test_stage_threads_checked_and_restored(tmp_path):
    result = make_result(tmp_path)
    with pytest.raises(ValueError, match="threads"):
        run_biophysical_stage(result, threads=0, progress=False)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        summary = run_biophysical_stage(
            result, BiophysicalConfig(albedo_model="local", coarse_factor=4), progress=False
        )
        assert summary["torch_threads"] == 1 and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert summary["timings_s"]["total_s"] > 0
    assert summary["texel_size_mm"] == pytest.approx(60.0 / RESOLUTION, rel=0.05)  # from the mesh
    spectral = read_exr(result / "maps" / "subsurface_spectral.exr")
    assert len(spectral) == 15 and "nm420" in spectral
    shapes = load_sog(result / "maps" / "sog.json")
    assert shapes.r_out_f.shape == (15, 9)
    assert torch.allclose(shapes.t_out_b.sum(-1), torch.ones(15, dtype=torch.float64), atol=1e-9)


def test_stage_recovers_truth(fitted_result):
    result, _ = fitted_result
    metrics = evaluate_biophysical(result, result.parent / "gt")
    assert metrics["texels"] == RESOLUTION * RESOLUTION
    assert metrics["c_m"]["median_abs_error"] < 1e-4
    assert metrics["c_h_out"]["median_abs_error"] < 1e-4
    assert metrics["c_h_in"]["median_abs_error"] < 1e-4
    assert metrics["beta_m"]["median_abs_error"] < 1e-3
    assert metrics["rho_sss_bar_relative_rmse"] < 1e-3
    assert "fit_relative_rmse" not in metrics  # one name per value
    assert metrics["rerender_vs_gt_relative_rmse"] < 1e-3
    assert metrics["input_vs_gt_relative_rmse"] == 0.0  # the input is the ground truth
    assert metrics["out_of_gamut_texels"] == 0


def test_per_texel_relative_residual():
    observed = np.full((2, 3, 6), 0.2, np.float32)
    rendered = observed * np.array([1.0, 1.1, 0.5], np.float32)[None, :, None]
    mask = np.array([[True, True, True], [True, True, False]])
    residual = per_texel_relative_residual(rendered, observed, mask)
    assert residual.shape == (2, 3) and residual.dtype == np.float32
    assert np.allclose(residual[0], [0.0, 0.1, 0.5], atol=1e-6) and residual[1, 2] == 0.0


@pytest.mark.slow
def test_stage_with_saturated_texels_reports_them_and_counts_them(tmp_path):
    """A 3x3 block of the input stuck at rho = 0.99 (a failed polarimetric fit): the stage flags exactly
    it as out of gamut, keeps it in the all-texel metric and reports the in-gamut one beside it."""
    result = make_result(tmp_path)
    path = result / "maps" / "rho_sss_bar.exr"
    channels = read_exr(path)
    for values in channels.values():
        values[10:13, 20:23] = 0.99
    write_exr(path, channels)
    summary = run_biophysical_stage(
        result, BiophysicalConfig(albedo_model="local", coarse_factor=4), progress=False
    )
    in_gamut = read_png(result / "maps" / "in_gamut.png") > 127
    expected = np.ones((RESOLUTION, RESOLUTION), bool)
    expected[10:13, 20:23] = False
    assert np.array_equal(in_gamut, expected)
    assert summary["out_of_gamut_texels"] == 9
    metrics = evaluate_biophysical(result, result.parent / "gt")
    names = list(paper_rig(width=96, height=80).spectral.to_calibration().channel_names)
    rendered = np.stack([read_exr(result / "maps" / "rho_sss_bar_rendered.exr")[n] for n in names], -1)
    observed = np.stack([channels[n] for n in names], -1)
    by_hand = np.sqrt(np.mean((rendered - observed) ** 2)) / np.sqrt(np.mean(observed**2))
    assert metrics["rho_sss_bar_relative_rmse"] == pytest.approx(by_hand, rel=1e-5)  # over all texels
    assert metrics["rho_sss_bar_relative_rmse"] > 0.1
    assert metrics["rho_sss_bar_relative_rmse_in_gamut"] < 1e-3
    assert 0.1 < metrics["gamut_floor_relative_rmse"] <= metrics["rho_sss_bar_relative_rmse"] + 1e-6
    assert metrics["input_vs_gt_relative_rmse"] > 0.1 and metrics["out_of_gamut_texels"] == 9
    # The chromophores around the block are not pulled towards the saturated values.
    truth = truth_maps()
    around = ~expected.copy()
    around[8:15, 18:25] = True
    around &= expected
    c_m = read_exr(result / "maps" / "c_m.exr")["Y"]
    assert np.abs(c_m[around] - truth["c_m"][around]).max() < 2e-3
    residual = read_exr(result / "maps" / "rho_sss_bar_residual.exr")["relative"]
    assert residual[~expected].min() > 0.3 and residual[expected].max() < 0.01


def test_report_section(fitted_result, tmp_path):
    result, _ = fitted_result
    page = HtmlPage("test")
    biophysical_section(page, result, evaluate_biophysical(result, result.parent / "gt"))
    html = page.render()
    assert "previews/c_m.png" in html and "Biophysical" in html and "median |error|" in html
    assert "skin gamut" in html and "rerender_vs_gt_relative_rmse" in html
    assert "previews/rho_sss_bar_residual.png" in html


def test_missing_spectral_calibration(tmp_path):
    result = make_result(tmp_path, spectral=False)
    with pytest.raises(ValueError, match="spectral calibration"):
        run_biophysical_stage(result, progress=False)


def test_rho_outside_unit_interval(tmp_path):
    result = make_result(tmp_path, rho_scale=4.0)
    with pytest.raises(ValueError, match=r"rho_sss_bar must lie in \[0, 1\]"):
        run_biophysical_stage(result, progress=False)


def test_missing_inputs(tmp_path):
    with pytest.raises(FileNotFoundError):
        run_biophysical_stage(tmp_path / "nope", progress=False)
    result = make_result(tmp_path)
    (result / "maps" / "rho_sss_bar.exr").unlink()
    with pytest.raises(FileNotFoundError, match="polarimetric stage"):
        run_biophysical_stage(result, progress=False)


def test_cli_biophysical(tmp_path, capsys):
    result = make_result(tmp_path)
    code = main(
        [
            "biophysical",
            str(result),
            "--local",
            "--coarse-factor",
            "4",
            "--no-progress",
            "--no-prior",
            "--gt",
            str(tmp_path / "gt"),
        ]
    )
    assert code == 0
    output = json.loads(capsys.readouterr().out)
    assert output["metrics"]["c_m"]["median_abs_error"] < 1e-4


def test_cli_biophysical_bad_input_exit_code(tmp_path, capsys):
    result = make_result(tmp_path, rho_scale=4.0)
    assert main(["biophysical", str(result), "--no-progress"]) == 2
    assert "rho_sss_bar" in capsys.readouterr().err


def test_reconstruct_stage_gives_the_fit_the_idle_worker_processes_threads(tmp_path):
    """In ``reconstruct`` with worker processes (``--executor processes``) the biophysical fit, which runs
    in the main process while the workers idle, takes all their threads; otherwise ``--threads``."""
    from polarface.executors import ProcessExecutor
    from polarface.pipeline.reconstruct import ReconstructContext
    from polarface.pipeline.reconstruct.stages import stage_biophysical

    result = make_result(tmp_path)
    context = ReconstructContext(capture=tmp_path, out=result, mesh_path=result / "mesh.obj",
                                 poses_path=tmp_path / "poses.json", texture_resolution=RESOLUTION,
                                 device="cpu", resume=False, progress=False, holdout_every=0,
                                 executor=ProcessExecutor(workers=2, threads_per_worker=1))
    before = torch.get_num_threads()
    assert stage_biophysical(context)["torch_threads"] == 2
    assert torch.get_num_threads() == before
    context.executor = None
    assert stage_biophysical(context)["torch_threads"] == 1
