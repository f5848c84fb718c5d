"""``polarface info``: what a capture store, a simulation folder and a RESULT folder hold."""

from __future__ import annotations

import json

import numpy as np
import pytest

from polarface.cli import main
from polarface.pipeline import folder_info, format_info
from polarface.results import ResultFolder
from polarface.simulate.sphere_capture import SphereCaptureConfig, make_sphere_capture


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    root = tmp_path_factory.mktemp("sim")
    make_sphere_capture(root, SphereCaptureConfig(texture_resolution=8, frames=2))
    (root / "simulation.json").write_text(json.dumps({
        "config": {"preset": "tiny", "seed": 0}, "channel_names": ["a", "b"],
        "timings": {"render_s": 1.0, "total_s": 2.5}, "peak_rss_mb": 300.0,
    }))
    return root


def _result(root):
    folder = ResultFolder(root)
    folder.write_result_header([f"channel{i}" for i in range(6)], (8, 8), 0.5)
    folder.record_stage("prepare", {"views": 4, "timings": {"prepare_s": 1.5}})
    folder.record_stage("polarimetric", {
        "texels": 40, "config": {"iterations": 120, "min_views": 4},
        "timings": {"fit_s": 9.0, "stage_s": 10.0},
    })
    folder.update_result(stage="biophysical", record={"timings_s": {"total_s": 3.0}})
    folder.write_scalar_map("eta", np.full((8, 8), 1.4, np.float32))
    (root / "report.html").write_text("<html></html>")
    return root


def test_capture_store(sim):
    info = folder_info(sim / "static")
    assert info["kind"] == "capture" and info["sequence"] == "static" and info["complete"]
    assert info["frames"] == 2 and info["frames_with_marker"] == 2
    cameras = {c["id"]: c for c in info["cameras"]}
    assert cameras["pol_upper"]["resolution"] == [160, 128] and cameras["pol_upper"]["role"] == "polarimetric"
    text = format_info(info)
    assert text.startswith(f"capture store {sim / 'static'}")
    assert "2 frames" in text and "160 x 128 px" in text


def test_simulation_folder(sim):
    info = folder_info(sim)
    assert info["kind"] == "simulation" and info["seconds"] == 2.5
    assert set(info["sequences"]) == {"static"} and info["sequences"]["static"]["frames"] == 2
    assert "eta.exr" in info["ground_truth_maps"] and info["configuration"]["preset"] == "tiny"
    text = format_info(info)
    assert "simulated in 2.5 s" in text and "static/:" in text and 'preset="tiny"' in text


def test_result_folder(tmp_path):
    info = folder_info(_result(tmp_path / "result"))
    assert info["kind"] == "result" and info["texture_resolution"] == [8, 8] and info["texels"] == 40
    assert info["stages"] == {
        "prepare": {"complete": True, "seconds": 1.5},
        "polarimetric": {"complete": True, "seconds": 10.0},
        "biophysical": {"complete": False, "seconds": 3.0},
    }
    assert info["maps"] == ["eta.exr"] and info["report"] == "report.html"
    assert info["configuration"] == {"polarimetric": {"iterations": 120, "min_views": 4}}
    assert info["fingerprint"] is None
    text = format_info(info)
    assert "polarimetric   done" in text and "10 s" in text and "not complete" in text
    assert "iterations=120" in text and "fingerprint" not in text


def test_fingerprint_is_shown(tmp_path):
    root = _result(tmp_path / "result")
    ResultFolder(root).update_result({"fingerprint": "abc123"})
    info = folder_info(root)
    assert info["fingerprint"] == "abc123" and "fingerprint: abc123" in format_info(info)


def test_cli_text_json_and_errors(sim, tmp_path, capsys):
    assert main(["info", str(sim / "static"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["frames"] == 2
    assert main(["info", str(_result(tmp_path / "r"))]) == 0
    assert capsys.readouterr().out.startswith("RESULT folder")
    assert main(["info", str(tmp_path / "missing")]) == 2
    assert "does not exist" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["info", str(tmp_path / "empty")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is not a RESULT folder, a capture store, an imported session or a" in err
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "result.json").write_text("{nope")
    assert main(["info", str(tmp_path / "bad")]) == 2
    assert "result.json' is not valid JSON" in capsys.readouterr().err
