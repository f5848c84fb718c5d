"""Non-ideal analyzers applied by demosaicing: reference values, the Stokes round trip, per-colour models,
bit-identical ideal captures, what the capture store records, and bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from polarface.capture.analyzers import (
    analyzer_record,
    applied_analyzers,
    camera_analyzer_models,
    ideal_analyzer_intensities,
    measured_analyzer_intensities,
)
from polarface.capture.demosaic import demosaic, demosaic_camera
from polarface.capture.observations import observations_from_intensities
from polarface.capture.rig import Rig, paper_rig
from polarface.capture.sensor import mosaic, simulate_raw
from polarface.capture.stokes_images import StokesOptions, write_stokes_images
from polarface.capture.store import CaptureStore
from polarface.capture.synthetic import stokes_pattern
from polarface.io import read_exr, write_png
from polarface.optics.analyzer import AnalyzerModel

ANGLES = (0.7, 44.2, 91.0, 134.5)


def _malus(stokes: np.ndarray, ratio: float, angles_deg) -> np.ndarray:
    """Independent reference: ``I = (k1 + k2)/2 s0 + (k1 - k2)/2 (cos 2a s1 + sin 2a s2)`` with
    ``k1 = ER / (ER + 1)``, ``k2 = 1 / (ER + 1)`` (Collett 2005), stacked on axis 0."""
    k1, k2 = ratio / (ratio + 1.0), 1.0 / (ratio + 1.0)
    return np.stack([
        0.5 * (k1 + k2) * stokes[..., 0]
        + 0.5 * (k1 - k2) * (np.cos(2 * a) * stokes[..., 1] + np.sin(2 * a) * stokes[..., 2])
        for a in np.radians(np.asarray(angles_deg))
    ])


def _ideal(stokes: np.ndarray) -> np.ndarray:
    s0, s1, s2 = stokes[..., 0], stokes[..., 1], stokes[..., 2]
    return 0.5 * np.stack([s0 + s1, s0 + s2, s0 - s1, s0 - s2])


def _stokes(shape, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    s0 = rng.uniform(0.2, 1.0, shape)
    dop = rng.uniform(0.0, 1.0, shape)
    angle = rng.uniform(0, np.pi, shape)
    return np.stack([s0, s0 * dop * np.cos(2 * angle), s0 * dop * np.sin(2 * angle)], axis=-1)


def test_reference_values_measured_to_ideal():
    """The measured intensities of a known Stokes field map to the ideal analyzers' (Malus) exactly."""
    stokes = _stokes((6, 5))
    model = AnalyzerModel(50.0, ANGLES)
    measured = _malus(stokes, 50.0, ANGLES)
    np.testing.assert_allclose(ideal_analyzer_intensities(measured, model), _ideal(stokes), atol=2e-6)
    np.testing.assert_allclose(measured_analyzer_intensities(_ideal(stokes), model), measured, atol=2e-6)
    # one hand value: fully polarized along 0 deg behind ER 3 analyzers at exactly 0/45/90/135 deg
    one = measured_analyzer_intensities(np.array([1.0, 0.5, 0.0, 0.5]).reshape(4, 1, 1), AnalyzerModel(3.0))
    np.testing.assert_allclose(one.ravel(), [0.75, 0.5, 0.25, 0.5], atol=1e-7)


def test_physics_dop_is_restored_and_energy_kept():
    """Finite ER scales the measured DoP by d = (ER-1)/(ER+1); the correction restores it and keeps s0."""
    stokes = _stokes((40, 3), seed=1)
    model = AnalyzerModel(20.0, (0.0, 45.0, 90.0, 135.0))
    measured = _malus(stokes, 20.0, model.angles_deg)
    naive = observations_from_intensities(*measured)["dop"]
    truth = np.hypot(stokes[..., 1], stokes[..., 2]) / stokes[..., 0]
    np.testing.assert_allclose(naive, model.diattenuation * truth, rtol=1e-5, atol=1e-6)
    corrected = ideal_analyzer_intensities(measured, model)
    np.testing.assert_allclose(observations_from_intensities(*corrected)["dop"], truth, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(corrected.sum(0), measured.sum(0), rtol=1e-5)


def test_per_colour_models_and_ideal_passthrough():
    stokes = _stokes((7, 4, 3), seed=2)
    models = (AnalyzerModel(30.0, ANGLES), AnalyzerModel(), AnalyzerModel(200.0, (-1.0, 45.0, 89.0, 136.0)))
    measured = np.stack([_malus(stokes[..., c, :], m.extinction_ratio, m.angles_deg) if not m.is_ideal
                         else _ideal(stokes[..., c, :]) for c, m in enumerate(models)], axis=-1)
    np.testing.assert_allclose(ideal_analyzer_intensities(measured, models), _ideal(stokes), atol=3e-6)
    data = measured.astype(np.float32)
    assert ideal_analyzer_intensities(data, (AnalyzerModel(),) * 3) is data  # ideal: bit for bit, no copy
    assert measured_analyzer_intensities(data, AnalyzerModel()) is data


def test_bad_input_names_the_argument():
    with pytest.raises(ValueError, match="argument 'intensities'"):
        ideal_analyzer_intensities(np.zeros((3, 4, 4)), AnalyzerModel(10.0))
    with pytest.raises(ValueError, match="argument 'models'"):
        ideal_analyzer_intensities(np.zeros((4, 4, 4, 3)), (AnalyzerModel(10.0), AnalyzerModel()))


def _colour_rig(analyzer=None) -> Rig:
    rig = paper_rig(width=64, height=48)
    data = rig.model_dump(mode="json")
    data["cameras"][0]["analyzer"] = analyzer
    return Rig.model_validate(data)


def test_demosaic_camera_applies_the_rig_calibration():
    """A smooth field behind non-ideal analyzers: the calibrated camera's DoP matches an ideal sensor's
    (same demosaicing error), the ideal formulas on the same raw frame are biased by about d."""
    per_colour = {"R": {"extinction_ratio": 40.0, "analyzer_angles_deg": list(ANGLES)},
                  "G": {"extinction_ratio": 60.0}, "B": {"extinction_ratio": 25.0}}
    rig = _colour_rig(per_colour)
    camera = rig.cameras[0]
    stokes = stokes_pattern("smooth", camera.height, camera.width, colour=True)  # (H, W, colour, 3)
    models = camera_analyzer_models(camera)
    ideal = _ideal(stokes)  # (4, H, W, 3)
    measured = measured_analyzer_intensities(ideal.astype(np.float32), models)
    raw = simulate_raw(mosaic(*measured, sensor=camera.sensor), noiseless=True)
    ideal_raw = simulate_raw(mosaic(*ideal, sensor=camera.sensor), noiseless=True)
    reference = observations_from_intensities(*demosaic(ideal_raw, camera.sensor, bit_depth=12).intensities)
    inner = (slice(8, -8), slice(8, -8))
    calibrated = observations_from_intensities(*demosaic_camera(raw, camera).intensities)["dop"]
    naive = observations_from_intensities(*demosaic(raw, camera.sensor, bit_depth=12).intensities)["dop"]
    assert np.abs(calibrated - reference["dop"])[inner].max() < 0.002
    bias = (naive - reference["dop"])[inner].mean(axis=(0, 1))
    assert np.all(bias < -0.008), bias  # DoP ~0.3 times 1 - d = 0.05 / 0.03 / 0.08
    assert analyzer_record(camera)["G"] == {
        "extinction_ratio": 60.0, "analyzer_angles_deg": [0.0, 45.0, 90.0, 135.0]
    }


def test_ideal_camera_is_bit_identical_and_unrecorded(tmp_path):
    rig = _colour_rig(None)
    camera = rig.cameras[0]
    raw = simulate_raw(np.full((camera.height, camera.width), 0.3), noiseless=True)
    np.testing.assert_array_equal(
        demosaic_camera(raw, camera).intensities, demosaic(raw, camera.sensor, bit_depth=12).intensities
    )
    assert analyzer_record(camera) is None and applied_analyzers(rig) is None
    store = _store(tmp_path / "ideal", rig, raw)
    assert "analyzers" not in json.loads((store.root / "manifest.json").read_text())
    assert "analyzers" not in json.loads((store.root / "frames" / "000000.json").read_text())


def _store(path, rig: Rig, raw: np.ndarray) -> CaptureStore:
    raws = {c.id: raw for c in rig.polarimetric_cameras()}
    stereo = [c for c in rig.cameras if c.role == "stereo"]
    raws.update({c.id: np.zeros((c.height, c.width, 3), np.uint16) for c in stereo})
    store = CaptureStore.create(path, rig)
    store.add_frame(0, 0.0, raws)
    store.finalize()
    return store


def test_store_records_and_applies_the_analyzers(tmp_path):
    calibration = {"extinction_ratio": 50.0, "analyzer_angles_deg": list(ANGLES)}
    rig = _colour_rig(calibration)
    camera = rig.cameras[0]
    raw = simulate_raw(np.full((camera.height, camera.width), 0.3), noiseless=True)
    store = _store(tmp_path / "store", rig, raw)
    manifest = json.loads((store.root / "manifest.json").read_text())
    assert manifest["analyzers"] == {camera.id: calibration}
    marker = json.loads((store.root / "frames" / "000000.json").read_text())
    assert marker["analyzers"] == {camera.id: calibration}
    np.testing.assert_array_equal(store.stack(0, camera.id), demosaic_camera(raw, camera).intensities)
    CaptureStore.open(store.root)  # valid


def test_stokes_images_with_a_rig_camera(tmp_path):
    rig = _colour_rig({"extinction_ratio": 10.0})
    rig.save(tmp_path / "rig.json")
    camera = rig.cameras[0]
    ideal = _ideal(np.broadcast_to([0.8, 0.4, 0.0], (camera.height, camera.width, 3, 3)).copy())
    measured = measured_analyzer_intensities(ideal.astype(np.float32), AnalyzerModel(10.0))
    write_png(tmp_path / "raw.png", simulate_raw(mosaic(*measured, sensor=camera.sensor), noiseless=True),
              bit_depth=16)
    options = StokesOptions(bit_depth=12, rig=tmp_path / "rig.json", camera=camera.id)
    summary = write_stokes_images(tmp_path / "raw.png", tmp_path / "out", camera.sensor, options)
    assert summary["analyzer"] == {"extinction_ratio": 10.0, "analyzer_angles_deg": [0.0, 45.0, 90.0, 135.0]}
    assert summary["median_dop"] == pytest.approx(0.5, abs=0.002)  # naive: 0.5 * 9/11 = 0.41
    naive = write_stokes_images(
        tmp_path / "raw.png", tmp_path / "naive", camera.sensor, StokesOptions(bit_depth=12)
    )
    assert naive["median_dop"] == pytest.approx(0.5 * 9 / 11, abs=0.002)
    assert read_exr(tmp_path / "out" / "dop.exr") is not None
    with pytest.raises(ValueError, match="'rig' and 'camera'"):
        StokesOptions(rig=tmp_path / "rig.json")
    with pytest.raises(ValueError, match="nope"):
        write_stokes_images(tmp_path / "raw.png", tmp_path / "x", camera.sensor,
                            StokesOptions(bit_depth=12, rig=tmp_path / "rig.json", camera="nope"))
    with pytest.raises(ValueError, match="argument 'camera'"):
        write_stokes_images(tmp_path / "raw.png", tmp_path / "x", "mono-polarization",
                            StokesOptions(bit_depth=12, rig=tmp_path / "rig.json", camera=camera.id))


@pytest.mark.parametrize(
    ("analyzer", "field"),
    [
        ({"extinction_ratio": 0.5}, "extinction_ratio"),
        ({"extinction_ratio": 100, "analyzer_angles_deg": [0, 45, 90]}, "analyzer_angles_deg"),
        ({"analyzer_angles_deg": [45, 0, 90, 135]}, "analyzer_angles_deg"),
        ({"R": {"extinction_ratio": "high"}}, "extinction_ratio"),
        ({"extinction": 100}, "extinction"),
        ("ideal", "analyzer"),
    ],
)
def test_bad_rig_analyzer_names_the_field(tmp_path, analyzer, field):
    data = paper_rig(width=64, height=48).model_dump(mode="json")
    data["cameras"][0]["analyzer"] = analyzer
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"rig\.json") as info:
        Rig.load(path)
    assert "cameras[0].analyzer" in str(info.value) and field in str(info.value)
