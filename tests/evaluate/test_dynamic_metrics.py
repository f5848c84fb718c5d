"""The dynamic metrics (``polarface.evaluate.dynamic``) on the tiny simulation's ground truth used
as its own reconstruction (errors ~0) and on perturbed copies (errors of the size of the perturbation),
the pressed-patch weight of the simulated sequence, and bad inputs (the recovery fit and the material
points on synthetic data: ``tests/evaluate/test_dynamic_measures.py``)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from polarface.evaluate import METRIC_GROUPS, evaluate
from polarface.evaluate.dynamic import (
    DYNAMIC_METRIC_KEYS,
    dynamic_group,
    dynamic_metrics,
    pressed_patch_weight,
)
from polarface.geometry import load_mesh, save_obj
from polarface.geometry.poses import invert_rigid
from polarface.io import read_exr, write_exr
from polarface.results import CHROMOPHORE_MAPS, POLARIMETRIC_MAPS, RHO_SSS_BAR, ResultFolder
from polarface.simulate import SimulationConfig, blood_flow_factor


@pytest.fixture(scope="module")
def sim(tiny_sim) -> Path:
    """The shared tiny simulation (tests/conftest.py): its dynamic sequence (2 frames, 1 s apart) with
    its ground truth."""
    return tiny_sim


def _rotation_x(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    out = np.eye(4)
    out[1:3, 1:3] = [[c, -s], [s, c]]
    return out


def write_truth_result(sim: Path, root: Path, *, vertex_shift_mm: float = 0.0, c_h_out_offset: float = 0.0,
                       rho_scale: float = 1.0, rho_s_scale: float = 1.0, c_m_offset: float = 0.0,
                       alignment_tilt_rad: float = 0.0) -> Path:
    """A dynamic RESULT made of the ground truth: frame 1 perturbed by the arguments (tracked vertices
    moved along +x, c_h_out, rho_sss_bar, rho_s, c_m changed); the recorded alignment tilted about x."""
    gt = sim / "ground_truth"
    summary = json.loads((sim / "simulation.json").read_text())
    placement = np.asarray(summary["head_placement"], np.float64)
    folder = ResultFolder(root)
    folder.write_result_header(summary["channel_names"], (256, 256), 1.0)
    shutil.copy(gt / "mesh_rest.obj", root / "mesh.obj")
    rest = load_mesh(gt / "mesh_rest.obj")
    tracked = []
    for t in (0, 1):
        frame = folder.frame(t)
        for name in (*POLARIMETRIC_MAPS, *CHROMOPHORE_MAPS, RHO_SSS_BAR):
            source = gt / "dynamic" / "maps" / f"{t:06d}_{name}.exr"
            channels = read_exr(source if source.is_file() else gt / "maps" / f"{name}.exr")
            if t == 1:
                scale = {"rho_s": rho_s_scale, RHO_SSS_BAR: rho_scale}.get(name, 1.0)
                offset = {"c_h_out": c_h_out_offset, "c_m": c_m_offset}.get(name, 0.0)
                channels = {k: v * scale + offset for k, v in channels.items()}
            write_exr(frame.map_path(name), channels)
        shutil.copy(gt / "maps" / "mask.png", frame.map_path("mask", ".png"))
        vertices = load_mesh(gt / "dynamic" / "meshes" / f"{t:06d}.ply").vertices.copy()
        save_obj(frame.root / "mesh.obj", rest.with_vertices(vertices).transformed(invert_rigid(placement)))
        if t == 1:
            vertices[:, 0] += vertex_shift_mm
        tracked.append(vertices)
    (root / "tracking").mkdir()
    np.savez(root / "tracking" / "tracked.npz", frames=np.array([0, 1], np.int64), vertices=np.stack(tracked),
             confidence=np.ones((2, len(rest.vertices)), np.float32))
    alignment = _rotation_x(alignment_tilt_rad) @ placement
    folder.record_stage("dynamic", {
        "capture": str(sim / "dynamic"), "frames": [0, 1], "completed": [0, 1], "failed_frames": {},
        "timestamps_s": {"0": 0.0, "1": 1.0}, "alignment": alignment.tolist(), "seconds_per_frame": 12.5,
    })
    return root


@pytest.fixture(scope="module")
def truth_metrics(sim, tmp_path_factory) -> dict:
    return dynamic_metrics(write_truth_result(sim, tmp_path_factory.mktemp("truth")), sim)


@pytest.fixture(scope="module")
def perturbed_metrics(sim, tmp_path_factory) -> dict:
    root = write_truth_result(sim, tmp_path_factory.mktemp("perturbed"), vertex_shift_mm=0.2,
                              c_h_out_offset=0.01, rho_scale=1.05, rho_s_scale=1.1, c_m_offset=0.003,
                              alignment_tilt_rad=np.radians(2.0))
    return dynamic_metrics(root, sim)


def test_truth_as_its_own_reconstruction_scores_zero(truth_metrics):
    assert tuple(truth_metrics) == DYNAMIC_METRIC_KEYS
    assert truth_metrics["frames"] == 2
    # the tracked vertices are the PLY's vertices: zero up to the float32 closest-point search (1e-5 mm)
    assert max(truth_metrics["tracking_mm"]["median_per_frame"]) < 1e-3
    assert truth_metrics["tracking_mm"]["max"] < 1e-3
    assert max(truth_metrics["c_h_out_patch_abs_error"]) < 1e-7  # identical float32 maps
    assert max(truth_metrics["rho_sss_bar_median_relative_error"]) < 1e-7
    # the frame meshes went through OBJ (6 decimals) and the alignment: normals agree to ~1e-3 deg
    assert max(truth_metrics["normal_median_deg"]) < 0.01
    assert truth_metrics["c_m_patch_drift_max"] == 0.0
    assert truth_metrics["rho_s_flicker_median"] == 0.0
    assert truth_metrics["seconds_per_frame"] == 12.5
    # two frames: no time constant can be fitted
    assert truth_metrics["recovery_time_constant_s"] == {"ground_truth": None, "reconstructed": None}


def test_perturbations_show_up_with_their_size(perturbed_metrics):
    tracking = perturbed_metrics["tracking_mm"]
    assert tracking["median_per_frame"][0] < 1e-3  # frame 0 defines the material points
    assert tracking["median_per_frame"][1] == pytest.approx(0.2, abs=1e-3)  # every vertex moved 0.2 mm
    assert tracking["max"] == pytest.approx(0.2, abs=1e-3)
    errors = perturbed_metrics["c_h_out_patch_abs_error"]
    assert errors[0] < 1e-7 and errors[1] == pytest.approx(0.01, abs=1e-6)
    relative = perturbed_metrics["rho_sss_bar_median_relative_error"]
    assert relative[0] < 1e-7 and relative[1] == pytest.approx(0.05, abs=1e-5)
    # the alignment tilt turns a normal n by arccos(nx^2 + (1 - nx^2) cos 2 deg): 2 deg where n is
    # perpendicular to the tilt axis x, less elsewhere (a face's normals spread over ~60 deg about it);
    # without the alignment the angle would be ~0, with the tilt applied twice up to 4 deg
    normal = perturbed_metrics["normal_median_deg"]
    assert 1.3 < normal[0] <= 2.0 + 1e-3 and normal[1] == pytest.approx(normal[0], abs=1e-6)
    assert perturbed_metrics["c_m_patch_drift_max"] == pytest.approx(0.003, abs=1e-6)
    assert perturbed_metrics["rho_s_flicker_median"] == pytest.approx(0.1, abs=1e-5)


def test_pressed_patch_weight_recovers_the_simulated_patch(sim):
    from polarface.simulate import SimulationScene
    from polarface.simulate.sequences import pressed_patch

    gt = sim / "ground_truth"
    static = read_exr(gt / "maps" / "c_h_out.exr")["Y"]
    first = read_exr(gt / "dynamic" / "maps" / "000000_c_h_out.exr")["Y"]
    weight = pressed_patch_weight(static, first)
    truth = pressed_patch(SimulationScene.build(SimulationConfig(preset="tiny", sequences=("dynamic",))))
    # the simulator's weight, up to the float32 rounding of the maps (c_h_out ~ 1e-2: ~1e-7 relative)
    assert np.abs(weight - truth)[static > 0].max() < 1e-5
    assert (weight > 0.5).sum() > 20  # a patch, not a few texels
    # frame 1 (t = 1 s) lowers c_h_out by 0.8 w exp(-1.5): the same weight from that frame
    later = read_exr(gt / "dynamic" / "maps" / "000001_c_h_out.exr")["Y"]
    from_later = pressed_patch_weight(static, later, 0.8 * (1.0 - float(blood_flow_factor(1.0))))
    assert np.abs(from_later - truth)[static > 0].max() < 1e-4


def test_evaluate_runs_the_dynamic_group(sim, tmp_path):
    assert "dynamic" in METRIC_GROUPS
    root = write_truth_result(sim, tmp_path / "result")
    metrics = evaluate(root, sim, ["dynamic"])
    assert tuple(metrics["dynamic"]) == DYNAMIC_METRIC_KEYS
    static_only = tmp_path / "static"
    ResultFolder(static_only).write_result_header(["a"], (4, 4), 1.0)
    assert "skipped" in dynamic_group(static_only, sim)


def test_bad_inputs_name_the_path(sim, tmp_path):
    static_only = tmp_path / "static"
    ResultFolder(static_only).write_result_header(["a"], (4, 4), 1.0)
    with pytest.raises(FileNotFoundError, match="frames"):
        dynamic_metrics(static_only, sim)
    root = write_truth_result(sim, tmp_path / "result")
    no_dynamic = tmp_path / "gt"
    shutil.copytree(sim / "ground_truth" / "maps", no_dynamic / "maps")
    with pytest.raises(FileNotFoundError, match="dynamic"):
        dynamic_metrics(root, no_dynamic)
    (root / "tracking" / "tracked.npz").unlink()
    with pytest.raises(FileNotFoundError, match=r"tracked\.npz"):
        dynamic_metrics(root, sim)


def test_info_lists_the_dynamic_frames(sim, tmp_path):
    from polarface.pipeline import folder_info, format_info

    root = write_truth_result(sim, tmp_path / "result")
    record = ResultFolder(root).stage_record("dynamic")
    record |= {"frames": [0, 1, 2], "failed_frames": {"2": "tracking lost"}}
    ResultFolder(root).update_result(stage="dynamic", record=record)
    info = folder_info(root)
    assert info["dynamic"] == {"frames": 3, "done": 2, "failed": {"2": "tracking lost"}}
    assert "dynamic frames: 3, done 2, failed 1: 2 (tracking lost)" in format_info(info)
