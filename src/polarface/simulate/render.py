"""One frame's render in a simulation: every camera of the rig for one posed or deformed head, noise-free
(:func:`render_frame` -> :class:`RenderedFrame`; the posed head alone, for any camera:
:func:`frame_scene`), the stereo cameras' colour image (:func:`stereo_rgb`), and the exposures a frame
fixes for the whole capture (:func:`frame_exposure`, :func:`with_exposure`). The raw sensor frames and
the files are made from the render by :mod:`polarface.simulate.frames`.
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

__all__ = [
    "FrameScene",
    "RenderedFrame",
    "exposure_from",
    "frame_exposure",
    "frame_scene",
    "render_frame",
    "sensor_images",
    "stereo_rgb",
    "with_exposure",
]


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


@dataclasses.dataclass(frozen=True, eq=False)
class FrameScene:
    """One frame's head in the rig world with its subsurface light diffused, ready to render at any camera
    (:func:`polarface.render.renderer.render_view` with these fields; internal to the simulator)."""

    mesh: TriangleMesh
    caster: RayCaster
    raster: UVRaster
    shading_normal: np.ndarray
    textures: FrameTextures
    lights: np.ndarray
    intensity: np.ndarray  # (K,) radiant intensity per LED module


def frame_scene(
    scene: SimulationScene, mesh_world: TriangleMesh, maps: AppearanceMaps, subsurface: SubsurfaceModel,
    timings: dict[str, float] | None = None,
) -> FrameScene:
    """The posed/deformed head ``mesh_world`` with ``maps`` under the rig's LEDs: its entering flux and
    diffused exitance (``timings``: adds ``geometry_s``, ``entering_flux_s`` and ``diffusion_s``)."""
    clock = StageClock(timings)
    caster = RayCaster(mesh_world)
    raster = reposition(scene.raster, mesh_world)
    shading = shading_normals(raster, maps.displacement_mm)
    lights, intensity = rig_lighting(scene.true_rig())  # where the LEDs really are, how bright
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
    return FrameScene(mesh_world, caster, raster, shading, textures, lights, intensity)


def render_frame(
    scene: SimulationScene, mesh_world: TriangleMesh, maps: AppearanceMaps, subsurface: SubsurfaceModel,
    timings: dict[str, float] | None = None, cameras: tuple[str, ...] | None = None,
) -> RenderedFrame:
    """Render every camera of the rig (or the ``cameras`` named) for one posed/deformed head (noise-free
    radiance). A view's pixels do not depend on which other cameras are rendered.

    ``timings``: adds the seconds of each stage (:data:`polarface.simulate.frames.FRAME_STAGES`, render
    part) to it.
    """
    posed = frame_scene(scene, mesh_world, maps, subsurface, timings)
    clock = StageClock(timings)
    views = {}
    for camera in scene.rig.cameras:
        if cameras is not None and camera.id not in cameras:
            continue
        polarimetric = camera.role == "polarimetric"
        views[camera.id] = render_view(
            posed.caster,
            mesh_world,
            camera.pinhole(),
            posed.textures,
            posed.lights,
            posed.intensity,
            _camera_channels(camera) if polarimetric else tuple(range(6)),
            polarization=polarimetric,
        )
        clock.lap("views_polarimetric_s" if polarimetric else "views_stereo_s")
    return RenderedFrame(mesh_world, posed.caster, views, posed.raster, posed.shading_normal)


def stereo_rgb(s0: np.ndarray, rig: Rig) -> np.ndarray:
    """RGB of an unfiltered (stereo) camera from the six half-band channels of its ``(h, w, 6)`` float32
    radiance image ``s0``: the mean of each colour's two halves (the polarimetric cameras' channel order);
    ``(h, w, 3)`` float32."""
    upper, lower = rig.polarimetric_cameras()[:2]
    rgb = [
        0.5 * (s0[..., upper.colour_channels[c]] + s0[..., lower.colour_channels[c]]) for c in ("R", "G", "B")
    ]
    return np.stack(rgb, axis=-1)


def sensor_images(scene: SimulationScene, camera: Camera,
                  images: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A camera's rendered ``images`` (a :class:`~polarface.render.renderer.ViewRender`'s) as its sensor
    records them, before exposure: a polarization camera's ``i0``..``i135`` ``(h, w, 3)`` times the true
    rig's ``channel_gains`` (a mono sensor: the first); a stereo camera's ``rgb`` ``(h, w, 3)``, its
    reference colours (:func:`stereo_rgb`) mixed to its native R, G, B
    (:meth:`~polarface.simulate.rig_perturbation.RigPerturbation.stereo_mixing`), clipped at 0. Unchanged
    values (the same arrays) when nothing is perturbed."""
    perturbation = scene.config.rig_perturbation
    if camera.role == "polarimetric":
        if perturbation.is_nominal:
            return images
        gains = np.asarray(scene.true_rig().camera(camera.id).channel_gains, dtype=np.float32)
        scale = gains if camera.sensor == "color-polarization" else gains[0]
        return {name: image * scale for name, image in images.items()}
    rgb = np.clip(stereo_rgb(images["s0"], scene.rig), 0.0, None)
    if not perturbation.is_nominal:
        mixing = perturbation.stereo_mixing(scene.rig, camera.id).astype(np.float32)
        rgb = np.clip(rgb @ mixing.T, 0.0, None)
    return {"rgb": rgb}


def _fill_exposure(values: np.ndarray, fill: float) -> float:
    level = float(np.percentile(values, 99.5)) if values.size else 1.0
    return fill / max(level, 1e-12)


def exposure_from(frame: RenderedFrame, scene: SimulationScene) -> dict[str, float]:
    """Each camera's exposure (camera id -> relative exposure), as a rig's operator sets them: the
    polarimetric cameras share one, putting the 99.5th percentile of the first polarimetric camera's
    co-polarized image at ``exposure_fill`` (the two are normalised to each other, as in the paper's
    calibration); each stereo camera its own, putting the 99.5th percentile of its brightest colour
    channel on the head at ``exposure_fill``. ``frame`` holds the first polarimetric camera's view and
    every stereo camera's (:func:`frame_exposure`)."""
    fill = scene.config.exposure_fill
    first = scene.rig.polarimetric_cameras()[0]
    view = frame.views[first.id]
    i0 = sensor_images(scene, first, {"i0": view.images["i0"]})["i0"]
    polarimetric = _fill_exposure(i0[view.mask], fill)
    exposures = {}
    for camera in scene.rig.cameras:
        if camera.role == "polarimetric":
            exposures[camera.id] = polarimetric
        else:
            view = frame.views[camera.id]
            rgb = sensor_images(scene, camera, view.images)["rgb"]
            exposures[camera.id] = _fill_exposure(rgb[view.mask].max(axis=-1), fill)
    return exposures


def frame_exposure(scene: SimulationScene, sequence: str, index: int) -> dict[str, float]:
    """The exposures that frame ``index`` of ``sequence`` fixes (:func:`exposure_from`), from a render of
    the cameras it reads: the first polarimetric camera and the stereo cameras, the same pixels as in the
    frame's full render (demo preset: about half its cost)."""
    _, _, mesh, maps, subsurface = sequence_frame(scene, sequence, index)
    first = scene.rig.polarimetric_cameras()[0].id
    cameras = (first, *(camera.id for camera in scene.rig.cameras if camera.role != "polarimetric"))
    return exposure_from(render_frame(scene, mesh, maps, subsurface, cameras=cameras), scene)


def with_exposure(rig: Rig, exposures: dict[str, float]) -> Rig:
    """The rig with each camera's exposure set from ``exposures`` (camera id -> exposure), so demosaiced
    images come back in radiance units."""
    data = rig.model_dump(mode="json")
    for camera in data["cameras"]:
        camera["exposure"] = exposures[camera["id"]]
    return Rig.model_validate(data)
