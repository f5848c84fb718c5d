"""Small inputs built on disk for the command tests: a skin-plane RESULT folder and an IOR sphere capture
(importable: ``tests`` is on pytest's ``pythonpath``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from polarface.capture.rig import paper_rig
from polarface.geometry.mesh import TriangleMesh, save_obj
from polarface.inverse.ior_scene import SphereScene
from polarface.inverse.ior_validation import default_sphere_scene, render_sphere
from polarface.io import write_exr, write_png

__all__ = ["plane_mesh", "sphere_scene_payload", "write_ior_capture", "write_plane_result"]


def plane_mesh(size_mm: float = 60.0, cells: int = 8) -> TriangleMesh:
    """A ``size_mm`` square in the model frame (face towards +z at z = 90 mm) with UVs over [0, 1]^2."""
    u = np.linspace(0.0, 1.0, cells + 1)
    uu, vv = np.meshgrid(u, u, indexing="xy")
    vertices = np.stack([(uu - 0.5) * size_mm, (vv - 0.5) * size_mm, np.full_like(uu, 90.0)], -1).reshape(
        -1, 3
    )
    faces = []
    for row in range(cells):
        for col in range(cells):
            a = row * (cells + 1) + col
            faces += [(a, a + 1, a + cells + 2), (a, a + cells + 2, a + cells + 1)]
    return TriangleMesh.from_arrays(vertices, np.array(faces), np.stack([uu, vv], -1).reshape(-1, 2))


def write_plane_result(
    root: Path, *, cells: int = 8, resolution: int = 32, width: int = 96, height: int = 80
) -> Path:
    """A RESULT of a 60 mm skin plane 90 mm in front of the polarimetric module, with constant maps
    (no sog.json): ``cells`` x ``cells`` quads, ``resolution``^2 texels, a paper rig of ``width`` x
    ``height`` pixels."""
    mesh = plane_mesh(cells=cells)
    values = {
        "eta": 1.42,
        "alpha_s": 0.5,
        "alpha_ss": 0.95,
        "rho_s": 0.5,
        "rho_ss": 0.25,
        "displacement_mm": 0.0,
        "c_m": 0.05,
        "beta_m": 0.1,
        "c_h_in": 0.03,
        "c_h_out": 0.05,
    }
    for name, value in values.items():
        write_exr(root / "maps" / f"{name}.exr", {"Y": np.full((resolution, resolution), value, np.float32)})
    write_png(root / "maps" / "mask.png", np.full((resolution, resolution), 255, np.uint8))
    save_obj(root / "mesh.obj", mesh)
    paper_rig(width=width, height=height).save(root / "rig.json")
    return root


def sphere_scene_payload(scene: SphereScene, **camera: Any) -> dict[str, Any]:
    """The ``scene.json`` object of ``polarface ior`` for ``scene`` (``camera`` items replace fields)."""
    return {
        "units": "mm",
        "camera": {
            "K": scene.K.tolist(),
            "world_to_camera": scene.world_to_camera.tolist(),
            "width": scene.width,
            "height": scene.height,
            **camera,
        },
        "lights": [{"position": p.tolist()} for p in scene.lights],
        "sphere": {"center": scene.centre.tolist(), "radius": scene.radius},
    }


def write_ior_capture(folder: Path, eta: float = 1.5, size: int = 64, **camera: Any) -> SphereScene:
    """An IOR capture folder: the four analyzer EXRs of a rendered ``size``^2 sphere of index ``eta`` and
    its ``scene.json`` (``camera`` items replace camera fields); returns the scene."""
    scene = default_sphere_scene(size)
    for name, image in render_sphere(scene, eta).items():
        write_exr(folder / f"{name}.exr", {"Y": image})
    (folder / "scene.json").write_text(json.dumps(sphere_scene_payload(scene, **camera)))
    return scene
