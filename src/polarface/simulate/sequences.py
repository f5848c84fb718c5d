"""The simulated sequences: static chair rotations and the dynamic expression + blood-flow frames.

:func:`sequence_frame` gives one frame of a sequence — the head mesh in the rig world and the maps and
subsurface model of that frame — from the frame's index alone (so frames can be rendered in any order,
in parallel: :mod:`polarface.simulate.frames`); :func:`sequence_frames` yields them in order. The
static sequence turns the rest head on the chair (:func:`static_poses`), the dynamic one deforms it
with the expression rig and lowers the outer haemoglobin under a pressed forehead patch that refills
over time (:func:`pressed_patch`, :func:`with_c_h_out`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
import torch

from polarface.geometry.deform import ExpressionRig, dynamic_sequence_weights
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.poses import StaticSequenceConfig, static_sequence_poses
from polarface.render.subsurface import SubsurfaceModel
from polarface.simulate.ground_truth import AppearanceMaps, blood_flow_factor, chromophore_maps
from polarface.simulate.scene import SimulationScene

__all__ = [
    "FRAME_RATE_HZ",
    "pressed_patch",
    "sequence_frame",
    "sequence_frames",
    "static_poses",
    "with_c_h_out",
]

FRAME_RATE_HZ = 20.0


def sequence_frames(
    scene: SimulationScene, sequence: str
) -> Iterable[tuple[int, float, TriangleMesh, AppearanceMaps, SubsurfaceModel]]:
    """Yield :func:`sequence_frame` of every frame of a sequence, in order."""
    count = scene.preset.static_frames if sequence == "static" else scene.preset.dynamic_frames
    for index in range(count):
        yield sequence_frame(scene, sequence, index)


def sequence_frame(
    scene: SimulationScene, sequence: str, index: int
) -> tuple[int, float, TriangleMesh, AppearanceMaps, SubsurfaceModel]:
    """``(index, timestamp s, mesh in rig world, maps, subsurface model)`` of frame ``index`` of a
    sequence (``static``: the rest head turned on the chair; ``dynamic``: deformed by the expression rig,
    the outer haemoglobin lowered under the pressed patch).

    Raises:
        ValueError: an unknown sequence, or ``index`` outside ``0 .. frames - 1``.
    """
    preset = scene.preset
    count = {"static": preset.static_frames, "dynamic": preset.dynamic_frames}.get(sequence)
    if count is None:
        raise ValueError(f"argument 'sequence' must be 'static' or 'dynamic'; got {sequence!r}")
    if not 0 <= int(index) < count:
        raise ValueError(f"argument 'index': {sequence} frame {index} is not in 0..{count - 1}")
    index = int(index)
    asset = scene.asset
    if sequence == "static":
        pose = static_poses(scene)[index]
        return index, index / FRAME_RATE_HZ, asset.mesh.transformed(pose), scene.maps, scene.subsurface
    weights = dynamic_sequence_weights(preset.dynamic_frames)
    time_s = index * preset.dynamic_frame_step / FRAME_RATE_HZ
    mesh = ExpressionRig(asset.mesh, asset.landmarks).deform(weights[index]).transformed(scene.placement)
    lowered = 0.8 * (1.0 - float(blood_flow_factor(time_s)))
    c_h_out = (scene.maps.c_h_out * (1.0 - lowered * pressed_patch(scene))).astype(np.float32)
    maps = with_c_h_out(scene, c_h_out)
    # Only the texels under the pressed patch change (a few percent; the Gaussian's tail rounds to the
    # rest map's float32 value): their layer totals are recomputed, the others are the rest model's.
    subsurface = scene.subsurface.updated(chromophore_maps(maps), _changed_texels(scene, c_h_out))
    return index, time_s, mesh, maps, subsurface


def _changed_texels(scene: SimulationScene, c_h_out: np.ndarray) -> np.ndarray:
    """``(Ht, Wt)`` bool: atlas texels whose outer haemoglobin differs from the rest maps'."""
    return scene.maps.mask & (c_h_out != scene.maps.c_h_out)


def static_poses(scene: SimulationScene) -> np.ndarray:
    """Model -> rig-world poses ``(N, 4, 4)`` of the static sequence (chair rotation, then placement)."""
    config = StaticSequenceConfig(
        frame_count=scene.preset.static_frames,
        yaw_range=math.radians(scene.preset.yaw_range_deg),
        pitch_amplitude=math.radians(scene.preset.pitch_range_deg / 2.0),
        pivot=tuple(float(v) for v in scene.asset.neck_pivot),
    )
    return np.stack([scene.placement @ pose for pose in static_sequence_poses(config)])


def pressed_patch(scene: SimulationScene) -> np.ndarray:
    """``(Ht, Wt)`` weight of the pressed forehead patch (Gaussian, sigma 10 mm, 15 mm below the
    ``forehead`` landmark and 28 mm to its side: the forehead's centre faces the cameras and the
    near-coaxial LEDs, and its specular highlight saturates the co-polarized pixels there, which the
    reconstruction cannot use; a patch on it would be measured on its rim only)."""
    centre = scene.asset.landmark_position("forehead") + np.array([28.0, -15.0, 0.0])
    distance2 = ((np.where(scene.raster.mask[..., None], scene.raster.position, 0.0) - centre) ** 2).sum(-1)
    return np.where(scene.raster.mask, np.exp(-0.5 * distance2 / 10.0**2), 0.0)


def with_c_h_out(scene: SimulationScene, c_h_out: np.ndarray) -> AppearanceMaps:
    """Maps with a new outer haemoglobin map ``(Ht, Wt)`` float32 and the matching six-channel
    rho_sss_bar (float64 two-layer ``R_bar`` integrated into the channels, per texel).

    Computed at the texels whose ``c_h_out`` differs from the rest maps' only; the others take the
    rest maps' values computed the same way once per scene (kept in ``scene.derived``), so the result is
    the same as computing every texel.
    """
    key = "rho_sss_bar_float64"  # rho_sss_bar of the rest maps through this function (not build's)
    if key not in scene.derived:
        scene.derived[key] = _rho_sss_bar(
            scene, scene.maps.mask, scene.maps.c_h_out, np.zeros_like(scene.maps.rho_sss_bar)
        )
    rho = _rho_sss_bar(scene, _changed_texels(scene, c_h_out), c_h_out, scene.derived[key])
    return scene.maps.replace(c_h_out=c_h_out, rho_sss_bar=rho)


def _rho_sss_bar(scene: SimulationScene, texels: np.ndarray, c_h_out: np.ndarray,
                 base: np.ndarray) -> np.ndarray:
    """Copy of ``base`` ``(Ht, Wt, 6)`` float32 with rho_sss_bar recomputed at ``texels`` ``(Ht, Wt)``."""
    from polarface.skin.layers import subsurface_albedo

    rho = base.copy()
    if not texels.any():
        return rho
    r_bar = subsurface_albedo(
        torch.from_numpy(scene.maps.c_m[texels].astype(np.float64)),
        torch.from_numpy(scene.maps.beta_m[texels].astype(np.float64)),
        torch.from_numpy(scene.maps.c_h_in[texels].astype(np.float64)),
        torch.from_numpy(c_h_out[texels].astype(np.float64)),
        scene.calibration.wavelengths_nm,
    )
    rho[texels] = scene.calibration.integrate(r_bar).float().numpy()
    return rho
