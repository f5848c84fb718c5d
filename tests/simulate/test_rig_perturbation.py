"""The perturbed rig of the simulator (``polarface.simulate.rig_perturbation``): its draws, the true rig
behind the nominal one, the sensor's images under it, and, end to end on the tiny preset, captures that
carry the nominal rig.json while the frames and ``ground_truth/rig.json`` are the true rig's."""

from __future__ import annotations

import json

import numpy as np
import pytest

from polarface.capture.rig import Rig, paper_rig
from polarface.capture.store import CaptureStore
from polarface.simulate.pipeline import SimulationConfig, simulate
from polarface.simulate.rig_perturbation import RigPerturbation
from polarface.skin.spectral import FINE_WAVELENGTHS_NM, channel_responses, rig_spectral_parts

RIG = paper_rig(width=64, height=48)


@pytest.mark.parametrize(
    ("kwargs", "argument"),
    [({"seed": -1}, "seed"), ({"seed": 1.5}, "seed"), ({"seed": True}, "seed"),
     ({"seed": 0, "light_position_mm": -1.0}, "light_position_mm"),
     ({"seed": 0, "camera_gain": float("nan")}, "camera_gain"),
     ({"seed": 0, "filter_shift_nm": 100.0}, "filter_shift_nm")],
)
def test_bad_configuration_names_the_argument(kwargs, argument):
    with pytest.raises(ValueError, match=f"argument '{argument}'"):
        RigPerturbation(**kwargs)
    with pytest.raises(ValueError, match="argument 'rig_perturbation'"):
        SimulationConfig(preset="tiny", rig_perturbation={"seed": 1})


def test_the_nominal_rig_is_unchanged():
    nominal = RigPerturbation()
    assert nominal.is_nominal and nominal.true_rig(RIG) is RIG and nominal.draws(RIG) == {}
    np.testing.assert_array_equal(nominal.stereo_mixing(RIG, "stereo0_a"), np.eye(3))
    assert "rig_perturbation" not in SimulationConfig(preset="tiny").to_json()  # older folders resume
    assert RigPerturbation.from_dict(RigPerturbation(seed=4).to_dict()) == RigPerturbation(seed=4)


def test_the_true_rig_is_the_nominal_one_moved_by_its_draws():
    perturbation = RigPerturbation(seed=7)
    true = perturbation.true_rig(RIG)
    draws = perturbation.draws(RIG)
    assert perturbation.draws(RIG) == draws and RigPerturbation(seed=8).draws(RIG) != draws  # seeded
    for nominal, moved, offset, factor in zip(RIG.lights, true.lights, draws["light_offsets_mm"],
                                              draws["light_factors"], strict=True):
        np.testing.assert_allclose(np.subtract(moved.position_mm, nominal.position_mm), offset)
        assert moved.radiant_intensity == pytest.approx(nominal.radiant_intensity * factor)
    offsets = np.asarray(draws["light_offsets_mm"])
    assert 0.5 < offsets.std() < 6.0 and 0.005 < np.std(draws["light_factors"]) < 0.08
    for camera in true.cameras:  # geometry and exposure as designed; gains on the polarization cameras
        nominal = RIG.camera(camera.id)
        assert (camera.K, camera.world_to_camera, camera.exposure) == (nominal.K, nominal.world_to_camera,
                                                                      nominal.exposure)
        expected = draws["camera_gains"].get(camera.id, [1.0, 1.0, 1.0])
        np.testing.assert_allclose(camera.channel_gains, expected)
    parts = rig_spectral_parts(draws["camera_shift_nm"], draws["filter_shift_nm"])
    expected = channel_responses(*parts, FINE_WAVELENGTHS_NM, RIG.spectral.wavelengths_nm)
    np.testing.assert_allclose(true.spectral.channel_responses, expected)
    assert np.abs(np.subtract(true.spectral.channel_responses, RIG.spectral.channel_responses)).max() > 0.01
    assert true.spectral.led_spd == RIG.spectral.led_spd
    assert sorted({d.split(".")[-1] for d in RIG.geometry_differences(true)}) == [
        "channel_gains", "position_mm", "radiant_intensity", "spectral"]
    mixing = perturbation.stereo_mixing(RIG, "stereo2_b")
    assert mixing.shape == (3, 3) and 0.005 < np.abs(mixing - np.eye(3)).mean() < 0.2


def test_a_rig_with_another_spectral_calibration_is_refused():
    data = RIG.model_dump(mode="json")
    data["spectral"]["led_spd"] = [1.0] * len(data["spectral"]["led_spd"])
    with pytest.raises(ValueError, match="default spectral calibration"):
        RigPerturbation(seed=1).true_rig(Rig.model_validate(data))


#: A rig whose only error is its polarization cameras' gains (so that a frame's ratio is the gains).
GAINS_ONLY = RigPerturbation(seed=3, light_position_mm=0.0, light_intensity=0.0, camera_shift_nm=0.0,
                             filter_shift_nm=0.0, stereo_colour=0.0)


@pytest.fixture(scope="module")
def simulations(tmp_path_factory):
    """Noise-free tiny static captures (2 frames) of the nominal rig and of :data:`GAINS_ONLY`'s."""
    outs = {}
    for name, perturbation in (("nominal", RigPerturbation()), ("gains", GAINS_ONLY)):
        outs[name] = tmp_path_factory.mktemp(name)
        config = SimulationConfig(preset="tiny", sequences=("static",), static_frames=2, noise=False,
                                  rig_perturbation=perturbation)
        simulate(outs[name], config, progress=False)
    return outs


@pytest.mark.slow
def test_the_captures_carry_the_nominal_rig_and_the_frames_are_the_true_ones(simulations):
    out = simulations["gains"]
    captured = Rig.load(out / "static" / "rig.json")
    nominal = Rig.load(simulations["nominal"] / "static" / "rig.json")
    true = Rig.load(out / "ground_truth" / "rig.json")
    assert captured.geometry_differences(nominal) == []  # the nominal rig (the exposures may differ)
    assert not (simulations["nominal"] / "ground_truth" / "rig.json").exists()
    assert true.model_dump() == GAINS_ONLY.true_rig(captured).model_dump()  # the exposures kept
    assert [d.split(".")[-1] for d in captured.geometry_differences(true)] == ["channel_gains"] * 2
    summary = json.loads((out / "simulation.json").read_text())
    assert summary["rig_perturbation"] == json.loads(json.dumps(GAINS_ONLY.draws(captured)))
    # the nominal rig divides by gains of 1, so the stored images are the true ones times each colour's
    # gain: against the nominal rig's frame, the ratio of the bright pixels is the gain (12-bit rounding)
    for camera_id in ("pol_upper", "pol_lower"):
        gains = np.asarray(true.camera(camera_id).channel_gains)
        assert np.abs(gains - 1.0).max() > 0.01
        stacks = [CaptureStore.open(simulations[name] / "static").stack(1, camera_id)
                  for name in ("gains", "nominal")]
        bright = stacks[1] > 0.05
        for colour in range(3):
            ratio = stacks[0][..., colour][bright[..., colour]] / stacks[1][..., colour][bright[..., colour]]
            assert np.median(ratio) == pytest.approx(gains[colour], abs=2e-3)
