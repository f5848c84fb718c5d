"""End to end: reconstruct -> evaluate on a synthetic capture; resume; bad input; bench smoke."""

from __future__ import annotations

import importlib
import json
import shutil

import numpy as np
import pytest
import torch
from scipy import ndimage

from polarface.cli import main
from polarface.geometry.mesh import TriangleMesh, load_mesh, save_obj
from polarface.io import read_exr, read_png
from polarface.pipeline import ReconstructContext, run_stages
from polarface.simulate.sphere_capture import SphereCaptureConfig, make_sphere_capture

RES = 16


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    root = tmp_path_factory.mktemp("sim")
    make_sphere_capture(root, SphereCaptureConfig(texture_resolution=RES, frames=4))
    return root


def _args(sim, out, *extra):
    return [
        "reconstruct",
        str(sim / "static"),
        "--geometry",
        str(sim / "ground_truth"),
        "--out",
        str(out),
        "--texture-resolution",
        str(RES),
        "--quiet",
        *extra,
    ]


@pytest.mark.slow
def test_reconstruct_evaluate_end_to_end(sim, tmp_path, capsys):
    out = tmp_path / "result"
    assert main(_args(sim, out, "--iterations", "120")) == 0
    result = json.loads((out / "result.json").read_text())
    assert result["format"] == "polarface-result" and result["texture_resolution"] == [RES, RES]
    assert len(result["channel_names"]) == 6 and result["stages"]["polarimetric"]["complete"]
    for name in ("eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss", "displacement_mm", "rho_sss_bar"):
        assert (out / "maps" / f"{name}.exr").exists()
    assert set(read_exr(out / "maps" / "rho_sss_bar.exr")) == set(result["channel_names"])
    view_count = read_exr(out / "maps" / "view_count.exr")["Y"]
    mask = read_png(out / "maps" / "mask.png") > 0
    mask = mask if mask.ndim == 2 else mask[..., 0]
    seen = view_count >= 4  # min_views 4, boundary_margin 1
    assert np.array_equal(mask, seen & ndimage.binary_erosion(seen, border_value=0))
    assert (out / "previews" / "view_count.png").exists()
    assert result["stages"]["polarimetric"]["texels_in_boundary_margin"] > 0
    assert "view_count.png" in (out / "report.html").read_text()
    assert (out / "report.html").exists() and (out / "rig.json").exists() and (out / "mesh.obj").exists()
    capsys.readouterr()
    assert main(["evaluate", str(out), "--gt", str(sim)]) == 0
    metrics = json.loads(capsys.readouterr().out)
    pol = metrics["polarimetric"]
    # stated tolerances of the small synthetic capture (4 frames, 160 x 128 px, demosaiced, noise-free)
    assert pol["rho_sss_bar"]["median_relative_error"] < 0.05
    assert pol["eta"]["median_abs_error"] < 0.1
    assert pol["alpha_s"]["median_abs_error"] < 0.1
    assert pol["normal_angular_error_deg"]["median_abs_error"] < 2.0
    assert metrics["rerender"]["held_out_views"] == 2 and metrics["rerender"]["i_sss_rmse"] < 0.15


def test_resume_after_interruption_gives_the_same_maps(sim, tmp_path):
    def context(out, stop=None):
        return ReconstructContext(
            sim / "static",
            out,
            sim / "ground_truth" / "mesh_rest.obj",
            sim / "ground_truth" / "static" / "poses.json",
            RES,
            "cpu",
            True,
            False,
            0,
            {"iterations": 15, "patch": 8},
            stop_after_patches=stop,
        )

    straight = tmp_path / "straight"
    straight.mkdir()
    run_stages(context(straight))
    interrupted = tmp_path / "interrupted"
    interrupted.mkdir()
    with pytest.raises(InterruptedError):
        run_stages(context(interrupted, stop=1))
    assert (interrupted / "checkpoints" / "polarimetric.npz").exists()
    assert not (interrupted / "maps" / "eta.exr").exists()
    run_stages(context(interrupted))
    for name in ("eta", "alpha_s", "rho_s", "displacement_mm"):
        np.testing.assert_array_equal(
            read_exr(straight / "maps" / f"{name}.exr")["Y"],
            read_exr(interrupted / "maps" / f"{name}.exr")["Y"],
        )


def test_bad_input_clear_error_and_nothing_written(sim, tmp_path, capsys):
    out = tmp_path / "r"
    no_poses = tmp_path / "geometry"
    no_poses.mkdir()
    shutil.copy(sim / "ground_truth" / "mesh_rest.obj", no_poses / "mesh_rest.obj")
    assert main(_args(sim, out, "--geometry", str(no_poses))) == 2
    assert "poses" in capsys.readouterr().err and not out.exists()
    # mismatched UV atlas: every UV collapsed onto one point covers no texel
    mesh = load_mesh(sim / "ground_truth" / "mesh_rest.obj")
    flat = TriangleMesh.from_arrays(mesh.vertices, mesh.faces, np.full_like(mesh.uv, 0.5))
    save_obj(tmp_path / "flat.obj", flat)
    assert (
        main(
            [
                "reconstruct",
                str(sim / "static"),
                "--mesh",
                str(tmp_path / "flat.obj"),
                "--poses",
                str(sim / "ground_truth" / "static" / "poses.json"),
                "--out",
                str(out),
                "--texture-resolution",
                str(RES),
                "--quiet",
            ]
        )
        == 2
    )
    assert "UV atlas" in capsys.readouterr().err and not out.exists()
    # all-invisible texels: poses that put the head behind the cameras
    poses = json.loads((sim / "ground_truth" / "static" / "poses.json").read_text())
    matrices = poses["poses"] if isinstance(poses, dict) else poses
    for matrix in matrices:
        matrix[2][3] = -5000.0
    (tmp_path / "away.json").write_text(json.dumps(matrices))
    assert (
        main(
            [
                "reconstruct",
                str(sim / "static"),
                "--mesh",
                str(sim / "ground_truth" / "mesh_rest.obj"),
                "--poses",
                str(tmp_path / "away.json"),
                "--out",
                str(out),
                "--texture-resolution",
                str(RES),
                "--quiet",
            ]
        )
        == 2
    )
    assert "invisible" in capsys.readouterr().err and not out.exists()
    # an existing non-empty output without --resume
    out.mkdir()
    (out / "x").write_text("x")
    assert main(_args(sim, out)) == 2


def test_reconstruct_with_lobe_refinement(sim, tmp_path):
    out = tmp_path / "refined"
    assert main(_args(sim, out, "--iterations", "20", "--refine-lobes", "1")) == 0
    stage = json.loads((out / "result.json").read_text())["stages"]["polarimetric"]
    assert stage["config"]["refine_lobes_iterations"] == 1 and stage["timings"]["refine_s"] > 0
    for name in ("alpha_s", "alpha_ss", "rho_s", "rho_ss"):
        assert np.isfinite(read_exr(out / "maps" / f"{name}.exr")["Y"]).all()
    assert main(_args(sim, tmp_path / "bad", "--refine-lobes", "-1")) == 2


def test_reconstruct_with_a_model_variant(sim, tmp_path, capsys):
    """``--model riviere2020``: one lobe, eta and alpha_s one value over the face (the free pass's
    medians, recorded); an unknown model or a contradicting option is refused before any work."""
    out = tmp_path / "riviere"
    assert main(_args(sim, out, "--iterations", "5", "--model", "riviere2020")) == 0
    stage = json.loads((out / "result.json").read_text())["stages"]["polarimetric"]
    assert stage["model"] == "riviere2020"
    assert stage["config"]["lobes"] == "one" and stage["config"]["homogeneous"] == ["eta", "alpha_s"]
    mask = read_png(out / "maps" / "mask.png") > 0
    for name in ("eta", "alpha_s"):
        values = read_exr(out / "maps" / f"{name}.exr")["Y"][mask]
        np.testing.assert_allclose(values, stage["homogeneous_values"][name], atol=1e-5)
    assert (out / "checkpoints" / "polarimetric_free.npz").is_file()
    capsys.readouterr()
    assert main(_args(sim, tmp_path / "bad", "--model", "hwang")) == 2
    assert "'--model' must be one of" in capsys.readouterr().err
    assert main(_args(sim, tmp_path / "bad", "--model", "no-single-scattering", "--lobes", "two")) == 2
    assert "lobes='one'" in capsys.readouterr().err and not (tmp_path / "bad").exists()


def test_bench_smoke(capsys):
    import numba

    before = torch.get_num_threads(), numba.get_num_threads()
    assert (
        main(
            [
                "bench",
                "--side",
                "8",
                "--frames",
                "2",
                "--iterations",
                "1",
                "--baseline-texels",
                "1",
                "--threads",
                "1",
                "--seconds",
                "0.05",
                "--repeats",
                "2",
                "--json",
            ]
        )
        == 0
    )
    result = json.loads(capsys.readouterr().out)
    assert (
        result["fused_kernel_texel_view_iterations_per_s"]
        > result["eager_baseline_texel_view_iterations_per_s"]
    )
    assert result["torch_vectorised_texel_view_iterations_per_s"] > 0 and result["speedup"] > 1
    # every workload: a median within its repeats' spread, at least --iterations per repeat
    for rates in result["workloads"].values():
        assert rates["min"] <= rates["q25"] <= rates["median"] <= rates["q75"] <= rates["max"]
        assert len(rates["rates"]) == result["repeats"] == 2 and rates["iterations_per_repeat"] >= 1
    headline = result["fused_kernel_texel_view_iterations_per_s"]
    assert headline == result["workloads"]["fused_objective"]["median"]
    assert len(result["load_average"]) == 2
    # --threads holds for the command only (other work in this process keeps its thread counts)
    assert (torch.get_num_threads(), numba.get_num_threads()) == before
    assert main(["bench", "--side", "2"]) == 2


def test_evaluate_bad_input(sim, tmp_path, capsys):
    assert main(["evaluate", str(tmp_path), "--gt", str(sim)]) == 2
    assert "result.json" in capsys.readouterr().err
    (tmp_path / "result.json").write_text("{}")
    assert main(["evaluate", str(tmp_path), "--gt", str(tmp_path / "nothing")]) == 2
    assert main(["evaluate", str(tmp_path), "--gt", str(sim), "--groups", "nope"]) == 2


def test_resume_refuses_other_options_or_capture(sim, tmp_path, capsys):
    out = tmp_path / "fp"
    assert main(_args(sim, out, "--iterations", "3")) == 0
    recorded = json.loads((out / "result.json").read_text())["fingerprint"]
    assert recorded["options"]["iterations"] == 3 and recorded["texture_resolution"] == RES
    assert recorded["capture"]["frames"] == 4 and len(recorded["mesh"]["sha256"]) == 64
    before = (out / "result.json").read_bytes()
    capsys.readouterr()
    # all stages done: a different --iterations used to be ignored silently
    assert main(_args(sim, out, "--iterations", "20", "--resume")) == 2
    err = capsys.readouterr().err
    assert "options.iterations: recorded 3, now 20" in err and "without --resume" in err
    # the message, then one line per differing key path (not the whole configurations)
    assert err.strip().splitlines()[1:] == ["  options.iterations: recorded 3, now 20"]
    # the patch grid (--patch, --sample-budget; larger by default on a GPU) cannot change mid-run
    assert main(_args(sim, out, "--iterations", "3", "--resume", "--patch", "32",
                      "--sample-budget", "5000")) == 2
    err = capsys.readouterr().err
    grid = recorded["options"]["patch"], recorded["options"]["sample_budget"]
    assert f"options.patch: recorded {grid[0]}, now 32" in err
    assert f"options.sample_budget: recorded {grid[1]}, now 5000" in err
    # another capture (one frame's raw content changed) is refused, naming the capture
    other = tmp_path / "other_sim"
    shutil.copytree(sim, other)
    marker = other / "static" / "frames" / "000000.json"
    payload = json.loads(marker.read_text())
    payload["timestamp"] = 99.0
    marker.write_text(json.dumps(payload))
    args = _args(other, out, "--iterations", "3", "--resume")
    assert main(args) == 2 and "  capture: recorded '" in capsys.readouterr().err
    # another texture resolution
    assert main([*_args(sim, out, "--iterations", "3", "--resume")[:-3], "--iterations", "3", "--resume",
                 "--texture-resolution", "8"]) == 2
    assert "texture_resolution: recorded 16, now 8" in capsys.readouterr().err
    assert (out / "result.json").read_bytes() == before
    # the same options (threads, device and the chunk cache's size do not count) resume fine
    assert "unwrap_cache_mb" not in recorded["options"]
    assert main(_args(sim, out, "--iterations", "3", "--resume", "--threads", "2",
                      "--unwrap-cache-mb", "0")) == 0


@pytest.mark.parametrize("stage", ["geometry", "prepare"])
def test_a_run_stopped_by_ctrl_c_in_an_early_stage_resumes(sim, tmp_path, capsys, monkeypatch, stage):
    """Ctrl-C in the geometry or the prepare stage says 'rerun with --resume', and the resume is taken:
    the folder is already a RESULT (its format keys are written with the fingerprint, before any stage)."""
    module = importlib.import_module("polarface.pipeline.reconstruct.stages")

    def interrupted(ctx):
        raise KeyboardInterrupt

    stages = [(name, interrupted if name == stage else function) for name, function in module.STAGES]
    monkeypatch.setattr(module, "STAGES", stages)
    out = tmp_path / "stopped"
    assert main(_args(sim, out, "--iterations", "2")) == 130
    assert "--resume" in capsys.readouterr().err
    assert json.loads((out / "result.json").read_text())["format"] == "polarface-result"
    monkeypatch.undo()
    assert main(_args(sim, out, "--iterations", "2", "--resume")) == 0
    assert (out / "maps" / "eta.exr").is_file()


def test_a_failed_write_leaves_no_new_result_folder(sim, tmp_path, capsys, monkeypatch):
    """A full disk in the prepare stage of a new RESULT: one line naming the file, nothing left behind (no
    stage worth resuming was complete)."""
    import errno

    import polarface.texture as texture

    def full_disk(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "full" / "unwrap.zarr"))

    monkeypatch.setattr(texture, "unwrap_capture", full_disk)
    assert main(_args(sim, tmp_path / "full", "--iterations", "2")) == 2
    err = capsys.readouterr().err
    assert "No space left on device" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "full").exists()


def test_resume_mid_fit_with_other_iterations_is_refused(sim, tmp_path):
    def context(iterations, stop=None):
        return ReconstructContext(
            sim / "static", out, sim / "ground_truth" / "mesh_rest.obj",
            sim / "ground_truth" / "static" / "poses.json", RES, "cpu", True, False, 0,
            {"iterations": iterations, "patch": 8}, stop_after_patches=stop,
        )

    out = tmp_path / "mid"
    out.mkdir()
    with pytest.raises(InterruptedError):
        run_stages(context(15, stop=1))
    with pytest.raises(ValueError, match=r"options\.iterations: recorded 15, now 20"):
        run_stages(context(20))
    assert not (out / "maps" / "eta.exr").exists()


def test_the_device_chooses_the_patch_grid_and_a_resume_keeps_it(sim, tmp_path, monkeypatch):
    import polarface.inverse.polarimetric as polarimetric

    gpu_grid = {"patch": 8, "sample_budget": 4000}  # as a GPU's device_fit_options would, scaled down
    monkeypatch.setattr(polarimetric, "device_fit_options", lambda device, units_per_gpu=1: dict(gpu_grid))
    out = tmp_path / "gpu"
    assert main(_args(sim, out, "--iterations", "2")) == 0
    recorded = json.loads((out / "result.json").read_text())["fingerprint"]["options"]
    assert (recorded["patch"], recorded["sample_budget"]) == (8, 4000)
    # resumed on "another device" (the CPU's defaults): the recorded grid is kept, not refused
    monkeypatch.setattr(polarimetric, "device_fit_options", lambda device, units_per_gpu=1: {})
    assert main(_args(sim, out, "--iterations", "2", "--resume")) == 0
    result = json.loads((out / "result.json").read_text())
    assert result["stages"]["polarimetric"]["config"]["patch"] == 8
    # the user's options win over the device's
    monkeypatch.setattr(polarimetric, "device_fit_options", lambda device, units_per_gpu=1: dict(gpu_grid))
    other = tmp_path / "user"
    assert main(_args(sim, other, "--iterations", "2", "--patch", "12")) == 0
    recorded = json.loads((other / "result.json").read_text())["fingerprint"]["options"]
    assert (recorded["patch"], recorded["sample_budget"]) == (12, 4000)
