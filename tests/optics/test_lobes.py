"""polarface.optics.lobes.add_lobes: the lobes of render_polarimetric light by light, the same bits for
any number of Stokes components, lazy shadow tests asked only where a lobe can be non-zero, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lobe_fixtures import lobe_fragments as _fragments
from polarface._validation import trusted_inputs
from polarface.optics import render_polarimetric
from polarface.optics.lobes import add_lobes


def _reference(geometry, params, lights, visible, intensity, start, light_stokes=None):
    """The per-light render_polarimetric loop (full 4x4 chain) times the visibility."""
    dtype = start.dtype
    total = start
    no_exitance = torch.zeros(len(start), intensity.shape[-1], dtype=dtype)
    for k in range(len(lights)):
        images = render_polarimetric(
            geometry["normal"], geometry["position"], geometry["camera_center"], geometry["camera_up"],
            torch.from_numpy(lights[k : k + 1]).to(dtype), intensity[k : k + 1] if intensity.shape[0] > 1
            else intensity, params["eta"], params["alpha_s"], params["alpha_ss"], params["rho_s"],
            params["rho_ss"], 0.0, diffused_exitance=no_exitance,
            light_stokes=None if light_stokes is None else light_stokes[k],
        )
        lit = torch.from_numpy(visible[:, k]).to(dtype)[:, None, None]
        total = total + lit * images.stokes
    return total


def _add(geometry, params, lights, visible, intensity, stokes, **kwargs):
    return add_lobes(stokes, geometry["normal"], geometry["position"], geometry["camera_center"],
                     geometry["camera_up"], lights, intensity, params["eta"], params["alpha_s"],
                     params["alpha_ss"], params["rho_s"], params["rho_ss"], visible, **kwargs)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_every_component_count_gives_the_full_paths_bits(dtype):
    geometry, params, lights, visible, start = _fragments(dtype)
    intensity = torch.full((1, 1), 2.5e6, dtype=dtype)
    reference = _reference(geometry, params, lights, visible, intensity, start)
    for components in (1, 2, 3, 4):
        got = _add(geometry, params, lights, visible, intensity, start[..., :components])
        assert got.shape == (len(start), 3, components)
        assert got.numpy().tobytes() == reference[..., :components].contiguous().numpy().tobytes()
    # per-light intensities (K, C) and polarizer states (K, 4)
    rng = np.random.default_rng(1)
    per_light = torch.from_numpy(rng.uniform(1e6, 3e6, (5, 3))).to(dtype)
    states = torch.tensor(
        [[1, 1, 0, 0], [1, -1, 0, 0], [1, 0, 1, 0], [1, 0, 0, 1], [1, 0.3, -0.4, 0.2]], dtype=dtype
    )
    reference = _reference(geometry, params, lights, visible, per_light, start, light_stokes=states)
    got = _add(geometry, params, lights, visible, per_light, start, light_stokes=states)
    assert torch.equal(got, reference)


def test_lazy_visibility_is_asked_only_where_a_lobe_can_be_nonzero():
    geometry, params, lights, visible, start = _fragments(torch.float32, seed=2)
    intensity = torch.ones(1, 1)
    asked = {}

    def shadow_test(k: int, rows: np.ndarray) -> np.ndarray:
        asked[k] = rows
        return visible[rows, k]

    lazy = _add(geometry, params, lights, shadow_test, intensity, start[..., :1])
    eager = _add(geometry, params, lights, visible, intensity, start[..., :1])
    assert torch.equal(lazy, eager)
    normal, position = geometry["normal"].double(), geometry["position"].double()
    to_camera = -position
    for k, rows in asked.items():
        to_light = torch.from_numpy(lights[k]) - position
        front = ((normal * to_light).sum(-1) > 0) & ((normal * to_camera).sum(-1) > 0)
        skipped = np.setdiff1d(np.arange(len(start)), rows)
        assert len(skipped) > 0  # some rays are not cast at all
        assert not front[torch.from_numpy(skipped)].any()  # ... only where no lobe can be lit
    assert set(asked) == set(range(len(lights)))


def test_bad_input():
    geometry, params, lights, visible, start = _fragments(torch.float32, count=20)
    intensity = torch.ones(1, 1)
    with pytest.raises(ValueError, match="'stokes'"):
        _add(geometry, params, lights, visible, intensity, torch.zeros(20, 3, 5))
    with pytest.raises(ValueError, match="'stokes'"):
        _add(geometry, params, lights, visible, intensity, torch.zeros(19, 3, 1))
    with pytest.raises(ValueError, match="'visible'"):
        _add(geometry, params, lights, visible[:, :2], intensity, start)
    with pytest.raises(ValueError, match="'visible'"):
        _add(geometry, params, lights, visible.astype(float), intensity, start)
    with pytest.raises(ValueError, match="'visible'"):
        _add(geometry, params, lights, lambda k, rows: np.ones(len(rows) + 1, bool), intensity, start)
    with pytest.raises(ValueError, match="'light_intensity'"):
        _add(geometry, params, lights, visible, torch.ones(3, 1), start)
    bad = dict(params, eta=torch.full((20, 1), 0.9))
    with pytest.raises(ValueError, match="'eta'"):
        _add(geometry, bad, lights, visible, intensity, start)
    with pytest.raises(ValueError, match="'normal'"):
        _add(dict(geometry, normal=2 * geometry["normal"]), params, lights, visible, intensity, start)
    with trusted_inputs():  # value checks skipped, shape checks kept
        _add(geometry, bad, lights, visible, intensity, start)
        with pytest.raises(ValueError, match="'visible'"):
            _add(geometry, params, lights, visible[:, :2], intensity, start)
