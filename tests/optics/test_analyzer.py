"""Non-ideal analyzers: pypolar's Mueller polarizers and polanalyser's least-squares Stokes as oracles."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from polarface.optics import AnalyzerModel, intensities_from_stokes, stokes_from_intensities

pypolar_mueller = pytest.importorskip("pypolar.mueller")
polanalyser = pytest.importorskip("polanalyser")

ANGLES = (0.7, 44.2, 91.0, 134.5)


def _pypolar_rows(extinction_ratio: float, angles_deg) -> np.ndarray:
    """``(4, 3)`` linear rows of a partial polarizer ``k1 P(a) + k2 P(a + 90)`` (k1 + k2 = 1), pypolar."""
    k1 = extinction_ratio / (extinction_ratio + 1.0)
    k2 = 1.0 - k1
    rows = []
    for angle in np.deg2rad(angles_deg):
        mueller = k1 * pypolar_mueller.op_linear_polarizer(angle) + k2 * pypolar_mueller.op_linear_polarizer(
            angle + math.pi / 2
        )
        rows.append(np.asarray(mueller, dtype=np.float64)[0, :3])
    return np.stack(rows)


def test_analysis_matrix_equals_pypolar_partial_polarizers():
    model = AnalyzerModel(120.0, ANGLES)
    np.testing.assert_allclose(model.analysis_matrix(), _pypolar_rows(120.0, ANGLES), atol=1e-12)


def test_reference_value_of_one_analyzer_row():
    # ER 9 -> d = 0.8; a = 15 deg: I = 0.5 (s0 + 0.8 (cos 30 deg s1 + sin 30 deg s2)).
    row = AnalyzerModel(9.0, (15.0, 45.0, 90.0, 135.0)).analysis_matrix()[0]
    np.testing.assert_allclose(row, [0.5, 0.2 * math.sqrt(3.0), 0.2], atol=1e-12)


def test_least_squares_stokes_equals_polanalyser_calcstokes():
    rng = np.random.default_rng(3)
    model = AnalyzerModel(60.0, ANGLES)
    k1 = 60.0 / 61.0
    muellers = [
        (k1 * polanalyser.polarizer(a) + (1 - k1) * polanalyser.polarizer(a + math.pi / 2))[:3, :3]
        for a in np.deg2rad(ANGLES)
    ]
    intensities = rng.uniform(0.1, 1.0, size=(5, 7, 4))
    reference = polanalyser.calcStokes(list(np.moveaxis(intensities, -1, 0)), muellers)  # (5, 7, 3)
    np.testing.assert_allclose(model.stokes(intensities), reference, rtol=1e-9, atol=1e-12)


def test_ideal_model_reduces_to_the_textbook_formulas():
    stokes = torch.tensor([[1.0, 0.3, -0.2], [0.5, -0.1, 0.4]], dtype=torch.float64)
    intensities = intensities_from_stokes(stokes)
    ideal = AnalyzerModel()
    assert ideal.is_ideal and ideal.diattenuation == 1.0
    torch.testing.assert_close(ideal.measure(stokes), intensities)
    torch.testing.assert_close(ideal.stokes(intensities), stokes_from_intensities(*intensities.unbind(-1)))
    # For ideal analyzers the map is the projection onto consistent intensities (I0 + I90 = I45 + I135).
    projector = ideal.to_ideal_matrix()
    np.testing.assert_allclose(projector @ projector, projector, atol=1e-12)
    np.testing.assert_allclose(projector @ intensities.numpy().T, intensities.numpy().T, atol=1e-12)


def test_to_ideal_undoes_the_sensor_so_dop_and_aolp_are_unbiased():
    model = AnalyzerModel(80.0, ANGLES)
    stokes = np.array([[1.0, 0.6, 0.3], [2.0, -0.4, 1.1], [0.3, 0.0, 0.0]])
    measured = model.measure(stokes)
    np.testing.assert_allclose(model.stokes(measured), stokes, atol=1e-12)
    np.testing.assert_allclose(model.to_ideal(measured), intensities_from_stokes(stokes), atol=1e-12)
    np.testing.assert_allclose(model.from_ideal(intensities_from_stokes(stokes)), measured, atol=1e-12)
    # The ideal formulas applied to the raw intensities read a DoP that is too low (the bias fixed here).
    naive = stokes_from_intensities(*np.moveaxis(measured, -1, 0))
    dop = np.hypot(stokes[:2, 1], stokes[:2, 2]) / stokes[:2, 0]
    naive_dop = np.hypot(naive[:2, 1], naive[:2, 2]) / naive[:2, 0]
    assert np.all(naive_dop < dop - 1e-3)


def test_physics_malus_energy_and_dop_bounds():
    rng = np.random.default_rng(0)
    model = AnalyzerModel(25.0, ANGLES)
    directions = rng.normal(size=(200, 2))
    dop = rng.uniform(0, 1, size=200)
    stokes = np.concatenate([np.ones((200, 1)), dop[:, None] * directions / np.linalg.norm(directions, axis=1,
                                                                                             keepdims=True)],
                            axis=1)
    measured = model.measure(stokes)
    assert np.all(measured >= 0) and np.all(measured <= stokes[:, :1])  # a passive element
    # Unpolarized light passes half through every analyzer, whatever its extinction ratio.
    np.testing.assert_allclose(model.measure(np.array([1.0, 0.0, 0.0])), np.full(4, 0.5), atol=1e-12)
    # Fully polarized light along an analyzer: Malus maximum k1 = ER / (ER + 1).
    along = np.array([1.0, math.cos(2 * math.radians(ANGLES[0])), math.sin(2 * math.radians(ANGLES[0]))])
    assert model.measure(along)[0] == pytest.approx(25.0 / 26.0)


def test_gradcheck_float64():
    model = AnalyzerModel(40.0, ANGLES)
    intensities = torch.rand(3, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(model.to_ideal, (intensities,))
    assert torch.autograd.gradcheck(model.stokes, (intensities,))


@pytest.mark.parametrize(("kwargs", "needle"), [
    ({"extinction_ratio": 1.0}, "extinction_ratio must be > 1"),
    ({"extinction_ratio": float("nan")}, "extinction_ratio must be > 1"),
    ({"angles_deg": (0.0, 45.0, 90.0)}, "4 finite angles"),
    ({"angles_deg": (45.0, 0.0, 90.0, 135.0)}, "within 22.5 deg"),
])
def test_bad_model_arguments(kwargs, needle):
    with pytest.raises(ValueError, match=needle):
        AnalyzerModel(**kwargs)


def test_dict_round_trip_and_bad_payloads():
    model = AnalyzerModel.from_dict({"extinction_ratio": 100, "analyzer_angles_deg": [1, 46, 89, 134]})
    assert AnalyzerModel.from_dict(model.to_dict()) == model
    assert AnalyzerModel.from_dict(None).is_ideal and AnalyzerModel.from_dict({}).is_ideal
    with pytest.raises(ValueError, match="polarizer: unknown field"):
        AnalyzerModel.from_dict({"extinction": 3})
    with pytest.raises(ValueError, match="polarizer: extinction_ratio must be > 1"):
        AnalyzerModel.from_dict({"extinction_ratio": 0.5})
    with pytest.raises(ValueError, match="last axis of 4"):
        model.to_ideal(np.zeros((3, 3)))
