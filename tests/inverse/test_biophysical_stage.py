"""Tests of the biophysical stage on RESULT folders, its evaluation, report section and CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from polarface.capture.rig import paper_rig
from polarface.cli import main
from polarface.geometry.mesh import TriangleMesh, save_obj
from polarface.inverse.biophysical import BiophysicalConfig
from polarface.inverse.biophysical_model import TotalsTable, local_channel_albedo
from polarface.inverse.biophysical_stage import (
    evaluate_biophysical,
    load_sog,
    report_section,
    run_biophysical_stage,
)
from polarface.io import read_exr, write_exr, write_png
from polarface.report.html import HtmlPage

RESOLUTION = 32


def plane_mesh(size_mm: float = 60.0, cells: int = 8) -> TriangleMesh:
    """A 60 mm square in the model frame (face towards +z at z = 90 mm) with UVs over [0, 1]^2."""
    u = np.linspace(0.0, 1.0, cells + 1)
    uu, vv = np.meshgrid(u, u, indexing="xy")
    vertices = np.stack([(uu - 0.5) * size_mm, (vv - 0.5) * size_mm, np.full_like(uu, 90.0)], -1).reshape(
        -1, 3
    )
    uv = np.stack([uu, vv], -1).reshape(-1, 2)
    faces = []
    for row in range(cells):
        for col in range(cells):
            a = row * (cells + 1) + col
            faces += [(a, a + 1, a + cells + 2), (a, a + cells + 2, a + cells + 1)]
    return TriangleMesh.from_arrays(vertices, np.array(faces), uv)


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
    for name in ("c_m", "chromophores", "subsurface_srgb"):
        assert (result / "previews" / f"{name}.png").is_file()
    data = json.loads((result / "result.json").read_text())
    assert data["stages"]["biophysical"]["albedo_model"] == "local"
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
    assert metrics["c_m"]["median_abs"] < 1e-4
    assert metrics["c_h_out"]["median_abs"] < 1e-4
    assert metrics["c_h_in"]["median_abs"] < 1e-4
    assert metrics["beta_m"]["median_abs"] < 1e-3
    assert metrics["rho_sss_bar_relative_rmse"] < 1e-3
    assert metrics["fit_relative_rmse"] < 1e-3


def test_report_section(fitted_result, tmp_path):
    result, _ = fitted_result
    page = HtmlPage("test")
    report_section(page, result, evaluate_biophysical(result, result.parent / "gt"))
    html = page.render()
    assert "previews/c_m.png" in html and "Biophysical" in html and "median |error|" in html


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
    assert output["metrics"]["c_m"]["median_abs"] < 1e-4


def test_cli_biophysical_bad_input_exit_code(tmp_path, capsys):
    result = make_result(tmp_path, rho_scale=4.0)
    assert main(["biophysical", str(result), "--no-progress"]) == 2
    assert "rho_sss_bar" in capsys.readouterr().err
