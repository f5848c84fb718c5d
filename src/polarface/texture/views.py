"""Views of an unwrapped capture: one per (frame, polarimetric camera), geometry in the model frame.

A :class:`ViewSpec` carries what the inverse stages need of a view besides its samples: the camera
centre and up, the LED module positions and radiant intensities, mapped into the rest mesh's model frame
(mm) through the frame's rigid pose, so the texel geometry of the rest mesh serves every view.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from polarface.capture.rig import Rig

__all__ = ["ViewSpec", "build_views"]


@dataclasses.dataclass(frozen=True)
class ViewSpec:
    """One polarimetric camera of one frame, with its geometry in the mesh's model frame (mm).

    Attributes:
        frame: frame index in the capture; camera_id: rig camera id.
        channels: the view's spectral channel indices for its R, G, B (e.g. ``(3, 4, 5)``).
        camera_center: ``(3,)`` camera centre; camera_up: ``(3,)`` unit camera up (image -y).
        reference_up: ``(3,)`` up of the rig's first polarimetric camera (frame of the LED polarizers
            for the subsurface entry, as in the simulator's texture-space entry flux).
        light_positions: ``(K, 3)`` LED module positions; light_intensity: ``(K, 3)`` radiant intensity
            of each module in the view's channels.
        held_out: True for views kept out of fitting (evaluation).
    """

    frame: int
    camera_id: str
    channels: tuple[int, int, int]
    camera_center: tuple[float, float, float]
    camera_up: tuple[float, float, float]
    reference_up: tuple[float, float, float]
    light_positions: tuple[tuple[float, float, float], ...]
    light_intensity: tuple[tuple[float, float, float], ...]
    held_out: bool = False

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, payload: dict) -> ViewSpec:
        return cls(
            frame=int(payload["frame"]),
            camera_id=str(payload["camera_id"]),
            channels=tuple(int(c) for c in payload["channels"]),  # type: ignore[arg-type]
            camera_center=tuple(payload["camera_center"]),
            camera_up=tuple(payload["camera_up"]),  # type: ignore[arg-type]
            reference_up=tuple(payload["reference_up"]),  # type: ignore[arg-type]
            light_positions=tuple(tuple(p) for p in payload["light_positions"]),  # type: ignore[arg-type]
            light_intensity=tuple(tuple(p) for p in payload["light_intensity"]),  # type: ignore[arg-type]
            held_out=bool(payload.get("held_out", False)),
        )


def _light_intensity(rig: Rig, channels: Sequence[int]) -> np.ndarray:
    rows = []
    for light in rig.lights:
        value = light.radiant_intensity
        values = np.full(6, float(value)) if np.ndim(value) == 0 else np.asarray(value, dtype=np.float64)
        rows.append(values[list(channels)])
    return np.asarray(rows)


def _check_lights(rig: Rig) -> None:
    if not rig.lights:
        raise ValueError("the rig has no lights ('lights' is empty)")
    for light in rig.lights:
        if not np.allclose(light.stokes, (1.0, 1.0, 0.0, 0.0), atol=1e-6):
            raise ValueError(
                f"light '{light.id}': only LED polarizers along image x (stokes [1, 1, 0, 0]) are "
                f"supported by the polarimetric stage; got {light.stokes}"
            )


def build_views(rig: Rig, frames: Sequence[int], poses: np.ndarray, holdout_every: int = 0) -> list[ViewSpec]:
    """One :class:`ViewSpec` per (frame, polarimetric camera), geometry mapped into the model frame.

    Args:
        rig: the capture's rig; frames: frame indices; poses: ``(F, 4, 4)`` model -> rig world per frame.
        holdout_every: see :class:`UnwrapConfig`.
    """
    cameras = rig.polarimetric_cameras()
    if not cameras:
        raise ValueError("the rig has no polarimetric camera")
    _check_lights(rig)
    reference_up_world = cameras[0].pinhole().up_vector
    lights_world = np.array([light.position_mm for light in rig.lights], dtype=np.float64)
    views = []
    for frame, pose in zip(frames, poses, strict=True):
        inverse = np.linalg.inv(pose)
        rotation_inv, translation_inv = inverse[:3, :3], inverse[:3, 3]
        held = holdout_every >= 2 and frame % holdout_every == holdout_every - 1
        for camera in cameras:
            cam = camera.pinhole()
            channels = tuple(int(camera.colour_channels[c]) for c in ("R", "G", "B"))
            views.append(
                ViewSpec(
                    frame=int(frame),
                    camera_id=camera.id,
                    channels=channels,  # type: ignore[arg-type]
                    camera_center=tuple(float(v) for v in rotation_inv @ cam.center + translation_inv),  # type: ignore[arg-type]
                    camera_up=tuple(float(v) for v in rotation_inv @ cam.up_vector),  # type: ignore[arg-type]
                    reference_up=tuple(float(v) for v in rotation_inv @ reference_up_world),  # type: ignore[arg-type]
                    light_positions=tuple(
                        tuple(float(v) for v in rotation_inv @ p + translation_inv) for p in lights_world
                    ),  # type: ignore[arg-type]
                    light_intensity=tuple(
                        tuple(float(v) for v in row) for row in _light_intensity(rig, channels)
                    ),  # type: ignore[arg-type]
                    held_out=held,
                )
            )
    return views
