"""The validation camera: novel viewpoints the reconstruction never sees, with their true images.

The paper validates its maps by rendering them "from a completely novel viewpoint of an RGB camera"
(Sec. 6) and compares the degree of polarization with a reference polarization camera. The simulator
places such a camera outside the rig at ``views`` viewpoints around the head (:func:`validation_cameras`)
and renders the true head at its rest placement there (:func:`write_validation`), noise-free, into::

    SIM/ground_truth/validation/
      validation.json     format, the head's pose (model -> rig world), channel names, and per view its
                          camera (``PinholeCamera.to_dict``) and image file (relative to this folder)
      NNNN.exr            per view, six channels each (the rig's channel names ``<ch>``):
                          ``s0.<ch>``, ``s1.<ch>``, ``s2.<ch>``  the Stokes image (camera frame)
                          ``specular.<ch>``                      s0 of the surface reflection alone
                          ``mask``                               1 where a ray hits the head

The camera is the rig's first polarimetric camera's intrinsics with all six channels and a full
polarization readout: its ``s0`` is the image of an unfiltered (RGB) camera at that viewpoint, its
Stokes images those of a polarization camera there. The viewpoints lie on a sphere around the head at
the polarimetric camera's distance, away from the rig's near-coaxial LEDs: azimuths between the rig's
yaw sweep and beyond it, three elevations (one for fewer than nine views), so the half vectors and
Fresnel angles differ from every fitted view. ``SIM/ground_truth`` is not read by the reconstruction;
:mod:`polarface.evaluate.validation` renders a RESULT at the same cameras.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from polarface.geometry.camera import PinholeCamera
from polarface.io import read_json_object, write_exr, write_json_atomic
from polarface.render.renderer import render_view
from polarface.simulate.render import frame_scene
from polarface.simulate.scene import SimulationScene

__all__ = [
    "VALIDATION_FOLDER",
    "VALIDATION_FORMAT",
    "VALIDATION_JSON",
    "validation_cameras",
    "write_validation",
]

#: The validation folder inside the ground-truth folder, and its index file.
VALIDATION_FOLDER = "validation"
VALIDATION_JSON = "validation.json"
VALIDATION_FORMAT = "polarface-validation"
#: Azimuths (degrees about the head's vertical axis, 0 = facing the polarimetric camera) and elevations
#: the viewpoints span.
AZIMUTH_RANGE_DEG = (-75.0, 75.0)
ELEVATIONS_DEG = (-20.0, 8.0, 32.0)


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues rotation ``(3, 3)`` about the unit ``axis`` by ``angle`` radians."""
    x, y, z = axis
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def validation_cameras(scene: SimulationScene, views: int) -> dict[str, PinholeCamera]:
    """``views`` novel cameras (id ``validation_NN`` -> pinhole, rig world, mm) around the head at its rest
    placement: the first polarimetric camera's intrinsics, at its distance from the head's centre, on a
    grid of azimuths (:data:`AZIMUTH_RANGE_DEG` in equal steps, each at its step's centre) and elevations
    (:data:`ELEVATIONS_DEG`; the middle one alone for fewer than 9 views), row by row."""
    if isinstance(views, bool) or not isinstance(views, int) or views < 1:
        raise ValueError(f"argument 'views' must be an integer >= 1; got {views!r}")
    reference = scene.rig.polarimetric_cameras()[0].pinhole()
    centre = scene.asset.mesh.transformed(scene.placement).vertices.mean(axis=0)
    offset = reference.center - centre
    distance = float(np.linalg.norm(offset))
    up = reference.up_vector  # the world direction up in the polarimetric camera's image
    up = up - offset * (up @ offset) / distance**2
    up /= np.linalg.norm(up)
    right = np.cross(offset / distance, up)
    elevations = ELEVATIONS_DEG if views >= 9 else ELEVATIONS_DEG[1:2]
    per_row = math.ceil(views / len(elevations))
    lo, hi = AZIMUTH_RANGE_DEG
    step = (hi - lo) / per_row
    azimuths = [lo + step * (i + 0.5) for i in range(per_row)]
    cameras = {}
    for elevation in elevations:
        for azimuth in azimuths:
            if len(cameras) == views:
                break
            turn = _rotation(up, math.radians(azimuth)) @ _rotation(right, math.radians(elevation))
            eye = centre + turn @ offset
            focal = float(reference.K[0, 0])
            cameras[f"validation_{len(cameras):02d}"] = PinholeCamera.look_at(
                eye, centre, up, width=reference.width, height=reference.height, focal=focal
            )
    return cameras


def write_validation(scene: SimulationScene, root: Path, views: int) -> dict:
    """Render the true head at :func:`validation_cameras` into ``root/validation`` (module docstring;
    ``root`` is the ground-truth folder) and return the index written to ``validation.json``. A folder
    whose index is complete for the same cameras is kept as it is (resumable); images are written
    before the index, atomically."""
    folder = root / VALIDATION_FOLDER
    cameras = validation_cameras(scene, views)
    index_path = folder / VALIDATION_JSON
    if index_path.is_file():
        recorded = read_json_object(index_path)
        if [view.get("camera") for view in recorded.get("views", [])] == [
            camera.to_dict() for camera in cameras.values()
        ]:
            return recorded
    mesh = scene.asset.mesh.transformed(scene.placement)
    posed = frame_scene(scene, mesh, scene.maps, scene.subsurface)
    specular = posed.textures.without_subsurface()
    names = list(scene.calibration.channel_names)
    entries = []
    for number, (camera_id, camera) in enumerate(cameras.items()):
        full = render_view(posed.caster, mesh, camera, posed.textures, posed.lights, posed.intensity,
                           tuple(range(6)), polarization=True)
        surface = render_view(posed.caster, mesh, camera, specular, posed.lights, posed.intensity,
                              tuple(range(6)), polarization=False)
        images = full.images
        stokes = {
            "s0": images["i0"] + images["i90"],
            "s1": images["i0"] - images["i90"],
            "s2": images["i45"] - images["i135"],
            "specular": surface.images["s0"],
        }
        channels = {
            f"{kind}.{name}": image[..., c] for kind, image in stokes.items() for c, name in enumerate(names)
        }
        channels["mask"] = full.mask.astype(np.float32)
        file = f"{number:04d}.exr"
        write_exr(folder / file, channels)
        entries.append({"id": camera_id, "file": file, "camera": camera.to_dict()})
    index = {
        "format": VALIDATION_FORMAT,
        "version": 1,
        "head_pose": scene.placement.tolist(),
        "channel_names": names,
        "views": entries,
    }
    write_json_atomic(index_path, index)
    return index
