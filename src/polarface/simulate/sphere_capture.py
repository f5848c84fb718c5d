"""A small synthetic static capture with known maps: a UV-mapped spherical cap on a turning chair.

For tests, benchmarks and examples of the polarimetric stage without the full head simulator: the
cap (radius ``radius_mm``, orthographic UV chart) is posed in front of :func:`polarface.capture.rig.paper_rig`
(small image), its parameter maps are smooth fields, the subsurface term is *local*
(``E = rho_sss_bar Phi``, the polarimetric stage's own model), and the frames are rendered with the
renderer (:func:`polarface.render.renderer.render_view`: shadow rays, full Mueller
specular), mosaicked, quantised (optionally with shot/read noise) and stored with
:class:`polarface.capture.store.CaptureStore` (demosaiced on ingest), exactly as real data would be.

``make_sphere_capture(out)`` writes::

    out/static/        capture store
    out/ground_truth/  maps/<name>.exr + mask.png, mesh_rest.obj, static/poses.json (simulator layout)
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import torch

from polarface.capture.analyzers import measured_analyzer_intensities
from polarface.capture.rig import Rig, paper_rig
from polarface.capture.sensor import SensorNoise, mosaic, simulate_raw
from polarface.capture.store import CaptureStore
from polarface.geometry.mesh import TriangleMesh, save_obj
from polarface.geometry.poses import rigid_transform, save_poses
from polarface.geometry.raycast import RayCaster
from polarface.geometry.uv_raster import UVRaster, rasterize_uv, reposition
from polarface.io import write_exr, write_png
from polarface.optics.pbssrdf import SURFACE_PARAMETER_NAMES
from polarface.render.renderer import ViewRender, render_view, rig_lighting, shading_normals
from polarface.render.shading import FrameTextures
from polarface.render.subsurface import entering_flux
from polarface.simulate.analyzers import SimulatedAnalyzers
from polarface.simulate.layout import GROUND_TRUTH, REST_MESH_OBJ

__all__ = [
    "SphereCaptureConfig",
    "make_sphere_capture",
    "sphere_cap_mesh",
    "sphere_maps",
    "sphere_placement",
]


@dataclasses.dataclass(frozen=True)
class SphereCaptureConfig:
    """Sizes of the synthetic capture (defaults: a few seconds to build).

    Attributes:
        width, height: polarimetric image size (multiples of 4); texture_resolution: atlas side.
        frames: static frames; yaw_range_deg: +- yaw sweep; radius_mm: cap radius; cap_deg: cap half angle.
        noise: shot/read noise; seed: noise and map seed; heights: add a displacement bump field.
        analyzers: the sensor's micro-polarizers and whether ``rig.json`` carries them (default ideal;
            :class:`polarface.simulate.analyzers.SimulatedAnalyzers`, ``docs/sensors.md``).
    """

    width: int = 160
    height: int = 128
    texture_resolution: int = 24
    frames: int = 4
    yaw_range_deg: float = 25.0
    radius_mm: float = 70.0
    cap_deg: float = 70.0
    noise: bool = False
    seed: int = 0
    heights: bool = True
    analyzers: SimulatedAnalyzers = dataclasses.field(default_factory=SimulatedAnalyzers)


def sphere_cap_mesh(radius_mm: float = 70.0, cap_deg: float = 70.0, segments: int = 48) -> TriangleMesh:
    """Spherical cap around +z (model frame, centre at the origin, mm) with an orthographic UV chart."""
    limit = math.sin(math.radians(cap_deg))
    grid = np.linspace(-limit, limit, segments + 1)
    x, y = np.meshgrid(grid, grid)
    inside = x * x + y * y <= limit * limit + 1e-12
    index = -np.ones(x.shape, np.int64)
    index[inside] = np.arange(int(inside.sum()))
    z = np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, 1.0))
    vertices = radius_mm * np.stack([x[inside], y[inside], z[inside]], axis=1)
    uv = np.stack([(x[inside] / limit + 1) / 2, (y[inside] / limit + 1) / 2], axis=1)
    a, b = index[:-1, :-1], index[:-1, 1:]
    c, d = index[1:, :-1], index[1:, 1:]
    full = (a >= 0) & (b >= 0) & (c >= 0) & (d >= 0)
    faces = np.concatenate(
        [np.stack([a[full], b[full], d[full]], 1), np.stack([a[full], d[full], c[full]], 1)]
    )
    return TriangleMesh.from_arrays(vertices, np.asarray(faces), uv, source="sphere cap")


def sphere_maps(
    resolution: int, mask: np.ndarray, seed: int = 0, heights: bool = True
) -> dict[str, np.ndarray]:
    """Smooth ground-truth maps ``(R, R)`` float32 (``rho_sss_bar`` ``(R, R, 6)``) in skin-like ranges."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:resolution, 0:resolution] / max(resolution - 1, 1)
    phase = rng.uniform(0, 2 * np.pi, 8)
    def wave(k: int) -> np.ndarray:
        along_u = np.sin(2 * np.pi * (x * (1 + k % 2) + phase[k]) / 1.5)
        return along_u * np.cos(2 * np.pi * (y + phase[k + 1]) / 1.7)

    maps = {
        "eta": 1.42 + 0.05 * wave(0),
        "alpha_s": 0.4 + 0.08 * wave(1),
        "alpha_ss": 0.9 + 0.05 * wave(2),
        "rho_s": 0.5 + 0.15 * wave(3),
        "rho_ss": 0.25 + 0.05 * wave(4),
        "displacement_mm": (0.04 * np.sin(2 * np.pi * 2.5 * x) * np.sin(2 * np.pi * 2.0 * y))
        if heights
        else np.zeros_like(x),
    }
    base = np.array([0.55, 0.40, 0.30, 0.50, 0.35, 0.25])
    maps["rho_sss_bar"] = base[None, None] * (1.0 + 0.15 * wave(5)[..., None])
    out = {
        k: np.where(mask if v.ndim == 2 else mask[..., None], v, 0.0).astype(np.float32)
        for k, v in maps.items()
    }
    out["eta"] = np.where(mask, out["eta"], 1.4).astype(np.float32)
    return out


def sphere_placement(yaw: float) -> np.ndarray:
    """``(4, 4)`` model -> rig world: face the cameras (half turn about x), turn by ``yaw`` (radians),
    put it at 1 m."""
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    turn = rigid_transform(yaw=yaw)
    move = np.eye(4)
    move[:3, 3] = (0.0, 0.0, 1000.0)
    return move @ flip @ turn


def _render_frames(
    mesh: TriangleMesh, raster: UVRaster, maps: dict[str, np.ndarray], rig: Rig, poses: np.ndarray
) -> list[dict[str, ViewRender]]:
    """Noise-free renders of the polarimetric cameras, one ``camera id -> ViewRender`` per pose."""
    cameras = rig.polarimetric_cameras()
    lights, intensity = rig_lighting(rig)
    reference_up = cameras[0].pinhole().up_vector
    renders = []
    for pose in poses:
        mesh_world = mesh.transformed(pose)
        caster = RayCaster(mesh_world)
        posed = reposition(raster, mesh_world)
        shading = shading_normals(posed, maps["displacement_mm"])
        flux = entering_flux(caster, posed, shading, maps["eta"], lights, intensity, reference_up)
        exitance = maps["rho_sss_bar"] * flux[..., None]
        textures = FrameTextures.build(
            {k: maps[k] for k in SURFACE_PARAMETER_NAMES},
            shading,
            exitance,
            posed.mask,
        )
        views = {}
        for camera in cameras:
            channels = tuple(camera.colour_channels[c] for c in ("R", "G", "B"))
            views[camera.id] = render_view(
                caster, mesh_world, camera.pinhole(), textures, lights, intensity, channels
            )
        renders.append(views)
    return renders


def _store_frames(
    out: Path, rig: Rig, renders: list[dict[str, ViewRender]], config: SphereCaptureConfig
) -> Rig:
    """Expose, mosaic, quantise and store the renders in ``out/static``; returns the exposed rig."""
    peak = max(
        float(np.percentile(v.images["i0"][v.mask], 99.5))
        for r in renders
        for v in r.values()
        if v.mask.any()
    )
    exposure = 0.8 / max(peak, 1e-12)
    data = rig.model_dump(mode="json")
    for camera in data["cameras"]:
        camera["exposure"] = exposure
    rig = Rig.model_validate(data)
    store = CaptureStore.create(out / "static", rig, sequence="static")
    noise = SensorNoise(exposure=exposure)
    true_models = {} if config.analyzers.is_ideal else config.analyzers.camera_models(rig)
    for index, views in enumerate(renders):
        raws = {}
        for number, camera in enumerate(rig.cameras):
            if camera.role == "polarimetric":
                view = views[camera.id]
                images = [np.ascontiguousarray(view.images[k]) for k in ("i0", "i45", "i90", "i135")]
                if camera.id in true_models:
                    images = list(measured_analyzer_intensities(np.stack(images), true_models[camera.id]))
                    images = [np.clip(image, 0.0, None) for image in images]
                images = [torch.from_numpy(np.ascontiguousarray(image)) for image in images]
                signal = mosaic(*images, sensor=camera.sensor).numpy()
            else:
                signal = np.zeros((camera.height, camera.width, 3))
            rng = np.random.default_rng((config.seed, index, number))
            if signal.ndim == 3:
                raws[camera.id] = np.stack(
                    [
                        simulate_raw(signal[..., c], noise, seed=rng, noiseless=not config.noise)
                        for c in range(3)
                    ],
                    axis=-1,
                )
            else:
                raws[camera.id] = simulate_raw(signal, noise, seed=rng, noiseless=not config.noise)
        store.add_frame(index, index / 20.0, raws)
    store.finalize()
    return rig


def make_sphere_capture(out: str | Path, config: SphereCaptureConfig | None = None) -> dict:
    """Render and store the synthetic capture (layout in the module docstring); returns a summary.

    Returns:
        ``{"capture": path, GROUND_TRUTH: path, "maps": maps, "mask": mask, "rig": Rig}`` (the ground-truth
        folder under the key :data:`~polarface.simulate.layout.GROUND_TRUTH`, its own name).
    """
    config = config or SphereCaptureConfig()
    out = Path(out)
    mesh = sphere_cap_mesh(config.radius_mm, config.cap_deg)
    raster = rasterize_uv(mesh, config.texture_resolution)
    maps = sphere_maps(config.texture_resolution, raster.mask, config.seed, config.heights)
    rig = config.analyzers.rig_for_folder(paper_rig(width=config.width, height=config.height))
    yaws = np.radians(np.linspace(-config.yaw_range_deg, config.yaw_range_deg, config.frames))
    poses = np.stack([sphere_placement(float(yaw)) for yaw in yaws])
    rig = _store_frames(out, rig, _render_frames(mesh, raster, maps, rig, poses), config)
    gt = out / GROUND_TRUTH
    for name, value in maps.items():
        if name == "rho_sss_bar":
            names = (
                rig.spectral.channel_names if rig.spectral is not None else [f"channel{i}" for i in range(6)]
            )
            write_exr(gt / "maps" / "rho_sss_bar.exr", {n: value[..., i] for i, n in enumerate(names)})
        else:
            write_exr(gt / "maps" / f"{name}.exr", {"Y": value})
    write_png(gt / "maps" / "mask.png", raster.mask.astype(np.uint8) * 255)
    save_obj(gt / REST_MESH_OBJ, mesh)
    save_poses(gt / "static" / "poses.json", poses)
    return {"capture": out / "static", GROUND_TRUTH: gt, "maps": maps, "mask": raster.mask, "rig": rig}
