"""Per-view residual check and eta uncertainty on a small simulated capture (known geometry).

The capture is the simulator's sphere cap (2 polarimetric cameras x 4 frames, 12-bit noise); the
"miscalibrated" reconstruction reads a copy whose rig.json turns camera ``pol_lower`` by 0.5 deg about
the vertical axis (the images stay those of the true rig).
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from polarface.io import read_exr
from polarface.pipeline import ReconstructContext, ViewCheckConfig, check_view_residuals, flag_view_residuals
from polarface.pipeline.reconstruct.stages import stage_polarimetric, stage_prepare
from polarface.results import ResultFolder
from polarface.simulate.sphere_capture import SphereCaptureConfig, make_sphere_capture

RES = 24


def _turn_camera(rig_path, camera_id: str, degrees: float) -> None:
    rig = json.loads(rig_path.read_text())
    angle = np.radians(degrees)
    rotation = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    for camera in rig["cameras"]:
        if camera["id"] == camera_id:
            matrix = np.array(camera["world_to_camera"])
            matrix[:3] = rotation @ matrix[:3]
            camera["world_to_camera"] = matrix.tolist()
    rig_path.write_text(json.dumps(rig))


def _reconstruct(capture, sim, out):
    out.mkdir()
    ctx = ReconstructContext(capture, out, sim / "ground_truth" / "mesh_rest.obj",
                             sim / "ground_truth" / "static" / "poses.json", RES, "cpu", False, False, 4,
                             {"iterations": 30}, view_check=True)
    ctx.folder.record_stage("prepare", stage_prepare(ctx))
    return stage_polarimetric(ctx)


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    root = tmp_path_factory.mktemp("viewcheck")
    sim = root / "sim"
    make_sphere_capture(sim, SphereCaptureConfig(texture_resolution=RES, frames=4, noise=True))
    bad_capture = root / "static_bad"
    shutil.copytree(sim / "static", bad_capture)
    _turn_camera(bad_capture / "rig.json", "pol_lower", 0.5)
    good = _reconstruct(sim / "static", sim, root / "good")
    bad = _reconstruct(bad_capture, sim, root / "bad")
    return sim, root, good, bad


@pytest.mark.slow
def test_calibrated_rig_flags_nothing(results):
    _, root, good, _ = results
    check = good["view_check"]
    assert check["views"] == 8 and check["flagged_cameras"] == [] and check["flagged_frames"] == []
    assert check["warnings"] == []
    table = json.loads((root / "good" / "view_residuals.json").read_text())
    assert len(table["rows"]) == 8 and all(r["score"] < 0.05 for r in table["rows"])


@pytest.mark.slow
def test_turned_camera_is_flagged_and_the_other_is_not(results):
    _, root, _, bad = results
    check = bad["view_check"]
    assert check["flagged_cameras"] == ["pol_lower"]
    assert any(w.startswith("camera pol_lower") for w in check["warnings"])
    table = json.loads((root / "bad" / "view_residuals.json").read_text())
    assert table["cameras"]["pol_lower"]["ratio_to_others"] > 2.0
    assert "flag" not in table["cameras"]["pol_upper"] and check["flagged_frames"] == []


@pytest.mark.slow
def test_eta_uncertainty_covers_the_error(results):
    """z = (eta - eta_true) / eta_std over the mask: the data-only Laplace sigma is conservative (measured
    median |z| ~0.3 on the tiny preset, a Gaussian's would be 0.67); at least 70 % within 2 sigma."""
    sim, root, good, _ = results
    std = read_exr(root / "good" / "maps" / "eta_std.exr")["Y"]
    eta = read_exr(root / "good" / "maps" / "eta.exr")["Y"]
    truth = read_exr(sim / "ground_truth" / "maps" / "eta.exr")["Y"]
    mask = ResultFolder(root / "good").read_mask() & (std > 0)
    assert mask.sum() > 50
    z = (eta - truth)[mask] / std[mask]
    assert 0.7 <= np.mean(np.abs(z) < 2.0) <= 1.0
    assert np.mean(np.abs(z) < 0.05) < 0.5  # not vacuous: the sigma is not orders of magnitude too large
    view_count = read_exr(root / "good" / "maps" / "view_count.exr")["Y"][mask]
    few, many = view_count <= np.median(view_count), view_count > np.median(view_count)
    if few.any() and many.any():
        assert np.median(std[mask][few]) >= np.median(std[mask][many])
    assert good["view_check"]["uncertainty"]["eta_std_median"] > 0


def test_flags_on_a_synthetic_table():
    rows = [{"view": i, "frame": i // 2, "camera": "ab"[i % 2], "score": 0.03 + 0.001 * i} for i in range(8)]
    assert flag_view_residuals(rows)["warnings"] == []
    rows[1]["score"] = rows[3]["score"] = rows[5]["score"] = rows[7]["score"] = 0.2  # camera b off
    flags = flag_view_residuals(rows)
    assert "flag" in flags["cameras"]["b"] and "flag" not in flags["cameras"]["a"]
    assert not any("flag" in g for g in flags["frames"].values())
    rows = [{"view": i, "frame": i // 2, "camera": "ab"[i % 2], "score": 0.03} for i in range(8)]
    rows[4]["score"] = rows[5]["score"] = 0.3  # frame 2 off in both cameras
    flags = flag_view_residuals(rows)
    assert list(k for k, g in flags["frames"].items() if "flag" in g) == ["2"]
    with pytest.raises(ValueError, match="ratio"):
        ViewCheckConfig(ratio=0.0)


def test_result_without_unwrap_store_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"unwrap\.zarr"):
        check_view_residuals(ResultFolder(tmp_path))
