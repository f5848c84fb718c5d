"""A :class:`polarface.capture.rig.Rig` for an authors' session: its two polarimetric cameras from the
COLMAP files and the paper's LED ring around them (the session files hold no light positions).

Lights (``docs/authors_dataset.md``, "Lights"): 8 LED modules on a circle of 100 mm radius (paper Sec. 4:
LEDs ~10 cm from the lens axis, 5.72 deg at 1 m) centred between the two camera centres, in the plane
spanned by the baseline (camera 1 -> camera 2, the ring's x axis) and the cameras' mean image-down
axis made orthogonal to it (the ring's y axis); module ``k`` at angle ``2 pi k / 8`` from x towards y.
For :func:`polarface.capture.rig.paper_rig` (and so for polarface simulations) this reproduces its
lights exactly. Each module's radiant intensity is ``1e6 / 8`` (mm^2 units): the eight modules together
give ``1 / d^2`` with ``d`` in metres, the normalisation of the authors' single co-located light whose
white balance maps the spectralon to ~1 (so the albedos come out on the authors' scale).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from pydantic import ValidationError

from polarface.capture.authors_layout import AUTHORS_CAMERAS, ColmapCamera
from polarface.capture.rig import Camera, LightModule, Rig, SpectralModel

__all__ = ["AUTHORS_LED_COUNT", "AUTHORS_LED_RADIUS_MM", "AUTHORS_TOTAL_INTENSITY", "authors_rig", "led_ring"]

#: LED modules and their circle radius (paper Sec. 4.1).
AUTHORS_LED_COUNT = 8
AUTHORS_LED_RADIUS_MM = 100.0
#: Summed radiant intensity of the modules (mm^2 units): 1 / d^2 with d in metres.
AUTHORS_TOTAL_INTENSITY = 1.0e6


def led_ring(world_to_camera: list[np.ndarray], count: int = AUTHORS_LED_COUNT,
             radius_mm: float = AUTHORS_LED_RADIUS_MM) -> np.ndarray:
    """``(count, 3)`` LED module positions (world, mm) around two cameras (module docstring).

    Args:
        world_to_camera: the two polarimetric cameras' ``(4, 4)`` world -> camera (OpenCV axes, mm).

    Raises:
        ValueError: not two cameras, or coincident camera centres.
    """
    if len(world_to_camera) != 2:
        raise ValueError(f"the LED ring needs the two polarimetric cameras; got {len(world_to_camera)}")
    poses = [np.asarray(p, dtype=np.float64) for p in world_to_camera]
    centres = [-p[:3, :3].T @ p[:3, 3] for p in poses]
    baseline = centres[1] - centres[0]
    if np.linalg.norm(baseline) < 1e-6:
        raise ValueError("the two polarimetric cameras share their centre: no baseline for the LED ring")
    x_axis = baseline / np.linalg.norm(baseline)
    down = poses[0][1, :3] + poses[1][1, :3]  # image +y (down) of each camera, in world
    y_axis = down - (down @ x_axis) * x_axis
    y_axis /= np.linalg.norm(y_axis)
    middle = 0.5 * (centres[0] + centres[1])
    angles = 2.0 * math.pi * np.arange(count) / count
    return middle + radius_mm * (np.cos(angles)[:, None] * x_axis + np.sin(angles)[:, None] * y_axis)


def _spectral() -> SpectralModel:
    from polarface.skin.spectral import default_spectral_calibration

    return SpectralModel.from_calibration(default_spectral_calibration())


def authors_rig(cameras: Mapping[int, ColmapCamera], world_to_camera: Mapping[int, np.ndarray],
                source: str = "authors") -> Rig:
    """The rig of an authors' session: cameras ``cam1`` (channels 0-2) and ``cam2`` (3-5) and the LED ring.

    Args:
        cameras: ``cameras.txt`` (:func:`polarface.capture.authors_layout.read_colmap_cameras`);
        world_to_camera: ``images.txt`` (:func:`~polarface.capture.authors_layout.read_colmap_images`);
        source: the session (for error messages and the rig's name).

    Raises:
        ValueError: camera 1 or 2 is missing from either file, or is not a valid camera (naming the files).
    """
    rig_cameras = []
    for index in AUTHORS_CAMERAS:
        for name, table in (("cameras.txt", cameras), ("images.txt", world_to_camera)):
            if index not in table:
                raise ValueError(f"'{source}/{name}' has no camera {index} (polarimetric camera {index})")
        camera = cameras[index]
        first = 3 * (index - 1)
        try:
            rig_cameras.append(Camera(
                id=f"cam{index}", role="polarimetric", sensor="color-polarization",
                width=int(camera.width), height=int(camera.height), K=np.asarray(camera.K).tolist(),
                distortion=[*camera.distortion[:4], 0.0],
                world_to_camera=np.asarray(world_to_camera[index]).tolist(),
                bit_depth=12, colour_channels={"R": first, "G": first + 1, "B": first + 2},
            ))
        except ValidationError as exc:  # one line naming the files, not pydantic's multi-line dump
            reasons = "; ".join(f"{'.'.join(str(p) for p in e['loc'])}: {' '.join(str(e['msg']).split())}"
                                for e in exc.errors()[:3])
            raise ValueError(f"'{source}/cameras.txt' / 'images.txt': camera {index} is not a valid camera "
                             f"({reasons})") from None
    positions = led_ring([world_to_camera[i] for i in AUTHORS_CAMERAS])
    lights = [
        LightModule(id=f"led{k}", position_mm=tuple(float(v) for v in p), polarizer_angle=0.0,
                    stokes=(1.0, 1.0, 0.0, 0.0), radiant_intensity=AUTHORS_TOTAL_INTENSITY / len(positions))
        for k, p in enumerate(positions)
    ]
    return Rig(name=f"authors-session:{source}", cameras=rig_cameras, lights=lights, spectral=_spectral())
