"""The simulated non-ideal sensor: configuration, true models, rig.json with and without the calibration,
and, end to end on the tiny preset, the capture store's Stokes/DoP against the simulator's ground truth."""

from __future__ import annotations

import json
import math
import types

import numpy as np
import pytest
import zarr
from scipy import ndimage

from polarface.capture.demosaic import demosaic_camera
from polarface.capture.rig import Rig, paper_rig
from polarface.capture.store import CaptureStore
from polarface.io import read_png
from polarface.optics.analyzer import AnalyzerModel
from polarface.simulate.analyzers import SimulatedAnalyzers
from polarface.simulate.frames import raw_frames
from polarface.simulate.pipeline import SimulationConfig, simulate

NON_IDEAL = SimulatedAnalyzers(extinction_ratio=100.0, angle_error_deg=1.0, seed=3)


@pytest.mark.parametrize(
    ("kwargs", "argument"),
    [
        ({"extinction_ratio": 1.0}, "extinction_ratio"),
        ({"extinction_ratio": float("nan")}, "extinction_ratio"),
        ({"extinction_ratio": (100.0, 50.0)}, "extinction_ratio"),
        ({"extinction_ratio": "high"}, "extinction_ratio"),
        ({"angle_error_deg": -1.0}, "angle_error_deg"),
        ({"angle_error_deg": float("inf")}, "angle_error_deg"),
        ({"angle_error_deg": (1.0, 2.0)}, "angle_error_deg"),
        ({"angle_error_deg": (0.0, 0.0, 30.0, 0.0)}, "angle_error_deg"),
        ({"seed": -1}, "analyzer_seed"),
        ({"seed": 1.5}, "analyzer_seed"),
        ({"calibration_supplied": "yes"}, "calibration_supplied"),
    ],
)
def test_bad_configuration_names_the_argument(kwargs, argument):
    with pytest.raises(ValueError, match=f"argument '{argument}'"):
        SimulatedAnalyzers(**kwargs)
    with pytest.raises(ValueError, match="argument 'analyzers'"):
        SimulationConfig(preset="tiny", analyzers={"extinction_ratio": 100})


def test_true_models():
    assert SimulatedAnalyzers().is_ideal and SimulatedAnalyzers(extinction_ratio=math.inf).is_ideal
    assert not NON_IDEAL.is_ideal
    rig = paper_rig(width=64, height=48)
    models = NON_IDEAL.camera_models(rig)
    assert sorted(models) == ["pol_lower", "pol_upper"]
    again = SimulatedAnalyzers(extinction_ratio=100.0, angle_error_deg=1.0, seed=3)
    assert models == again.camera_models(rig)
    other = SimulatedAnalyzers(extinction_ratio=100.0, angle_error_deg=1.0, seed=4).camera_models(rig)
    assert other["pol_upper"][0].angles_deg != models["pol_upper"][0].angles_deg
    errors = np.array([[m.angles_deg for m in ms] for ms in models.values()]) - (0.0, 45.0, 90.0, 135.0)
    assert 0.2 < errors.std() < 3.0 and len({m.angles_deg for ms in models.values() for m in ms}) == 6
    fixed = SimulatedAnalyzers(extinction_ratio=(300.0, 200.0, 80.0), angle_error_deg=(0.5, -0.5, 0.0, 1.0))
    upper = fixed.camera_models(rig)["pol_upper"]
    assert [m.extinction_ratio for m in upper] == [300.0, 200.0, 80.0]
    assert upper[2].angles_deg == (0.5, 44.5, 90.0, 136.0)
    assert fixed.models(0, colour_count=1) == (AnalyzerModel(300.0, (0.5, 44.5, 90.0, 136.0)),)


def test_rig_json_with_and_without_the_calibration(tmp_path):
    rig = paper_rig(width=64, height=48)
    supplied = NON_IDEAL.rig_for_folder(rig)
    supplied.save(tmp_path / "rig.json")
    loaded = Rig.load(tmp_path / "rig.json")
    for camera_id, models in NON_IDEAL.camera_models(rig).items():
        camera = loaded.camera(camera_id)
        assert tuple(camera.analyzer_model(c) for c in "RGB") == models
    assert all(c.analyzer is None for c in loaded.cameras if c.role == "stereo")
    not_supplied = SimulatedAnalyzers(extinction_ratio=100.0, angle_error_deg=1.0, calibration_supplied=False)
    assert not_supplied.rig_for_folder(rig) == rig and SimulatedAnalyzers().rig_for_folder(rig) == rig
    record = not_supplied.record(rig)
    assert record["calibration_supplied"] is False and record["ideal"] is False
    assert record["analyzers"]["pol_lower"]["B"]["extinction_ratio"] == 100.0
    assert json.loads(json.dumps(record)) == record


def test_configuration_record_keeps_older_folders():
    """An ideal sensor's configuration is recorded as before (older simulation folders resume); a
    non-ideal one is recorded with its analyzers."""
    assert "analyzers" not in SimulationConfig(preset="tiny").to_json()
    recorded = SimulationConfig(preset="tiny", analyzers=NON_IDEAL).to_json()
    assert recorded["analyzers"] == {"extinction_ratio": 100.0, "angle_error_deg": 1.0, "seed": 3,
                                     "calibration_supplied": True}


def test_raw_frames_pass_through_the_analyzers():
    """Noise-free raw frames: a non-ideal sensor's differ; its calibrated demosaic gives the ideal one's."""
    rig = paper_rig(width=64, height=48)
    rng = np.random.default_rng(5)
    views = {}
    for camera in rig.cameras:
        shape = (camera.height, camera.width)
        if camera.role == "polarimetric":
            s0 = rng.uniform(0.2, 0.4, (*shape, 3))
            s1 = 0.5 * s0  # smooth is not needed: compare at the super-pixel level below
            images = {"i0": (s0 + s1) / 2, "i45": s0 / 2, "i90": (s0 - s1) / 2, "i135": s0 / 2}
            images = {k: np.full_like(v, float(v.mean())).astype(np.float32) for k, v in images.items()}
        else:
            images = {"s0": rng.uniform(0.05, 0.2, (*shape, 6)).astype(np.float32)}
        views[camera.id] = types.SimpleNamespace(images=images)
    frame = types.SimpleNamespace(views=views)

    def raws(analyzers):
        config = SimulationConfig(preset="tiny", noise=False, analyzers=analyzers)
        exposures = {camera.id: 1.0 for camera in rig.cameras}
        scene = types.SimpleNamespace(config=config, rig=rig, exposures=exposures)
        return raw_frames(scene, frame, "static", 0)

    ideal, other = raws(SimulatedAnalyzers()), raws(NON_IDEAL)
    calibrated_rig = NON_IDEAL.rig_for_folder(rig)
    for camera in rig.polarimetric_cameras():
        assert not np.array_equal(ideal[camera.id], other[camera.id])
        expected = demosaic_camera(ideal[camera.id], camera).intensities
        got = demosaic_camera(other[camera.id], calibrated_rig.camera(camera.id)).intensities
        np.testing.assert_allclose(got, expected, atol=2e-3)  # 12-bit quantisation, amplified ~1/d
    for camera in rig.cameras:
        if camera.role == "stereo":
            np.testing.assert_array_equal(ideal[camera.id], other[camera.id])


# ------------------------------------------------------------------------------------------------------------
# End to end on the tiny preset


@pytest.fixture(scope="module")
def simulations(tmp_path_factory):
    """The tiny preset's static sequence (2 frames, noise) with an ideal sensor and with ER 100 and
    1-deg (sigma) analyzer errors whose calibration is supplied; same noise seed."""
    root = tmp_path_factory.mktemp("sensor_sims")
    base = {"preset": "tiny", "sequences": ("static",), "static_frames": 2, "seed": 7}
    for name, analyzers in (("ideal", SimulatedAnalyzers()), ("calibrated", NON_IDEAL)):
        simulate(root / name, SimulationConfig(**base, analyzers=analyzers), progress=False)
    return root


def _stokes_samples(sim, store: CaptureStore, ideal_formulas: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Stacked ``(3, N, 3)`` linear Stokes of the capture store's stacks (``ideal_formulas``: of its raw
    frames demosaiced as if the analyzers were ideal) and of the noise-free ground truth, at interior
    unsaturated head pixels of both cameras and frames."""
    measured, truth = [], []
    group = zarr.open_group(sim / "ground_truth" / "observations.zarr", mode="r")
    for camera in store.rig.polarimetric_cameras():
        for frame in range(2):
            arrays = group[f"static/{camera.id}"]
            gt = {k: np.asarray(arrays[k][frame]) for k in ("i_sss", "i_zeta", "i_s", "mask")}
            s0 = gt["i_s"] + gt["i_sss"]
            lit = s0.min(-1) > 0.05 * s0[gt["mask"]].max()
            unsaturated = (store.mask(frame, camera.id) & 1) == 0
            valid = ndimage.binary_erosion(gt["mask"], iterations=4) & unsaturated & lit
            if ideal_formulas:
                raw = read_png(sim / "static" / "raw" / camera.id / f"{frame:06d}.png")
                stack = demosaic_camera(raw, camera.model_copy(update={"analyzer": None})).intensities
            else:
                stack = store.stack(frame, camera.id)
            i0, i45, i90, i135 = stack
            measured.append(np.stack([0.5 * (i0 + i45 + i90 + i135), i0 - i90, i45 - i135])[:, valid])
            truth.append(np.stack([s0, gt["i_s"], -gt["i_zeta"]])[:, valid])
    return np.concatenate(measured, axis=1), np.concatenate(truth, axis=1)


def _s1_gain(measured: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per colour, the least-squares gain of the measured s1 on the true s1 (noise averages out)."""
    return (measured[1] * truth[1]).sum(0) / (truth[1] ** 2).sum(0)


def _dop_bias(measured: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per colour, the mean of measured minus true DoP."""
    dop = np.hypot(measured[1], measured[2]) / measured[0]
    return (dop - np.hypot(truth[1], truth[2]) / truth[0]).mean(0)


@pytest.mark.slow
def test_calibrated_sensor_measures_what_an_ideal_one_does(simulations):
    ideal_store = CaptureStore.open(simulations / "ideal" / "static")
    store = CaptureStore.open(simulations / "calibrated" / "static")
    samples = {
        "ideal": _stokes_samples(simulations / "ideal", ideal_store),
        "calibrated": _stokes_samples(simulations / "calibrated", store),
        "ideal formulas": _stokes_samples(simulations / "calibrated", store, ideal_formulas=True),
    }
    gain = {name: _s1_gain(*pair) for name, pair in samples.items()}
    bias = {name: _dop_bias(*pair) for name, pair in samples.items()}
    # the calibrated sensor's Stokes and DoP equal the ideal sensor's within noise ...
    np.testing.assert_allclose(gain["calibrated"], gain["ideal"], atol=0.008)
    np.testing.assert_allclose(bias["calibrated"], bias["ideal"], atol=0.0012)
    # ... while the ideal formulas on the same raw frames lose ~2 % of the polarized part (d = 0.98)
    assert np.all(gain["ideal formulas"] < gain["ideal"] - 0.012), gain
    assert np.all(bias["ideal formulas"] < bias["ideal"] - 0.0008), bias
    # rig.json carries the true analyzers; simulation.json and the manifest record them
    truth_models = NON_IDEAL.camera_models(store.rig)
    for camera_id, models in truth_models.items():
        assert tuple(store.rig.camera(camera_id).analyzer_model(c) for c in "RGB") == models
    summary = json.loads((simulations / "calibrated" / "simulation.json").read_text())
    assert summary["sensor"]["calibration_supplied"] is True
    assert summary["sensor"]["analyzers"] == NON_IDEAL.record(store.rig)["analyzers"]
    manifest = json.loads((store.root / "manifest.json").read_text())
    assert sorted(manifest["analyzers"]) == ["pol_lower", "pol_upper"]
    ideal_summary = json.loads((simulations / "ideal" / "simulation.json").read_text())
    assert ideal_summary["sensor"]["ideal"] is True and "analyzers" not in ideal_summary["config"]
    assert "analyzers" not in json.loads((ideal_store.root / "manifest.json").read_text())
    # the store's stacks are the calibrated demosaic of its raw frames
    raw = read_png(simulations / "calibrated" / "static" / "raw" / "pol_upper" / "000000.png")
    expected = demosaic_camera(raw, store.rig.cameras[0]).intensities
    np.testing.assert_array_equal(store.stack(0, "pol_upper"), expected)


def test_sphere_capture_with_a_calibrated_sensor(tmp_path):
    """The sphere-cap capture (noise-free) through ER 100 analyzers with fixed orientation offsets,
    calibration supplied: rig.json carries it, and inside the silhouette its stored stacks give the
    ideal sensor's polarized part (the ideal formulas on the same raw frames lose 1 - d = 2 %)."""
    from polarface.simulate.sphere_capture import SphereCaptureConfig, make_sphere_capture

    small = {"width": 64, "height": 48, "texture_resolution": 16, "frames": 2}
    sensor = SimulatedAnalyzers(extinction_ratio=100.0, angle_error_deg=(1.0, -1.0, 0.5, 1.0))
    ideal = make_sphere_capture(tmp_path / "ideal", SphereCaptureConfig(**small))
    other = make_sphere_capture(tmp_path / "other", SphereCaptureConfig(**small, analyzers=sensor))
    camera = other["rig"].camera("pol_lower")
    assert camera.analyzer_model("G") == AnalyzerModel(100.0, (1.0, 44.0, 90.5, 136.0))
    expected = CaptureStore.open(ideal["capture"]).stack(1, "pol_lower")
    got = CaptureStore.open(other["capture"]).stack(1, "pol_lower")
    raw = read_png(other["capture"] / "raw" / "pol_lower" / "000001.png")
    naive = demosaic_camera(raw, camera.model_copy(update={"analyzer": None})).intensities
    s0 = expected.sum(axis=(0, -1))
    inside = ndimage.binary_erosion(s0 > 0.2 * s0.max(), iterations=4)  # away from the silhouette's edge

    def s1_ratio(stack: np.ndarray) -> np.ndarray:
        return (stack[0] - stack[2])[inside].sum(0) / (expected[0] - expected[2])[inside].sum(0)

    np.testing.assert_allclose(s1_ratio(got), 1.0, atol=0.005)
    assert np.all(s1_ratio(naive) < 0.99), s1_ratio(naive)
    # per pixel the two agree but where demosaicing errs (highlights): the correction mixes the four
    # analyzer images, each interpolated from its own lattice
    assert np.median(np.abs(got - expected)[:, inside]) < 5e-4
