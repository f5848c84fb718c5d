"""End-to-end simulator on the tiny preset: store validity, ground truth, demosaic, resume, seeds."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import types

import numpy as np
import pytest
from scipy import ndimage

from polarface.capture.rig import Rig, paper_rig
from polarface.capture.store import CaptureStore
from polarface.geometry.poses import check_rigid, load_poses
from polarface.io import read_exr
from polarface.results.fingerprint import RecordMismatchError
from polarface.simulate.frames import raw_frames
from polarface.simulate.pipeline import SimulationConfig, SimulationScene, simulate
from polarface.simulate.presets import SKIN_TYPES, get_preset, get_skin_type


def test_config_errors():
    with pytest.raises(ValueError, match="preset"):
        SimulationConfig(preset="huge")
    with pytest.raises(ValueError, match="skin_type"):
        SimulationConfig(skin_type="VII")
    with pytest.raises(ValueError, match="sequences"):
        SimulationConfig(sequences=("rotation",))
    for seed in (-1, 1.5, True):  # numpy's default_rng rejects a negative seed only after rendering began
        with pytest.raises(ValueError, match="argument 'seed'"):
            SimulationConfig(seed=seed)
    for frames in (1, 2.5, True, "24"):
        with pytest.raises(ValueError, match="argument 'static_frames'"):
            SimulationConfig(static_frames=frames)
    assert get_preset("demo").static_frames == 24
    assert [SKIN_TYPES[k].c_m for k in ("I", "II", "III", "IV")] == sorted(
        SKIN_TYPES[k].c_m for k in ("I", "II", "III", "IV")
    )
    assert get_skin_type("iv").name == "IV"


def test_static_frames_resample_the_preset_sweep():
    """``static_frames`` replaces the preset's frame count and keeps its yaw and pitch ranges."""
    scene = SimulationScene.build(SimulationConfig(preset="tiny", static_frames=7, sequences=("static",)))
    preset = get_preset("tiny")
    assert scene.preset.static_frames == 7
    assert dataclasses.replace(scene.preset, static_frames=preset.static_frames) == preset


def _fake_frame(rig):
    views = {}
    rng = np.random.default_rng(5)
    for camera in rig.cameras:
        shape = (camera.height, camera.width)
        if camera.role == "polarimetric":
            images = {
                k: rng.uniform(0.05, 0.2, (*shape, 3)).astype(np.float32)
                for k in ("i0", "i45", "i90", "i135")
            }
        else:
            images = {"s0": rng.uniform(0.05, 0.2, (*shape, 6)).astype(np.float32)}
        views[camera.id] = types.SimpleNamespace(images=images)
    return types.SimpleNamespace(views=views)


def test_same_seed_same_bytes_other_seed_other_noise():
    rig = paper_rig(width=64, height=48)
    frame = _fake_frame(rig)

    def raws(seed, noise=True):
        scene = types.SimpleNamespace(
            config=SimulationConfig(preset="tiny", seed=seed, noise=noise), rig=rig,
            exposures={camera.id: 2.0 for camera in rig.cameras},
        )
        return raw_frames(scene, frame, "static", 3)

    first, again, other = raws(0), raws(0), raws(1)
    for cam in first:
        assert first[cam].dtype == np.uint16
        np.testing.assert_array_equal(first[cam], again[cam])
        assert not np.array_equal(first[cam], other[cam])
    # Noise-free frames do not depend on the seed at all.
    for cam, raw in raws(0, noise=False).items():
        np.testing.assert_array_equal(raw, raws(7, noise=False)[cam])


def _digest(folder):
    return {
        p.relative_to(folder).as_posix(): hashlib.sha1(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("raw/*/*.png"))
    }


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "tiny"
    summary = simulate(out, SimulationConfig(preset="tiny", noise=False), progress=False)
    return out, summary


@pytest.mark.slow
def test_tiny_layout_and_store_validation(tiny_run):
    out, summary = tiny_run
    preset = get_preset("tiny")
    static = CaptureStore.open(out / "static")
    static.validate(deep=True)
    assert len(static.frames) == preset.static_frames
    assert len(CaptureStore.open(out / "dynamic").frames) == preset.dynamic_frames
    poses = load_poses(out / "ground_truth" / "static" / "poses.json")
    assert poses.shape == (preset.static_frames, 4, 4)
    check_rigid(poses)
    maps = {
        name: read_exr(out / "ground_truth" / "maps" / f"{name}.exr")
        for name in ("eta", "alpha_s", "rho_sss_bar")
    }
    eta = maps["eta"]["Y"]
    assert 1.38 - 1e-6 <= eta.min() and eta.max() <= 1.48 + 1e-6
    assert len(maps["rho_sss_bar"]) == 6
    assert len(list((out / "ground_truth" / "dynamic" / "meshes").glob("*.ply"))) == preset.dynamic_frames
    recorded = json.loads((out / "simulation.json").read_text())
    assert recorded["config"]["preset"] == "tiny"
    rig = Rig.load(out / "static" / "rig.json")
    assert recorded["exposures"] == {camera.id: camera.exposure for camera in rig.cameras}
    assert all(value > 0 for value in recorded["exposures"].values())
    assert summary["timings"]["total_s"] > 0


@pytest.mark.slow
def test_tiny_raw_demosaic_reproduces_ground_truth(tiny_run):
    import zarr

    out, _ = tiny_run
    store = CaptureStore.open(out / "static")
    truth = zarr.open_group(str(out / "ground_truth" / "observations.zarr"), mode="r")
    for camera in ("pol_upper", "pol_lower"):
        mask = ndimage.binary_erosion(truth[f"static/{camera}/mask"][0], iterations=4)
        stack = store.stack(0, camera)
        i_sss = 2.0 * stack[2]
        expected = truth[f"static/{camera}/i_sss"][0]
        error = np.abs(i_sss - expected)[mask]
        assert np.median(error) / np.median(expected[mask]) < 0.03  # demosaic error of the face pattern
        i_s = stack[0] - stack[2]
        expected_s = truth[f"static/{camera}/i_s"][0]
        assert np.median(np.abs(i_s - expected_s)[mask]) < 0.05 * np.median(expected[mask])


@pytest.mark.slow
def test_tiny_resume_keeps_bytes(tiny_run, monkeypatch):
    out, summary = tiny_run
    before = _digest(out)
    # a finished simulation is returned at once: its scene is not even built
    with monkeypatch.context() as patched:
        patched.setattr(SimulationScene, "build", classmethod(lambda cls, config: pytest.fail("scene built")))
        again = simulate(out, SimulationConfig(preset="tiny", noise=False), progress=False)
    assert _digest(out) == before and again == json.loads(json.dumps(summary))  # as recorded
    # another configuration is refused with one line per differing key
    with pytest.raises(RecordMismatchError) as refused:
        simulate(out, SimulationConfig(preset="tiny", noise=True), progress=False)
    assert refused.value.details == ["config.noise: recorded false, now true"]
    # a frame gone (its completion marker removed): not finished, the frame is rendered again, same bytes
    (out / "static" / "frames" / "000001.json").unlink()
    again = simulate(out, SimulationConfig(preset="tiny", noise=False), progress=False)
    assert _digest(out) == before and (out / "static" / "frames" / "000001.json").is_file()
    assert again["exposures"] == pytest.approx(summary["exposures"])
