"""The model variants (``polarface.inverse.polarimetric.variants``) and the configuration they rest on:
a map held at a fixed value is not optimised, a homogeneous map is fitted in two passes and ends at one
value over the face (the first pass's median), a clustered map takes one value per cluster (the
alternating passes' medians), and bad options are named (a fixed map on one texel: ``test_fit.py``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from polarface.inverse.polarimetric import (
    MODEL_VARIANTS,
    PolarimetricConfig,
    fit_polarimetric,
    model_fit_options,
    model_name,
)
from polarimetric_reference import sphere_unwrap

RES, PATCH = 48, 8
CONFIG = PolarimetricConfig(iterations=8, patch=PATCH)


def test_the_registry_and_its_options():
    assert next(iter(MODEL_VARIANTS)) == "paper" and MODEL_VARIANTS["paper"].fit_options == {}
    assert set(MODEL_VARIANTS) == {
        "paper", "no-single-scattering", "homogeneous-ior", "homogeneous-ior-no-single-scattering",
        "riviere2020", "hwang2022",
    }
    for variant in MODEL_VARIANTS.values():
        config = PolarimetricConfig(**model_fit_options(variant.name))  # each a valid configuration
        assert variant.description and model_name(config) == variant.name
    assert model_name(PolarimetricConfig(homogeneous=("alpha_s",))) is None
    assert model_fit_options("riviere2020", {"iterations": 5}) == {
        "iterations": 5, "lobes": "one", "homogeneous": ("eta", "alpha_s"),
    }
    with pytest.raises(ValueError, match=r"'--model'.*got 'hwang'"):
        model_fit_options("hwang")
    with pytest.raises(ValueError, match=r"no-single-scattering.*lobes='one'.*'two'"):
        model_fit_options("no-single-scattering", {"lobes": "two"})


@pytest.mark.parametrize(
    "options,match",
    [
        ({"homogeneous": ("rho_s",)}, "homogeneous"),
        ({"homogeneous": ("eta", "eta")}, "homogeneous"),
        ({"fixed_eta": 3.0}, "fixed_eta"),
        ({"fixed_alpha_s": float("nan")}, "fixed_alpha_s"),
        ({"fixed_eta": 1.4, "homogeneous": ("eta",)}, "either fitted homogeneous or fixed"),
        ({"fixed_alpha_s": 0.3, "refine_lobes_iterations": 3}, "refine_lobes_iterations"),
        ({"clustered": ("rho_sss_bar",)}, "'clustered'"),
        ({"held": ("eta", "eta")}, "'held'"),
        ({"clusters": 0}, "'clusters'"),
        ({"cluster_rounds": -1}, "'cluster_rounds'"),
        ({"clustered": ("eta",), "homogeneous": ("alpha_s",)}, "not both"),
        ({"held": ("alpha_ss",), "refine_lobes_iterations": 2}, "refine_lobes_iterations"),
    ],
)
def test_bad_homogeneous_fixed_or_clustered_options_are_named(options, match):
    with pytest.raises(ValueError, match=match):
        PolarimetricConfig(**options)


@pytest.fixture(scope="module")
def unwrap(tmp_path_factory):
    return sphere_unwrap(tmp_path_factory.mktemp("variants"), RES, PATCH)


def test_a_homogeneous_map_is_the_free_fits_median_everywhere(unwrap, tmp_path):
    free = fit_polarimetric(unwrap, CONFIG, progress=False, threads=1)
    config = dataclasses.replace(CONFIG, homogeneous=("eta", "alpha_s"))
    checkpoint = tmp_path / "polarimetric.npz"
    fit = fit_polarimetric(unwrap, config, progress=False, threads=1, checkpoint=checkpoint)
    assert fit.complete and (tmp_path / "polarimetric_free.npz").is_file() and checkpoint.is_file()
    for name in ("eta", "alpha_s"):
        median = float(np.median(free.maps[name][free.mask]))
        assert fit.homogeneous_values[name] == pytest.approx(median, abs=1e-6)
        np.testing.assert_allclose(fit.maps[name][fit.mask], median, atol=1e-5)
    assert np.ptp(free.maps["eta"][free.mask]) > 0.01  # the free fit's eta does vary
    assert fit.timings["free_fit_s"] > 0
    # resumed: both passes are complete in their checkpoints, the same maps come back
    again = fit_polarimetric(unwrap, config, progress=False, threads=1, checkpoint=checkpoint)
    for name in fit.maps:
        np.testing.assert_array_equal(again.maps[name], fit.maps[name])


def test_clustered_maps_take_one_value_per_cluster(unwrap, tmp_path):
    options = model_fit_options("hwang2022", {"iterations": 8, "patch": PATCH, "clusters": 3})
    config = PolarimetricConfig(**options)
    checkpoint = tmp_path / "polarimetric.npz"
    fit = fit_polarimetric(unwrap, config, progress=False, threads=1, checkpoint=checkpoint)
    assert fit.complete and checkpoint.is_file()
    for tag in ("free", "index0", "specular0"):
        assert (tmp_path / f"polarimetric_{tag}.npz").is_file()
    labels = fit.cluster_labels
    assert labels.shape == fit.mask.shape and set(np.unique(labels[fit.mask])) <= {0, 1, 2}
    assert set(fit.cluster_values) == {"eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss"}
    for name, values in fit.cluster_values.items():
        assert len(values) == 3
        np.testing.assert_allclose(fit.maps[name][fit.mask], np.asarray(values)[labels[fit.mask]],
                                   rtol=1e-4, atol=1e-5)  # held: the optimiser left it at its cluster value
    assert np.ptp(fit.maps["rho_sss_bar"][fit.mask]) > 0.01  # the diffuse albedo stays per texel
    again = fit_polarimetric(unwrap, config, progress=False, threads=1, checkpoint=checkpoint)
    for name in fit.maps:  # resumed from the passes' checkpoints
        np.testing.assert_array_equal(again.maps[name], fit.maps[name])
