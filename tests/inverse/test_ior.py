"""Refractive index from a sphere (paper's IOR validation): ten objects, noise, CLI, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from disk_fixtures import sphere_scene_payload, write_ior_capture
from polarface.cli import main
from polarface.inverse.ior import estimate_ior
from polarface.inverse.ior_scene import SphereScene
from polarface.inverse.ior_validation import (
    PAPER_OBJECTS,
    default_sphere_scene,
    render_sphere,
    validate_paper_objects,
)


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
    result = estimate_ior(rgb, scene, refine=False)  # a 10 px sphere: exact scene, no silhouette fit
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
    write_ior_capture(tmp_path, eta=2.1, size=64)
    assert main(["ior", str(tmp_path), "--json", "--no-refine"]) == 0  # 10 px sphere, exact scene
    assert json.loads(capsys.readouterr().out)["eta"] == pytest.approx(2.1, abs=5e-3)
    (tmp_path / "scene.json").unlink()
    assert main(["ior", str(tmp_path)]) == 2


def _scaled_pose(scene, scale):
    pose = scene.world_to_camera.copy()
    pose[:3, :3] *= scale
    return pose.tolist()


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda s: {"K": (s.K * np.diag([-1.0, 1.0, 1.0])).tolist()}, "camera.K focal"),
        (
            lambda s: {"K": (s.K + np.array([[0, 0, 500.0], [0, 0, 0], [0, 0, 0]])).tolist()},
            "principal point",
        ),
        (lambda s: {"world_to_camera": _scaled_pose(s, 1.2)}, "camera.world_to_camera must be rigid"),
        (lambda s: {"world_to_camera": (np.diag([1.0, 1.0, -1.0, 1.0]) @ s.world_to_camera).tolist()}, "det"),
        (
            lambda s: {"world_to_camera": (np.diag([-1.0, 1.0, -1.0, 1.0]) @ s.world_to_camera).tolist()},
            "front",
        ),
    ],
)
def test_ior_rejects_an_invalid_camera_naming_the_field(tmp_path, capsys, edit, field):
    """A negative focal length or a non-rigid pose used to give eta 1.05 / 1.15 (true 1.5), exit 0."""
    scene = default_sphere_scene(64)
    write_ior_capture(tmp_path, **edit(scene))
    assert main(["ior", str(tmp_path), "--json"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    err = captured.err.strip()
    assert field in err and "scene.json" in err and "\n" not in err


def test_ior_estimate_on_the_eta_range_bound_is_an_error(tmp_path, capsys):
    """True eta 1.5 searched in [1.6, 3]: the fit sits on 1.6, which is not a measurement."""
    write_ior_capture(tmp_path, eta=1.5)
    scene = SphereScene.from_dict(json.loads((tmp_path / "scene.json").read_text()))
    images = render_sphere(scene, 1.5)
    assert estimate_ior(images, scene, eta_range=(1.6, 3.0)).at_bound
    assert not estimate_ior(images, scene).at_bound
    assert main(["ior", str(tmp_path), "--eta-range", "1.6", "3.0"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and "eta_range" in captured.err and "bound" in captured.err
    assert main(["ior", str(tmp_path), "--eta-range", "3.0", "1.6"]) == 2
    assert "eta_range" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("path", "value", "field"),
    [
        (["lights"], "on", "'lights'"),
        (["lights"], [{"pos": [0, 0, 0]}], "'lights'"),
        (["lights"], [{"position": [0, 0]}], "'lights'"),
        (["camera", "K"], "eye", "'camera.K'"),
        (["camera", "width"], "wide", "'camera.width'"),
        (["sphere"], [1, 2, 3], "'sphere.center'"),
        (["sphere", "radius"], None, "'sphere.radius'"),
    ],
)
def test_scene_field_errors_name_the_field(path, value, field):
    scene = default_sphere_scene(16)
    payload = sphere_scene_payload(scene)
    assert SphereScene.from_dict(payload).lights.shape == scene.lights.shape
    node = payload
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    with pytest.raises(ValueError, match=field):
        SphereScene.from_dict(payload)
