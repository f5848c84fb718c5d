"""One frame's render in a simulation: every camera of the rig for one posed or deformed head, noise-free
(:func:`render_frame` -> :class:`RenderedFrame`), and the exposure a frame fixes for the whole capture
(:func:`frame_exposure`, :func:`with_exposure`). The raw sensor frames and the files are made from the
render by :mod:`polarface.simulate.frames`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from polarface._validation import trusted_inputs
from polarface.capture.rig import Camera, Rig
from polarface.executors.timing import StageClock
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.raycast import RayCaster
from polarface.geometry.uv_raster import UVRaster, reposition
from polarface.render.renderer import render_view, rig_lighting, shading_normals
from polarface.render.shading import FrameTextures
from polarface.render.subsurface import SubsurfaceModel, entering_flux, texture_space_exitance
from polarface.simulate.ground_truth import AppearanceMaps
from polarface.simulate.scene import SimulationScene
from polarface.simulate.sequences import sequence_frame

__all__ = ["RenderedFrame", "exposure_from", "frame_exposure", "render_frame", "with_exposure"]


def _camera_channels(camera: Camera) -> tuple[int, int, int]:
    return tuple(camera.colour_channels[c] for c in ("R", "G", "B"))  # type: ignore[return-value]


@dataclasses.dataclass(frozen=True)
class RenderedFrame:
    """The per-camera renders and the geometry of one frame (internal to the simulator)."""

    mesh: TriangleMesh
    caster: RayCaster  # Embree scene of ``mesh``, reused for the texel visibility
    views: dict  # camera id -> ViewRender
    raster: UVRaster
    shading_normal: np.ndarray


def render_frame(
    scene: SimulationScene, mesh_world: TriangleMesh, maps: AppearanceMaps, subsurface: SubsurfaceModel,
    timings: dict[str, float] | None = None, cameras: tuple[str, ...] | None = None,
) -> RenderedFrame:
    """Render every camera of the rig (or the ``cameras`` named) for one posed/deformed head (noise-free
    radiance). A view's pixels do not depend on which other cameras are rendered.

    ``timings``: adds the seconds of each stage (:data:`polarface.simulate.frames.FRAME_STAGES`, render
    part) to it.
    """
    clock = StageClock(timings)
    caster = RayCaster(mesh_world)
    raster = reposition(scene.raster, mesh_world)
    shading = shading_normals(raster, maps.displacement_mm)
    lights, intensity = rig_lighting(scene.rig)
    reference = scene.rig.polarimetric_cameras()[0].pinhole()
    clock.lap("geometry_s")
    # the scene's maps and model were checked when built, the flux is computed here: the value checks
    # (finite, ranges) of the physics functions inside are skipped (about 0.2 s of the diffusion)
    with trusted_inputs():
        flux = entering_flux(caster, raster, shading, maps.eta, lights, intensity, reference.up_vector)
        clock.lap("entering_flux_s")
        blur = scene.config.subsurface_blur
        exitance = texture_space_exitance(flux, subsurface, scene.calibration, blur=blur)
        clock.lap("diffusion_s")
    textures = FrameTextures.build(
        {
            "eta": maps.eta,
            "alpha_s": maps.alpha_s,
            "alpha_ss": maps.alpha_ss,
            "rho_s": maps.rho_s,
            "rho_ss": maps.rho_ss,
        },
        shading,
        exitance,
        raster.mask,
    )
    views = {}
    for camera in scene.rig.cameras:
        if cameras is not None and camera.id not in cameras:
            continue
        polarimetric = camera.role == "polarimetric"
        views[camera.id] = render_view(
            caster,
            mesh_world,
            camera.pinhole(),
            textures,
            lights,
            intensity,
            _camera_channels(camera) if polarimetric else tuple(range(6)),
            polarization=polarimetric,
        )
        clock.lap("views_polarimetric_s" if polarimetric else "views_stereo_s")
    return RenderedFrame(mesh_world, caster, views, raster, shading)


def exposure_from(frame: RenderedFrame, scene: SimulationScene) -> float:
    """Exposure putting the 99.5th percentile of the first polarimetric camera's co-polarized image at
    ``exposure_fill``."""
    camera = scene.rig.polarimetric_cameras()[0]
    view = frame.views[camera.id]
    values = view.images["i0"][view.mask]
    level = float(np.percentile(values, 99.5)) if values.size else 1.0
    return scene.config.exposure_fill / max(level, 1e-12)


def frame_exposure(scene: SimulationScene, sequence: str, index: int) -> float:
    """The exposure that frame ``index`` of ``sequence`` fixes (:func:`exposure_from`), from a render of
    the one camera it reads: the same pixels as in the frame's full render, at about a quarter of its
    cost (demo preset: geometry, subsurface light and one of ten views)."""
    _, _, mesh, maps, subsurface = sequence_frame(scene, sequence, index)
    first = scene.rig.polarimetric_cameras()[0].id
    return exposure_from(render_frame(scene, mesh, maps, subsurface, cameras=(first,)), scene)


def with_exposure(rig: Rig, exposure: float) -> Rig:
    """The rig with every camera's exposure set (so demosaiced images come back in radiance units)."""
    data = rig.model_dump(mode="json")
    for camera in data["cameras"]:
        camera["exposure"] = exposure
    return Rig.model_validate(data)
