"""The rig simulator: synthetic captures of the bundled head with ground truth.

``simulate(out_dir, SimulationConfig(...))`` writes (layout in ``docs/simulate.md``)::

    SIM_DIR/
      simulation.json            configuration, channel order, exposure, timings, peak memory
      static/                    capture store (polarface.capture.store), sequence "static"
      dynamic/                   capture store, sequence "dynamic"
      ground_truth/
        maps/<name>.exr          parameter maps on the UV atlas (Y channel; rho_sss_bar: 6 named channels)
        maps/mask.png            atlas coverage
        mesh_rest.obj            the rest mesh in the model frame (mm, with UVs)
        static/poses.json        model -> rig-world 4x4 per static frame
        static/meshes/NNNNNN.ply posed mesh per static frame (rig world, mm)
        dynamic/meshes/NNNNNN.ply deformed + placed mesh per dynamic frame
        dynamic/maps/NNNNNN_c_h_out.exr, NNNNNN_rho_sss_bar.exr   per-frame maps that change (blood flow)
        observations.zarr        noise-free I_sss, I_zeta, I_s and texel->pixel visibility per view

Frames are resumable: the capture store skips complete frames and ground-truth files are written
atomically and skipped when present, so an interrupted run continues where it stopped. Rendering is
deterministic; raw noise is drawn from ``numpy.random.default_rng((seed, sequence, frame, camera))``.
"""

from __future__ import annotations

import dataclasses
import logging
import resource
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from polarface.capture.rig import Camera, Rig, paper_rig
from polarface.capture.sensor import SensorNoise, mosaic, simulate_raw
from polarface.capture.store import CaptureStore
from polarface.geometry.head_asset import HeadAsset, head_placement, load_head_asset
from polarface.geometry.mesh import TriangleMesh, save_ply
from polarface.geometry.raycast import RayCaster
from polarface.geometry.uv_raster import UVRaster, rasterize_uv, reposition
from polarface.io import read_json_object, write_exr, write_json_atomic
from polarface.render.renderer import render_view, rig_lighting, shading_normals
from polarface.render.shading import FrameTextures
from polarface.render.subsurface import SubsurfaceModel, entering_flux, texture_space_exitance
from polarface.simulate.ground_truth import AppearanceMaps, build_appearance_maps
from polarface.simulate.ground_truth_store import ObservationWriter, write_static_ground_truth
from polarface.simulate.presets import SimulationPreset, get_preset, get_skin_type
from polarface.simulate.sequences import FRAME_RATE_HZ, chromophore_maps, sequence_frames, static_poses

__all__ = ["SimulationConfig", "SimulationScene", "render_frame", "simulate"]

LOGGER = logging.getLogger(__name__)
#: Seed of the ground-truth map variations (fixed, so the simulation seed changes the noise only).
MAP_SEED = 2024


@dataclasses.dataclass(frozen=True)
class SimulationConfig:
    """What to simulate.

    Attributes:
        preset: ``tiny``, ``demo`` or ``full`` (:mod:`polarface.simulate.presets`).
        seed: seed of the sensor noise (the ground-truth maps are fixed: a different seed changes the
            noise only).
        skin_type: ``I``..``VI``.
        noise: add shot/read noise (False: only quantisation).
        subsurface_blur: diffuse light in texture space (False: local ``R_bar`` only, for tests).
        texel_stretch: blur with each texel's own size in mm (exact for a distorted atlas, ~20x
            slower) instead of the atlas's median texel size.
        sequences: which sequences to render (``static``, ``dynamic``).
        exposure_fill: the exposure puts the 99.5th percentile of the first frame's co-polarized image
            at this fraction of the full well (fixed for the whole capture).
        static_frames: frames of the static sequence (None: the preset's); the yaw and pitch sweeps
            keep their ranges, so more frames sample them more densely (view-count studies,
            docs/reconstruct.md).
    """

    preset: str = "demo"
    seed: int = 0
    skin_type: str = "II"
    noise: bool = True
    subsurface_blur: bool = True
    texel_stretch: bool = False
    sequences: tuple[str, ...] = ("static", "dynamic")
    exposure_fill: float = 0.8
    static_frames: int | None = None

    def __post_init__(self) -> None:
        """Check every field before any work (ValueError naming the argument)."""
        if isinstance(self.seed, bool) or not isinstance(self.seed, int | np.integer) or self.seed < 0:
            raise ValueError(f"argument 'seed' must be an integer >= 0; got {self.seed!r}")
        get_preset(self.preset)
        get_skin_type(self.skin_type)
        bad = set(self.sequences) - {"static", "dynamic"}
        if bad or not self.sequences:
            raise ValueError(
                f"argument 'sequences' must be a non-empty subset of static/dynamic; got {self.sequences}"
            )
        if self.static_frames is not None and (
            isinstance(self.static_frames, bool)
            or not isinstance(self.static_frames, int | np.integer)
            or self.static_frames < 2
        ):
            raise ValueError(f"argument 'static_frames' must be an integer >= 2; got {self.static_frames!r}")
        if not 0 < self.exposure_fill <= 1:  # NaN fails too
            raise ValueError(f"argument 'exposure_fill' must lie in (0, 1]; got {self.exposure_fill}")


@dataclasses.dataclass
class SimulationScene:
    """Everything fixed over a simulation: rig, asset, rest raster, maps, subsurface model.

    Built once by :meth:`build`; reused for every frame.
    """

    config: SimulationConfig
    preset: SimulationPreset
    rig: Rig
    asset: HeadAsset
    raster: UVRaster
    maps: AppearanceMaps
    calibration: object
    subsurface: SubsurfaceModel
    placement: np.ndarray
    exposure: float | None = None

    @classmethod
    def build(cls, config: SimulationConfig) -> SimulationScene:
        preset = get_preset(config.preset)
        if config.static_frames is not None:
            preset = dataclasses.replace(preset, static_frames=int(config.static_frames))
        rig = _with_stereo_resolution(
            paper_rig(width=preset.width, height=preset.height), preset.stereo_width, preset.stereo_height
        )
        if rig.spectral is None:  # pragma: no cover - the skin module is part of the package
            raise ValueError("the rig has no spectral calibration")
        calibration = rig.spectral.to_calibration()
        asset = load_head_asset(texture_resolution=preset.texture_resolution)
        raster = rasterize_uv(asset.mesh, preset.texture_resolution)
        landmarks = {name: asset.landmark_position(name) for name in asset.landmarks}
        maps = build_appearance_maps(
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
        subsurface = SubsurfaceModel.build(
            chromophore_maps(maps), raster, calibration.wavelengths_nm, per_texel_stretch=config.texel_stretch
        )
        return cls(config, preset, rig, asset, raster, maps, calibration, subsurface, head_placement())


def _camera_channels(camera: Camera) -> tuple[int, int, int]:
    return tuple(camera.colour_channels[c] for c in ("R", "G", "B"))  # type: ignore[return-value]


@dataclasses.dataclass(frozen=True)
class RenderedFrame:
    """The per-camera renders and the geometry of one frame (internal to the pipeline)."""

    mesh: TriangleMesh
    caster: RayCaster  # Embree scene of ``mesh``, reused for the texel visibility
    views: dict  # camera id -> ViewRender
    raster: UVRaster
    shading_normal: np.ndarray


def render_frame(
    scene: SimulationScene, mesh_world: TriangleMesh, maps: AppearanceMaps, subsurface: SubsurfaceModel
) -> RenderedFrame:
    """Render every camera of the rig for one posed/deformed head (noise-free radiance)."""
    caster = RayCaster(mesh_world)
    raster = reposition(scene.raster, mesh_world)
    shading = shading_normals(raster, maps.displacement_mm)
    lights, intensity = rig_lighting(scene.rig)
    reference = scene.rig.polarimetric_cameras()[0].pinhole()
    flux = entering_flux(caster, raster, shading, maps.eta, lights, intensity, reference.up_vector)
    exitance = texture_space_exitance(flux, subsurface, scene.calibration, blur=scene.config.subsurface_blur)
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
    return RenderedFrame(mesh_world, caster, views, raster, shading)


def _with_stereo_resolution(rig: Rig, width: int, height: int) -> Rig:
    """The rig with its RGB stereo cameras resampled to ``width`` x ``height`` (K scaled)."""
    cameras = []
    for camera in rig.cameras:
        if camera.role == "stereo" and (camera.width, camera.height) != (width, height):
            scale_x, scale_y = width / camera.width, height / camera.height
            K = np.asarray(camera.K, dtype=np.float64).copy()
            K[0] *= scale_x
            K[1] *= scale_y
            K[0, 2] = (width - 1) / 2.0
            K[1, 2] = (height - 1) / 2.0
            camera = camera.model_copy(update={"width": width, "height": height, "K": K.tolist()})
        cameras.append(camera)
    return Rig.model_validate(
        {**rig.model_dump(mode="json"), "cameras": [c.model_dump(mode="json") for c in cameras]}
    )


def _stereo_rgb(s0: np.ndarray, rig: Rig) -> np.ndarray:
    """RGB of an unfiltered camera from the six half-band channels: mean of each colour's two halves."""
    upper, lower = rig.polarimetric_cameras()[:2]
    rgb = [
        0.5 * (s0[..., upper.colour_channels[c]] + s0[..., lower.colour_channels[c]]) for c in ("R", "G", "B")
    ]
    return np.stack(rgb, axis=-1)


def _raw_frames(
    scene: SimulationScene, frame: RenderedFrame, sequence: str, index: int
) -> dict[str, np.ndarray]:
    """Noisy (or noise-free) integer raw frames of every camera."""
    noise = SensorNoise(exposure=float(scene.exposure))
    raws = {}
    for camera_number, camera in enumerate(scene.rig.cameras):
        view = frame.views[camera.id]
        rng = np.random.default_rng(
            (scene.config.seed, 0 if sequence == "static" else 1, index, camera_number)
        )
        if camera.role == "polarimetric":
            images = [
                torch.from_numpy(np.ascontiguousarray(view.images[k])) for k in ("i0", "i45", "i90", "i135")
            ]
            # Analyzer intensities are >= 0; clip float rounding (~1e-8) of s0 - s1 at dark pixels.
            signal = np.clip(mosaic(*images, sensor=camera.sensor).numpy(), 0.0, None)
            raws[camera.id] = simulate_raw(signal, noise, seed=rng, noiseless=not scene.config.noise)
        else:
            rgb = np.clip(_stereo_rgb(view.images["s0"], scene.rig), 0.0, None)
            channels = [
                simulate_raw(rgb[..., c], noise, seed=rng, noiseless=not scene.config.noise) for c in range(3)
            ]
            raws[camera.id] = np.stack(channels, axis=-1)
    return raws


def _exposure_from(frame: RenderedFrame, scene: SimulationScene) -> float:
    """Exposure putting the 99.5th percentile of the co-polarized image at ``exposure_fill``."""
    camera = scene.rig.polarimetric_cameras()[0]
    view = frame.views[camera.id]
    values = view.images["i0"][view.mask]
    level = float(np.percentile(values, 99.5)) if values.size else 1.0
    return scene.config.exposure_fill / max(level, 1e-12)


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _check_resumable(summary_path: Path, config_dict: dict) -> None:
    """ValueError unless ``summary_path`` is absent or records the configuration ``config_dict``."""
    if not summary_path.exists():
        return
    previous = read_json_object(summary_path)
    if previous.get("config") != config_dict:
        raise ValueError(
            f"'{summary_path.parent}' holds a simulation with another configuration {previous.get('config')}"
        )


def simulate(
    out_dir: str | Path, config: SimulationConfig, *, progress: bool = True, resume: bool = True
) -> dict:
    """Render the configured sequences into ``out_dir`` (see the module docstring); returns the summary.

    Resumable (``resume``): rerunning with the same configuration skips complete frames; a run killed
    at any point and resumed writes the same files as an uninterrupted one. ``simulation.json`` is
    written with ``complete: false`` and the configuration when the run starts, so an interrupted
    folder is refused to another configuration too.

    Raises:
        ValueError: ``out_dir`` holds a simulation with another configuration, or (``resume`` False)
            is not empty.
    """
    started = time.perf_counter()
    out = Path(out_dir)
    summary_path = out / "simulation.json"
    config_dict = _check_resume(out, config, resume)
    out.mkdir(parents=True, exist_ok=True)
    scene = SimulationScene.build(config)
    if not summary_path.exists():
        write_json_atomic(summary_path, _summary_head(config_dict, scene, complete=False))
    setup_s = time.perf_counter() - started
    poses = static_poses(scene)
    gt = out / "ground_truth"
    write_static_ground_truth(gt, scene, poses)
    counts = {"static": scene.preset.static_frames, "dynamic": scene.preset.dynamic_frames}
    writer = ObservationWriter(gt / "observations.zarr", scene, counts)
    timings: dict[str, float] = {"setup_s": setup_s}
    for sequence in config.sequences:
        seq_started = time.perf_counter()
        store: CaptureStore | None = None
        if (out / sequence / "rig.json").exists():
            store = CaptureStore.create(
                out / sequence, Rig.load(out / sequence / "rig.json"), sequence=sequence
            )
            scene.rig = store.rig
            scene.exposure = float(store.rig.cameras[0].exposure)
        frames = sequence_frames(scene, sequence)
        bar = tqdm(
            frames, total=counts[sequence], desc=f"simulate {sequence}", unit="frame", disable=not progress
        )
        for index, time_s, mesh, maps, subsurface in bar:
            mesh_path = gt / sequence / "meshes" / f"{index:06d}.ply"
            if (
                store is not None
                and store.has_frame(index)
                and writer.done(sequence, index)
                and mesh_path.exists()
            ):
                continue  # resume: this frame is complete
            frame = render_frame(scene, mesh, maps, subsurface)
            if scene.exposure is None:
                scene.exposure = _exposure_from(frame, scene)
                scene.rig = _with_exposure(scene.rig, scene.exposure)
            if store is None:
                store = CaptureStore.create(out / sequence, scene.rig, sequence=sequence)
            store.add_frame(index, time_s, _raw_frames(scene, frame, sequence, index))
            save_ply(mesh_path, mesh)
            if sequence == "dynamic":
                names = list(scene.calibration.channel_names)
                write_exr(gt / "dynamic" / "maps" / f"{index:06d}_c_h_out.exr", {"Y": maps.c_h_out})
                write_exr(
                    gt / "dynamic" / "maps" / f"{index:06d}_rho_sss_bar.exr",
                    {n: maps.rho_sss_bar[..., i] for i, n in enumerate(names)},
                )
            writer.write(sequence, index, frame)
        if store is not None:
            store.finalize()
        timings[f"{sequence}_s"] = time.perf_counter() - seq_started
    summary = {
        **_summary_head(config_dict, scene, complete=True),
        "exposure": scene.exposure,
        "frame_rate_hz": FRAME_RATE_HZ,
        "head_placement": scene.placement.tolist(),
        "timings": {**timings, "total_s": time.perf_counter() - started},
        "peak_rss_mb": _peak_rss_mb(),
    }
    write_json_atomic(summary_path, summary)
    return summary


def _check_resume(out: Path, config: SimulationConfig, resume: bool) -> dict:
    """The configuration as recorded in ``simulation.json``; refuse a folder this run must not continue.

    Stale ``.tmp-*`` files of a killed run under ``ground_truth/`` are removed (the capture stores
    remove theirs in :meth:`polarface.capture.store.CaptureStore.create`).
    """
    config_dict = dataclasses.asdict(config)
    config_dict["sequences"] = list(config.sequences)
    if out.exists() and not resume and any(out.iterdir()):
        raise ValueError(
            f"output folder '{out}' exists and is not empty; pass '--resume' or choose another --out"
        )
    for stale in sorted((out / "ground_truth").rglob(".tmp-*")):  # left by a killed run
        if stale.is_file():
            stale.unlink(missing_ok=True)
    _check_resumable(out / "simulation.json", config_dict)
    return config_dict


def _summary_head(config_dict: dict, scene: SimulationScene, *, complete: bool) -> dict:
    """The keys of ``simulation.json`` known when the run starts (``complete`` false until it ends)."""
    return {
        "format": "polarface-simulation",
        "version": 1,
        "complete": complete,
        "config": config_dict,
        "preset": dataclasses.asdict(scene.preset),
        "channel_names": list(scene.calibration.channel_names),
    }


def _with_exposure(rig: Rig, exposure: float) -> Rig:
    """The rig with every camera's exposure set (so demosaiced images come back in radiance units)."""
    data = rig.model_dump(mode="json")
    for camera in data["cameras"]:
        camera["exposure"] = exposure
    return Rig.model_validate(data)
