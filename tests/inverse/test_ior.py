"""Refractive index from a sphere (paper's IOR validation): ten objects, noise, CLI, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from polarface.cli import main
from polarface.inverse.ior import (
    PAPER_OBJECTS,
    SphereScene,
    default_sphere_scene,
    estimate_ior,
    render_sphere,
    validate_paper_objects,
)
from polarface.io import write_exr


def test_ten_objects_noise_free_exact():
    rows = validate_paper_objects(noise=False, size=96)
    assert len(rows) == len(PAPER_OBJECTS) == 10
    assert max(r["abs_error"] for r in rows) < 2e-3


@pytest.mark.slow
def test_ten_objects_with_rig_noise_within_target():
    rows = validate_paper_objects(noise=True, size=160)
    assert np.mean([r["abs_error"] for r in rows]) <= 0.01


def test_rgb_input_and_bad_input():
    scene = default_sphere_scene(64)
    images = render_sphere(scene, 1.6)
    rgb = {k: np.repeat(v[..., None], 3, -1) for k, v in images.items()}
    result = estimate_ior(rgb, scene)
    assert result.eta == pytest.approx(1.6, abs=2e-3) and len(result.channels) == 3
    with pytest.raises(ValueError, match="I135"):
        estimate_ior({k: v for k, v in images.items() if k != "I135"}, scene)
    bad = dict(images)
    bad["I45"] = images["I45"].copy()
    bad["I45"][0, 0] = np.nan
    with pytest.raises(ValueError, match="I45"):
        estimate_ior(bad, scene)
    with pytest.raises(ValueError, match="usable"):
        estimate_ior({k: np.zeros_like(v) for k, v in images.items()}, scene)
    with pytest.raises(ValueError, match="radius"):
        SphereScene.from_dict(
            {
                "camera": {
                    "K": np.eye(3).tolist(),
                    "world_to_camera": np.eye(4).tolist(),
                    "width": 4,
                    "height": 4,
                },
                "sphere": {"center": [0, 0, 5], "radius": -1},
            }
        )


def test_cli_json(tmp_path, capsys):
    scene = default_sphere_scene(64)
    for name, image in render_sphere(scene, 2.1).items():
        write_exr(tmp_path / f"{name}.exr", {"Y": image})
    payload = {
        "units": "mm",
        "camera": {
            "K": scene.K.tolist(),
            "world_to_camera": scene.world_to_camera.tolist(),
            "width": 64,
            "height": 64,
        },
        "lights": [{"position": p.tolist()} for p in scene.lights],
        "sphere": {"center": scene.centre.tolist(), "radius": scene.radius},
    }
    (tmp_path / "scene.json").write_text(json.dumps(payload))
    assert main(["ior", str(tmp_path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["eta"] == pytest.approx(2.1, abs=5e-3)
    (tmp_path / "scene.json").unlink()
    assert main(["ior", str(tmp_path)]) == 2
