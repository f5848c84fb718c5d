"""The dynamic stage end to end on the tiny preset: blood flow recovered, per-frame resume, failures.

One tiny simulation (static + 2 dynamic frames 1 s apart) and one static reconstruction (known geometry,
shortened fit) serve every test; each test runs the dynamic stage into its own copy of the static RESULT.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

import polarface.pipeline.dynamic.frames as frames_module
from polarface.capture.store import CaptureStore
from polarface.cli import main
from polarface.io import read_exr, write_png
from polarface.pipeline.dynamic import DynamicStageConfig, reconstruct_dynamic
from polarface.pipeline.inputs import parse_frame_selection
from polarface.results import ResultFolder

MAPS = ("rho_s", "rho_ss", "displacement_mm", "c_h_out", "c_m")


@pytest.fixture(scope="module")
def tiny(tiny_sequence):
    """``(SIM, static RESULT)``: the shared tiny sequence (tests/conftest.py)."""
    return tiny_sequence


@pytest.fixture(scope="module")
def sequence(tiny, tmp_path_factory):
    """The dynamic stage run once on a copy of the static RESULT: ``(RESULT, record)``."""
    sim, static = tiny
    result = tmp_path_factory.mktemp("sequence") / "result"
    shutil.copytree(static, result)
    record = reconstruct_dynamic(result, sim, progress=False)
    return result, record


def _patch(sim):
    """``(H, W)`` bool texels of the pressed patch (weight > 0.5) and the ground truth's c_h_out per frame:
    frame 0 has c_h_out = static * (1 - 0.8 w) (simulate/sequences.py)."""
    static = read_exr(sim / "ground_truth" / "maps" / "c_h_out.exr")["Y"]
    maps = sim / "ground_truth" / "dynamic" / "maps"
    frames = [read_exr(maps / f"{f:06d}_c_h_out.exr")["Y"] for f in (0, 1)]
    weight = np.where(static > 0, (1.0 - frames[0] / np.where(static > 0, static, 1.0)) / 0.8, 0.0)
    return weight > 0.5, frames


def test_patch_c_h_out_drop_and_recovery_are_recovered(tiny, sequence):
    sim, _ = tiny
    result, record = sequence
    assert record["completed"] == [0, 1] and record["failed_frames"] == {}
    patch, truth = _patch(sim)
    folder = ResultFolder(result)
    estimates = []
    for frame in (0, 1):
        frame_folder = folder.frame(frame)
        mask = frame_folder.read_mask() & patch  # the RESULT's atlas is the ground truth's (given mesh)
        assert mask.sum() > 20
        estimate = frame_folder.read_scalar_map("c_h_out")
        estimates.append(float(np.median(estimate[mask])))
        # the per-frame stage's tolerance: C_h_out within 0.015 of the truth in the patch (issue target
        # 0.01 on the demo; the tiny atlas has ~60 patch texels at 1.2 mm)
        assert abs(estimates[-1] - float(np.median(truth[frame][mask]))) < 0.015, (frame, estimates)
    # the drop: frame 0 (just released) holds far less outer haemoglobin than frame 1 (1 s later)
    drop_truth = float(np.median(truth[1][patch]) - np.median(truth[0][patch]))
    assert estimates[1] - estimates[0] > 0.5 * drop_truth > 0
    # fixed maps are the static ones, bit for bit
    static = ResultFolder(tiny[1])
    for name in ("eta", "alpha_s", "alpha_ss"):
        frame_map = folder.frame(1).read_scalar_map(name)
        np.testing.assert_array_equal(frame_map[folder.frame(1).read_mask()],
                                      static.read_scalar_map(name)[folder.frame(1).read_mask()])


def test_outputs_and_records(sequence):
    result, record = sequence
    folder = ResultFolder(result)
    assert folder.frame_indices() == [0, 1]
    tracking = json.loads((result / "tracking" / "tracking.json").read_text())
    assert tracking["alignment"]["fitness"] > 0.25
    assert np.asarray(record["alignment"]).shape == (4, 4)
    assert record["timestamps_s"] == {"0": 0.0, "1": 1.0}
    assert record["seconds_per_frame"] > 0
    mesh = folder.frame(1).read_mesh()
    reference = folder.read_mesh()
    np.testing.assert_array_equal(mesh.faces, reference.faces)
    np.testing.assert_array_equal(mesh.uv, reference.uv)
    assert (result / "tracking" / "stereo" / "000001.ply").is_file()
    render = read_exr(result / "frames" / "0001" / "render" / "srgb_linear.exr")
    assert set(render) == {"R", "G", "B"} and float(render["G"].max()) > 0  # the frame, rendered
    # the chromophore fit started from the static result (the default), recorded per frame
    biophysical = folder.frame(1).stage_record("biophysical")
    assert biophysical["start"] == str(result) and biophysical["timings_s"]["coarse_s"] < 0.05
    assert record["config"]["biophysical_start"] == "static"


def test_biophysical_start_from_scratch_is_recorded_and_bad_values_refused(tiny, tmp_path):
    sim, static = tiny
    result = tmp_path / "result"
    shutil.copytree(static, result)
    record = reconstruct_dynamic(result, sim, DynamicStageConfig(biophysical_start="scratch"), frames="1",
                                 progress=False)
    assert record["completed"] == [1]
    assert ResultFolder(result).frame(1).stage_record("biophysical")["start"] == "scratch"
    with pytest.raises(ValueError, match="biophysical_start"):
        DynamicStageConfig(biophysical_start="previous")


def test_resume_after_an_interruption_mid_sequence_gives_identical_maps(tiny, sequence, tmp_path,
                                                                        monkeypatch):
    """The per-frame stages resume to the maps of an uninterrupted run. Both runs share the sequence's
    stereo meshes, alignment and tracking (``tracking/``, computed once per RESULT and reloaded by a
    resumed run), so only the per-frame stages are compared."""
    sim, static = tiny
    result = tmp_path / "result"
    shutil.copytree(static, result)
    shutil.copytree(sequence[0] / "tracking", result / "tracking")
    original = frames_module.process_frame

    def interrupted(store, folder, frame, *args, **kwargs):
        if frame == 1:
            raise KeyboardInterrupt
        return original(store, folder, frame, *args, **kwargs)

    monkeypatch.setattr(frames_module, "process_frame", interrupted)
    with pytest.raises(KeyboardInterrupt):
        reconstruct_dynamic(result, sim, progress=False)
    assert ResultFolder(result).frame(0).stage_complete("biophysical")
    assert not ResultFolder(result).frame(1).stage_complete("polarimetric")
    monkeypatch.setattr(frames_module, "process_frame", original)
    record = reconstruct_dynamic(result, sim, progress=False)
    assert record["completed"] == [0, 1]
    uninterrupted = ResultFolder(sequence[0])
    for frame in (0, 1):
        for name in MAPS:
            np.testing.assert_array_equal(ResultFolder(result).frame(frame).read_scalar_map(name),
                                          uninterrupted.frame(frame).read_scalar_map(name), err_msg=name)


def _blank_frame(capture, frame: int) -> None:
    """Every camera of ``frame`` sees nothing (the face left the view): black raw frames and stacks."""
    import zarr

    store = CaptureStore.open(capture)
    record = next(r for r in store.frames if r.index == frame)
    for camera_id, path in record.raw.items():
        raw = store.read_raw(frame, camera_id)
        write_png(capture / path, np.zeros_like(raw), bit_depth=16)
    group = zarr.open_group(capture / "derived.zarr", mode="a")
    for name in ("stacks", "spectral"):
        if name in group:
            for _, array in group[name].arrays():
                array[frame] = 0


def test_a_frame_where_the_face_leaves_the_view_is_reported_and_the_rest_completes(tiny, tmp_path):
    sim, static = tiny
    capture = tmp_path / "dynamic"
    shutil.copytree(sim / "dynamic", capture)
    _blank_frame(capture, 1)
    result = tmp_path / "result"
    shutil.copytree(static, result)
    record = reconstruct_dynamic(result, capture, progress=False)
    assert record["completed"] == [0]
    assert list(record["failed_frames"]) == ["1"]
    assert record["failed_frames"]["1"]  # a reason, not an empty string
    assert ResultFolder(result).frame(0).has_map("c_h_out")


def test_bad_inputs_are_named(tiny, tmp_path, capsys):
    sim, static = tiny
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match="no static result"):
        reconstruct_dynamic(empty, sim, progress=False)
    assert main(["dynamic", str(empty), str(sim), "--quiet"]) == 2
    assert "no static result" in capsys.readouterr().err
    capture = tmp_path / "other_rig"
    shutil.copytree(sim / "dynamic", capture)
    rig = json.loads((capture / "rig.json").read_text())
    rig["cameras"][0]["K"][0][0] *= 1.01
    (capture / "rig.json").write_text(json.dumps(rig))
    result = tmp_path / "result"
    shutil.copytree(static, result)
    with pytest.raises(ValueError, match=r"differs from the static one.*cameras\[pol_upper\]\.K"):
        reconstruct_dynamic(result, capture, progress=False)
    with pytest.raises(ValueError, match="'--frames'"):
        reconstruct_dynamic(result, sim, frames="0,7", progress=False)
    assert not (result / "tracking").exists()  # nothing written before the inputs are checked
    # the one-command form checks the dynamic capture before the static stages write anything
    fresh = tmp_path / "fresh"
    assert main(["reconstruct", str(sim), "--dynamic", str(capture), "--out", str(fresh), "--quiet"]) == 2
    assert "cameras[pol_upper].K" in capsys.readouterr().err and not fresh.exists()
    assert main(["reconstruct", str(sim), "--dynamic", str(sim), "--frames", "0,7", "--out", str(fresh),
                 "--quiet"]) == 2
    assert "'--frames'" in capsys.readouterr().err and not fresh.exists()
    assert main(["reconstruct", str(sim), "--frames", "0", "--out", str(fresh), "--quiet"]) == 2
    assert "pass '--dynamic' too" in capsys.readouterr().err


def test_frame_selection():
    assert parse_frame_selection(None, [0, 1, 2]) == [0, 1, 2]
    assert parse_frame_selection("0-1", [0, 1, 2]) == [0, 1]
    assert parse_frame_selection("2,0", [0, 1, 2]) == [0, 2]
    assert parse_frame_selection([1], [0, 1, 2]) == [1]
    for bad in ("x", "1-", "0-9"):
        with pytest.raises(ValueError, match="'--frames'"):
            parse_frame_selection(bad, [0, 1, 2])


def test_a_frame_without_motion_keeps_the_static_maps_outside_the_patch(tiny, sequence):
    """The tiny sequence's frames have the static head's shape (no expression): only the pressed patch's
    outer haemoglobin changes. Where the truth does not change a frame's maps stay the static ones:
    (almost) nothing flagged as untracked (measured 0), rho_s within 2 % (0.4 %), rho_sss_bar within 6 %
    (3.5 and 4.4 %: more than the static map's own error there, 2.2 %: a frame has one view per channel
    where the static fit had every frame's, docs/dynamic.md) and C_h_out within 0.01 (0.0057 and
    0.0058; the static map's own error 0.0044)."""
    sim, static_dir = tiny
    result, _ = sequence
    _, c_h_out_truth = _patch(sim)
    static, truth = ResultFolder(static_dir), ResultFolder(sim / "ground_truth")
    names = static.channel_names()
    rho_static = static.read_channel_map("rho_sss_bar", names)
    rho_truth = truth.read_channel_map("rho_sss_bar", names, strict=False)
    unchanged = np.abs(c_h_out_truth[0] - truth.read_scalar_map("c_h_out")) < 1e-6  # outside the patch
    for frame in (0, 1):
        frame_folder = ResultFolder(result).frame(frame)
        mask = frame_folder.read_mask() & static.read_mask() & unchanged
        rho = frame_folder.read_channel_map("rho_sss_bar", names)
        change = np.median(np.abs(rho - rho_static)[mask] / rho_static[mask])
        static_error = np.median(np.abs(rho_static - rho_truth)[mask] / rho_truth[mask])
        rho_s, rho_s_static = frame_folder.read_scalar_map("rho_s"), static.read_scalar_map("rho_s")
        rho_s_change = np.median(np.abs(rho_s - rho_s_static)[mask] / rho_s_static[mask])
        c_h_out_static = static.read_scalar_map("c_h_out")
        c_h_out_change = np.median(np.abs(frame_folder.read_scalar_map("c_h_out") - c_h_out_static)[mask])
        c_h_out_error = np.median(np.abs(c_h_out_static - truth.read_scalar_map("c_h_out"))[mask])
        tracking = frame_folder.stage_record("polarimetric")["tracking"]
        print(f"frame {frame}: rho_sss_bar change {change:.4f} (static error {static_error:.4f}), "
              f"rho_s change {rho_s_change:.4f}, C_h_out change {c_h_out_change:.4f} "
              f"(static error {c_h_out_error:.4f}), "
              f"flagged {tracking['flagged_fraction']:.4f}")
        assert mask.sum() > 500
        assert change < 0.06
        assert rho_s_change < 0.02
        assert c_h_out_change < 0.01
        assert tracking["flagged_fraction"] < 0.02
