"""Static captures whose radiance comes from Mitsuba 3 instead of polarface (docs/mitsuba_captures.md).

The simulator and the inverse stage share polarface's optics; a capture rendered by an independent
renderer protects against a mistake they would share. Per pixel of each polarimetric camera of the
simulator's rig (:func:`polarface.capture.rig.paper_rig` at a preset's image size), Mitsuba 3
(variant ``scalar_spectral_polarized``) provides:

* the hit point, UV and geometric normal of the camera ray on the posed head (``scene.ray_intersect``
  on a ``ply`` shape of the frame's mesh) and the LED shadows (``scene.ray_test``);
* the Mueller matrix of its ``pplastic`` BSDF (GGX specular with the full Fresnel Mueller matrix plus
  the local Fresnel-transmission diffuse lobe: the paper's pBSSRDF with ``rho_ss = 0``), evaluated
  once with (diffuse 1, specular 0) and once with (0, 1): the BSDF is linear in its two reflectances,
  which are then taken from the ground-truth textures (``rho_sss_bar`` per channel, ``rho_s``);
* the frame rotations between its implicit Stokes bases and the rig's frames (``mi.mueller``), the
  LEDs' linear polarizers and the camera's four analyzers (``mi.mueller.linear_polarizer``).

The parameter mapping (established against polarface's terms by ``tests/optics/test_pbssrdf.py``):
``int_ior = eta``, ``alpha = alpha_s`` (GGX, not squared), ``specular_reflectance = rho_s``,
``diffuse_reflectance = rho_sss_bar``. The shading normal is the ground truth's (the rest atlas's
interpolated normal with the displacement map, :func:`polarface.render.shading_normals`), read at the
hit's UV together with the other textures, since ``displacement_mm`` is one of the recovered maps.

Radiance then goes through polarface's sensor model and capture store (mosaic, quantisation,
optional noise, demosaicing on ingest) as in :mod:`polarface.simulate.pipeline`, and the ground truth
is written in the simulator's layout, so ``polarface reconstruct OUT/static --mesh
OUT/ground_truth/mesh_rest.obj --poses OUT/ground_truth/static/poses.json`` and ``polarface evaluate
RESULT --gt OUT`` work unchanged.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import numpy as np
import torch

from polarface.capture.rig import Camera, Rig, paper_rig
from polarface.capture.sensor import SensorNoise, mosaic, simulate_raw
from polarface.capture.store import CaptureStore
from polarface.geometry.head_asset import head_placement, load_head_asset
from polarface.geometry.mesh import TriangleMesh, save_obj, save_ply
from polarface.geometry.poses import StaticSequenceConfig, save_poses, static_sequence_poses
from polarface.geometry.uv_raster import UVRaster, rasterize_uv, reposition, sample_texture
from polarface.io import write_exr, write_json_atomic, write_png
from polarface.optics import stokes_frame
from polarface.render.renderer import shading_normals
from polarface.render.shading import fill_empty_texels
from polarface.simulate.ground_truth import build_appearance_maps
from polarface.simulate.presets import get_preset, get_skin_type
from polarface.simulate.scene import MAP_SEED

__all__ = [
    "ANALYZER_ANGLES",
    "MitsubaCaptureConfig",
    "MitsubaScene",
    "family_a",
    "family_b",
    "render_mitsuba_view",
    "write_mitsuba_capture",
]

#: Analyzer angles of the polarization cameras, radians from image +x towards camera up.
ANALYZER_ANGLES = {"i0": 0.0, "i45": math.pi / 4, "i90": math.pi / 2, "i135": 3 * math.pi / 4}
#: The paper's range of skin refractive indices (family B's eta must lie inside it).
ETA_RANGE = (1.15, 2.4)


@dataclasses.dataclass(frozen=True)
class MitsubaCaptureConfig:
    """What to render.

    Attributes:
        preset: simulator preset (:mod:`polarface.simulate.presets`) giving the rig's image size, the
            texture resolution of the truth maps and the static poses.
        frames: number of static frames rendered (the first ``frames`` of the sweep; None: all).
        sweep_frames, yaw_range_deg: frame count and yaw range (+-, degrees) of the static sweep (None:
            the preset's): the tiny preset's +-12 deg sees the face nearly frontally, where the DoP
            constrains eta weakly (docs/mitsuba_captures.md).
        texture_resolution: side of the truth maps' atlas in texels (None: the preset's); the
            reconstruction must use the same one for ``polarface evaluate``'s texel-by-texel metrics.
        eta: constant refractive index (dimensionless, in ``ETA_RANGE``).
        alpha_s: constant GGX roughness of the specular lobe (dimensionless, > 0).
        albedo_scale: multiplies the simulator's six-channel ``rho_sss_bar`` (result clipped to [0, 1]).
        rho_s_scale: multiplies the simulator's ``rho_s`` map.
        displacement: keep the simulator's displacement map (False: zero, the shading normal is the
            interpolated mesh normal).
        skin_type: simulator skin type ``I``..``VI`` (chooses the truth maps).
        noise: shot and read noise on the raw frames (False: quantisation only).
        seed: seed of the raw noise.
        renderer: ``mitsuba``, or ``polarface`` for a control capture of the identical scene whose radiance
            comes from polarface's image formation at the same hit points (``polarface_reference_views``,
            ``local``): recovery differences between the two isolate the renderer.
        exposure_fill: the 99.5th percentile of frame 0's co-polarized image of the first polarimetric
            camera is exposed at this fraction of the full well.
    """

    preset: str = "tiny"
    frames: int | None = None
    sweep_frames: int | None = None
    yaw_range_deg: float | None = None
    texture_resolution: int | None = None
    eta: float = 1.44
    alpha_s: float = 0.35
    albedo_scale: float = 1.0
    rho_s_scale: float = 1.0
    displacement: bool = True
    skin_type: str = "II"
    noise: bool = False
    seed: int = 0
    exposure_fill: float = 0.8
    renderer: str = "mitsuba"

    def __post_init__(self) -> None:
        get_preset(self.preset)
        if self.renderer not in ("mitsuba", "polarface"):
            raise ValueError(f"argument 'renderer' must be 'mitsuba' or 'polarface'; got {self.renderer!r}")
        get_skin_type(self.skin_type)
        if not ETA_RANGE[0] <= self.eta <= ETA_RANGE[1]:
            raise ValueError(f"argument 'eta' must lie in {ETA_RANGE}; got {self.eta}")
        if not 0.0 < self.alpha_s <= 1.0:
            raise ValueError(f"argument 'alpha_s' must lie in (0, 1]; got {self.alpha_s}")
        for name in ("albedo_scale", "rho_s_scale"):
            if not 0.0 <= getattr(self, name) < 10.0:
                raise ValueError(f"argument '{name}' must lie in [0, 10); got {getattr(self, name)}")
        if self.sweep_frames is not None and not 2 <= self.sweep_frames <= 1000:
            raise ValueError(f"argument 'sweep_frames' must lie in [2, 1000]; got {self.sweep_frames}")
        if self.yaw_range_deg is not None and not 0.0 <= self.yaw_range_deg <= 90.0:
            raise ValueError(f"argument 'yaw_range_deg' must lie in [0, 90]; got {self.yaw_range_deg}")
        sweep = self.sweep_frames or get_preset(self.preset).static_frames
        if self.frames is not None and not 1 <= self.frames <= sweep:
            raise ValueError(f"argument 'frames' must lie in [1, sweep frames]; got {self.frames}")
        if self.texture_resolution is not None and not 8 <= self.texture_resolution <= 4096:
            raise ValueError(
                f"argument 'texture_resolution' must lie in [8, 4096]; got {self.texture_resolution}"
            )
        if not 0.0 < self.exposure_fill <= 1.0:
            raise ValueError(f"argument 'exposure_fill' must lie in (0, 1]; got {self.exposure_fill}")


def family_a(preset: str = "tiny", **changes) -> MitsubaCaptureConfig:
    """Family A: the simulator's textured ``rho_s`` and ``rho_sss_bar``, constant eta 1.44, alpha_s 0.35."""
    return MitsubaCaptureConfig(preset=preset, **changes)


def family_b(
    eta: float, alpha_s: float, albedo_scale: float, preset: str = "tiny", **changes
) -> MitsubaCaptureConfig:
    """Family B: family A with the constant ``eta`` and ``alpha_s`` and the albedo scale chosen."""
    return MitsubaCaptureConfig(preset=preset, eta=eta, alpha_s=alpha_s, albedo_scale=albedo_scale, **changes)


@dataclasses.dataclass(frozen=True, eq=False)
class MitsubaScene:
    """Everything fixed over a capture.

    Attributes:
        config: the configuration.
        rig: the simulator's rig at the preset's image size (exposure not yet set).
        mesh: rest head mesh, model frame, mm, with UVs.
        raster: rest UV raster of ``mesh`` at the preset's texture resolution.
        maps: truth maps ``name -> (Ht, Wt)`` float32 (``rho_sss_bar`` ``(Ht, Wt, 6)``), zero outside
            ``mask``: eta, alpha_s, alpha_ss, rho_s, rho_ss (0), displacement_mm, rho_sss_bar.
        mask: ``(Ht, Wt)`` bool atlas coverage.
        poses: ``(N, 4, 4)`` float64 model -> rig-world transforms of the rendered static frames.
        channel_names: the six spectral channel names of the rig's calibration.
    """

    config: MitsubaCaptureConfig
    rig: Rig
    mesh: TriangleMesh
    raster: UVRaster
    maps: dict
    mask: np.ndarray
    poses: np.ndarray
    channel_names: tuple

    @classmethod
    def build(cls, config: MitsubaCaptureConfig) -> MitsubaScene:
        """The simulator's rig, head, truth maps and static poses for ``config``."""
        preset = get_preset(config.preset)
        rig = paper_rig(width=preset.width, height=preset.height)
        calibration = rig.spectral.to_calibration()
        resolution = config.texture_resolution or preset.texture_resolution
        asset = load_head_asset(texture_resolution=resolution)
        raster = rasterize_uv(asset.mesh, resolution)
        landmarks = {name: asset.landmark_position(name) for name in asset.landmarks}
        truth = build_appearance_maps(
            albedo_linear=asset.albedo,
            specular=asset.specular[..., 0],
            displacement_mm=asset.displacement[..., 0],
            positions=raster.position,
            mask=raster.mask,
            landmarks=landmarks,
            skin_type=get_skin_type(config.skin_type),
            calibration=calibration,
            seed=MAP_SEED,
        )
        mask = raster.mask
        inside = mask.astype(np.float32)
        maps = {
            "eta": np.float32(config.eta) * inside,
            "alpha_s": np.float32(config.alpha_s) * inside,
            "alpha_ss": truth.alpha_ss * inside,  # unused: rho_ss = 0
            "rho_s": np.float32(config.rho_s_scale) * truth.rho_s * inside,
            "rho_ss": np.zeros_like(inside),
            "displacement_mm": (truth.displacement_mm if config.displacement else 0.0) * inside,
            "rho_sss_bar": np.clip(config.albedo_scale * truth.rho_sss_bar, 0.0, 1.0) * inside[..., None],
        }
        maps = {k: np.asarray(v, np.float32) for k, v in maps.items()}
        sweep = config.sweep_frames or preset.static_frames
        yaw_range = preset.yaw_range_deg if config.yaw_range_deg is None else config.yaw_range_deg
        sequence = StaticSequenceConfig(
            frame_count=sweep,
            yaw_range=math.radians(yaw_range),
            pitch_amplitude=math.radians(preset.pitch_range_deg / 2.0),
            pivot=tuple(float(v) for v in asset.neck_pivot),
        )
        placement = head_placement()
        poses = np.stack([placement @ pose for pose in static_sequence_poses(sequence)])
        poses = poses[: config.frames or sweep]
        names = tuple(calibration.channel_names)
        return cls(config, rig, asset.mesh, raster, maps, mask, poses, names)


def _mitsuba():
    import mitsuba as mi

    mi.set_variant("scalar_spectral_polarized")
    return mi


def _pplastic(mi, eta: float, alpha: float, diffuse: float, specular: float):
    return mi.load_dict(
        {
            "type": "pplastic",
            "distribution": "ggx",
            "alpha": alpha,
            "int_ior": eta,
            "ext_ior": 1.0,
            "diffuse_reflectance": {"type": "uniform", "value": diffuse},
            "specular_reflectance": {"type": "uniform", "value": specular},
        }
    )


@dataclasses.dataclass(frozen=True, eq=False)
class _Hits:
    """Mitsuba's first hits of a camera's pixel rays (``N`` hit pixels) and the LED shadow tests."""

    pixel: np.ndarray  # (N,) int64 flat pixel index
    position: np.ndarray  # (N, 3) float64 world mm
    uv: np.ndarray  # (N, 2) float64 texture coordinates (v up, the mesh's convention)
    geometric_normal: np.ndarray  # (N, 3) float64 unit, facing the camera
    lit: np.ndarray  # (N, K) bool: the shadow ray to LED k is free


def _cast(mi, scene, camera, lights: np.ndarray) -> _Hits:
    """Camera rays through the pixel centres against Mitsuba's scene, and the shadow rays to the LEDs."""
    origins, directions = camera.pixel_rays()
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
    rows: list[tuple] = []
    for pixel in range(len(origins)):
        ray = mi.Ray3f(mi.Point3f(*origins[pixel]), mi.Vector3f(*directions[pixel]))
        si = scene.ray_intersect(ray)
        if not si.is_valid():
            continue
        lit = tuple(not scene.ray_test(si.spawn_ray_to(mi.Point3f(*light))) for light in lights)
        rows.append((pixel, tuple(si.p), tuple(si.uv), tuple(si.n), lit))
    if not rows:
        empty = np.zeros((0, 3))
        return _Hits(np.zeros(0, np.int64), empty, np.zeros((0, 2)), empty, np.zeros((0, len(lights)), bool))
    pixel, position, uv, normal, lit = (np.asarray(column) for column in zip(*rows, strict=True))
    normal = normal / np.linalg.norm(normal, axis=1, keepdims=True)
    towards = np.einsum("nc,nc->n", normal, camera.center - position) < 0
    normal[towards] *= -1.0
    return _Hits(pixel.astype(np.int64), position, uv, normal, lit.astype(bool))


def _textures_at(scene: MitsubaScene, normal_map: np.ndarray, uv: np.ndarray) -> dict[str, np.ndarray]:
    """Bilinear reads of the truth maps and the posed shading-normal map at ``uv`` ``(N, 2)``."""
    stack = np.concatenate(
        [scene.maps["rho_s"][..., None], scene.maps["rho_sss_bar"], normal_map.astype(np.float32)], axis=-1
    )
    filled = torch.from_numpy(fill_empty_texels(stack, scene.mask))
    sampled = sample_texture(filled, torch.from_numpy(uv.astype(np.float32))).double().numpy()
    return {"rho_s": sampled[:, 0], "rho_sss_bar": sampled[:, 1:7], "normal": sampled[:, 7:10]}


def _facing(normal: np.ndarray, geometric: np.ndarray, to_camera: np.ndarray) -> np.ndarray:
    """Unit shading normals; where they face away from the camera (n . w_o <= 1e-3), the geometric one."""
    normal = normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    facing = np.einsum("nc,nc->n", normal, to_camera) > 1e-3
    return np.where(facing[:, None], normal, geometric)


def _analyzer_rows(mi) -> np.ndarray:
    """``(4, 4)`` first rows of Mitsuba's linear polarizer rotated to the four analyzer angles."""
    rows = []
    for angle in ANALYZER_ANGLES.values():
        matrix = mi.mueller.rotated_element(angle, mi.mueller.linear_polarizer(1.0))
        rows.append(np.array(matrix)[0, :, 0] if np.array(matrix).ndim == 3 else np.array(matrix)[0])
    return np.stack(rows)


def _light_stokes(mi, rig: Rig) -> np.ndarray:
    """``(K, 4)`` Stokes of each LED in its own frame: unpolarized light of unit radiant intensity
    through Mitsuba's linear polarizer at the module's ``polarizer_angle``."""
    out = []
    for light in rig.lights:
        matrix = np.array(mi.mueller.rotated_element(light.polarizer_angle, mi.mueller.linear_polarizer(1.0)))
        matrix = matrix[..., 0] if matrix.ndim == 3 else matrix
        out.append(matrix @ np.array([2.0, 0.0, 0.0, 0.0]))
    return np.stack(out)


def _light_intensities(rig: Rig) -> np.ndarray:
    """``(K, 6)`` radiant intensity of each module per spectral channel."""
    return np.stack(
        [np.broadcast_to(np.asarray(light.radiant_intensity, float), (6,)) for light in rig.lights]
    )


def _local(frame, vector: np.ndarray, mi):
    return frame.to_local(mi.Vector3f(*vector))


def _lobe_stokes(mi, hits: _Hits, normal: np.ndarray, camera, lights: np.ndarray, bsdfs, light_stokes):
    """``(N, K, 2, 4)`` camera-frame Stokes per unit irradiance-free light (BSDF x cos only) of the
    diffuse-only and specular-only pplastic for every hit and LED (0 where shadowed or below horizon)."""
    up = camera.up_vector
    w_o = camera.center - hits.position
    w_o /= np.linalg.norm(w_o, axis=1, keepdims=True)
    x_out = np.asarray(stokes_frame(w_o, up)[0])
    to_light = lights[None] - hits.position[:, None]
    w_i = to_light / np.linalg.norm(to_light, axis=2, keepdims=True)
    x_in = np.asarray(stokes_frame(-w_i, up)[0])
    cos_i = np.einsum("nkc,nc->nk", w_i, normal)
    ctx = mi.BSDFContext()
    si = mi.SurfaceInteraction3f()
    si.p = [0.0, 0.0, 0.0]
    si.n = [0.0, 0.0, 1.0]
    si.sh_frame = mi.Frame3f([0.0, 0.0, 1.0])
    si.wavelengths = [500.0, 550.0, 600.0, 650.0]
    out = np.zeros((len(normal), len(lights), 2, 4))
    for n in range(len(normal)):
        active = np.flatnonzero(hits.lit[n] & (cos_i[n] > 0.0))
        if active.size == 0:
            continue
        frame = mi.Frame3f(mi.Vector3f(*normal[n]))
        wo_local = _local(frame, w_o[n], mi)
        si.wi = wo_local  # Mitsuba: si.wi points to the sensor
        to_ours = np.array(
            mi.mueller.rotate_stokes_basis(
                wo_local, mi.mueller.stokes_basis(wo_local), _local(frame, x_out[n], mi)
            )
        )
        for k in active:
            wi_local = _local(frame, w_i[n, k], mi)
            back = -wi_local  # propagation direction of the incident light
            to_mitsuba = np.array(
                mi.mueller.rotate_stokes_basis(
                    back, _local(frame, x_in[n, k], mi), mi.mueller.stokes_basis(back)
                )
            )
            s_in = to_mitsuba @ light_stokes[k]
            for lobe, bsdf in enumerate(bsdfs):
                matrix = np.array(bsdf.eval(ctx, si, wi_local))
                matrix = matrix[..., 0] if matrix.ndim == 3 else matrix
                out[n, k, lobe] = to_ours @ (matrix @ s_in)
    return out


def render_mitsuba_view(
    scene: MitsubaScene, mi_scene, mesh_world: TriangleMesh, camera: Camera, normal_map: np.ndarray
) -> dict[str, np.ndarray]:
    """One polarimetric camera's noise-free analyzer images from Mitsuba.

    Args:
        scene: the capture's scene; mi_scene: Mitsuba scene of ``mesh_world`` (the posed head, mm).
        camera: a polarimetric camera of ``scene.rig``.
        normal_map: ``(Ht, Wt, 3)`` world unit shading normals of the posed frame.

    Returns:
        ``i0``, ``i45``, ``i90``, ``i135``: ``(H, W, 3)`` float32 radiance (LED intensity unit mm^-2
        sr^-1) in the camera's R, G, B channels; ``mask``: ``(H, W)`` bool hit pixels.
    """
    mi = _mitsuba()
    pinhole = camera.pinhole()
    lights = np.array([light.position_mm for light in scene.rig.lights], dtype=np.float64)
    hits = _cast(mi, mi_scene, pinhole, lights)
    channels = [camera.colour_channels[c] for c in ("R", "G", "B")]
    textures = _textures_at(scene, normal_map, hits.uv)
    normal = _facing(textures["normal"], hits.geometric_normal, _unit(pinhole.center - hits.position))
    bsdfs = (
        _pplastic(mi, scene.config.eta, scene.config.alpha_s, 1.0, 0.0),
        _pplastic(mi, scene.config.eta, scene.config.alpha_s, 0.0, 1.0),
    )
    lobes = _lobe_stokes(mi, hits, normal, pinhole, lights, bsdfs, _light_stokes(mi, scene.rig))
    distance2 = ((lights[None] - hits.position[:, None]) ** 2).sum(-1)  # (N, K)
    intensity = _light_intensities(scene.rig)[:, channels]  # (K, 3)
    weight = intensity[None] / distance2[..., None]  # (N, K, 3) irradiance factor I_k / Gamma^2
    diffuse = np.einsum("nkc,nks->ncs", weight, lobes[:, :, 0]) * textures["rho_sss_bar"][:, channels, None]
    specular = np.einsum("nkc,nks->ncs", weight, lobes[:, :, 1]) * textures["rho_s"][:, None, None]
    stokes = diffuse + specular  # (N, 3, 4) camera frame
    rows = _analyzer_rows(mi)
    height, width = pinhole.height, pinhole.width
    out = {}
    for index, name in enumerate(ANALYZER_ANGLES):
        image = np.zeros((height * width, 3), np.float32)
        image[hits.pixel] = stokes @ rows[index]
        out[name] = image.reshape(height, width, 3)
    mask = np.zeros(height * width, bool)
    mask[hits.pixel] = True
    out["mask"] = mask.reshape(height, width)
    return out


def _unit(vectors: np.ndarray) -> np.ndarray:
    return vectors / np.linalg.norm(vectors, axis=-1, keepdims=True)


def mitsuba_scene_of(mesh_path: Path):
    """Mitsuba scene holding the posed head PLY at ``mesh_path`` (vertex positions in rig-world mm)."""
    mi = _mitsuba()
    return mi.load_dict({"type": "scene", "head": {"type": "ply", "filename": str(mesh_path)}})


def render_frame_views(scene: MitsubaScene, pose: np.ndarray, mesh_path: Path) -> dict[str, dict]:
    """Analyzer images of every polarimetric camera for the head at ``pose``; the posed mesh is written
    to ``mesh_path`` (PLY, rig world, mm) and loaded by Mitsuba from there."""
    mesh_world = scene.mesh.transformed(pose)
    save_ply(mesh_path, mesh_world)
    if scene.config.renderer == "polarface":
        from mitsuba_reference import polarface_reference_views

        return polarface_reference_views(scene, pose)["local"]
    mi_scene = mitsuba_scene_of(mesh_path)
    posed = reposition(scene.raster, mesh_world)
    normal_map = shading_normals(posed, scene.maps["displacement_mm"])
    return {
        camera.id: render_mitsuba_view(scene, mi_scene, mesh_world, camera, normal_map)
        for camera in scene.rig.polarimetric_cameras()
    }


def _with_exposure(rig: Rig, exposure: float) -> Rig:
    data = rig.model_dump(mode="json")
    for camera in data["cameras"]:
        camera["exposure"] = exposure
    return Rig.model_validate(data)


def _raws(
    rig: Rig, views: dict[str, dict], config: MitsubaCaptureConfig, index: int
) -> dict[str, np.ndarray]:
    """Mosaicked, quantised (optionally noisy) raw frames of the polarimetric cameras."""
    noise = SensorNoise(exposure=float(rig.cameras[0].exposure))
    raws = {}
    for number, camera in enumerate(rig.polarimetric_cameras()):
        images = [torch.from_numpy(np.ascontiguousarray(views[camera.id][k])) for k in ANALYZER_ANGLES]
        signal = np.clip(mosaic(*images, sensor=camera.sensor).numpy(), 0.0, None)
        rng = np.random.default_rng((config.seed, 0, index, number))
        raws[camera.id] = simulate_raw(signal, noise, seed=rng, noiseless=not config.noise)
    return raws


def _write_ground_truth(root: Path, scene: MitsubaScene) -> None:
    for name, values in scene.maps.items():
        if name == "rho_sss_bar":
            write_exr(
                root / "maps" / "rho_sss_bar.exr",
                {n: values[..., i] for i, n in enumerate(scene.channel_names)},
            )
        else:
            write_exr(root / "maps" / f"{name}.exr", {"Y": values})
    write_png(root / "maps" / "mask.png", scene.mask.astype(np.uint8) * 255)
    save_obj(root / "mesh_rest.obj", scene.mesh)
    save_poses(root / "static" / "poses.json", scene.poses)


def write_mitsuba_capture(out: str | Path, config: MitsubaCaptureConfig, *, progress: bool = False) -> dict:
    """Render the capture into ``out`` and return its summary (also ``out/mitsuba_capture.json``).

    Layout::

        out/static/                        capture store (rig with exposure; polarimetric cameras only)
        out/ground_truth/maps/*.exr, mask.png   truth maps (simulator layout; rho_ss = 0)
        out/ground_truth/mesh_rest.obj     rest mesh (model frame, mm, UVs)
        out/ground_truth/static/poses.json model -> rig world per frame
        out/ground_truth/static/meshes/NNNNNN.ply   posed meshes Mitsuba rendered
        out/mitsuba_capture.json           configuration, exposure, timings

    Raises:
        ValueError: ``out`` exists and is not empty.
    """
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise ValueError(f"argument 'out': '{out}' exists and is not empty")
    started = time.perf_counter()
    scene = MitsubaScene.build(config)
    gt = out / "ground_truth"
    _write_ground_truth(gt, scene)
    rig, store = scene.rig, None
    render_s = 0.0
    for index, pose in enumerate(scene.poses):
        tick = time.perf_counter()
        views = render_frame_views(scene, pose, gt / "static" / "meshes" / f"{index:06d}.ply")
        render_s += time.perf_counter() - tick
        if store is None:
            first = views[rig.polarimetric_cameras()[0].id]
            level = float(np.percentile(first["i0"][first["mask"]], 99.5))
            rig = _with_exposure(rig, config.exposure_fill / max(level, 1e-12))
            store = CaptureStore.create(out / "static", rig, sequence="static")
        store.add_frame(index, index / 20.0, _raws(rig, views, config, index))
        if progress:
            print(f"frame {index}: {time.perf_counter() - tick:.1f} s", flush=True)
    store.finalize()
    summary = {
        "format": "polarface-mitsuba-capture",
        "config": dataclasses.asdict(config),
        "channel_names": list(scene.channel_names),
        "exposure": float(rig.cameras[0].exposure),
        "frames": len(scene.poses),
        "texture_resolution": list(scene.mask.shape),
        "timings": {"render_s": render_s, "total_s": time.perf_counter() - started},
    }
    write_json_atomic(out / "mitsuba_capture.json", summary)
    return summary
