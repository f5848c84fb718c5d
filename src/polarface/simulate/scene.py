"""What a simulation is: its configuration (:class:`SimulationConfig`) and the scene built from it once and
reused for every frame (:class:`SimulationScene`: rig, head asset, rest raster, ground-truth maps,
subsurface model, placement). The bottom module of the simulator's frame machinery: the sequences, the
frame renders, the ground-truth files, the frame units and the driver (:func:`polarface.simulate.simulate`)
all take the scene from here.
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any

import numpy as np

from polarface.capture.rig import Rig, paper_rig
from polarface.geometry.head_asset import HeadAsset, head_placement, load_head_asset
from polarface.geometry.uv_raster import UVRaster, rasterize_uv
from polarface.render.subsurface import SubsurfaceModel
from polarface.simulate.analyzers import SimulatedAnalyzers
from polarface.simulate.ground_truth import AppearanceMaps, build_appearance_maps, chromophore_maps
from polarface.simulate.layout import SEQUENCE_NAMES
from polarface.simulate.presets import SimulationPreset, get_preset, get_skin_type
from polarface.simulate.rig_perturbation import RigPerturbation

__all__ = ["MAP_SEED", "SimulationConfig", "SimulationScene"]

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
        exposure_fill: the exposures put the 99.5th percentile of the first frame's co-polarized image
            (the polarimetric cameras') and of each stereo camera's brightest colour channel at this
            fraction of the full well (fixed for the whole capture).
        static_frames: frames of the static sequence (None: the preset's); the yaw and pitch sweeps
            keep their ranges, so more frames sample them more densely (view-count studies,
            docs/reconstruct.md).
        single_scattering: the skin has its single-scattering lobe (False: rho_ss = 0 everywhere, a
            simulation on which a model without that lobe must do as well as the paper's;
            docs/validation.md).
        analyzers: the sensor's micro-polarizers (:class:`polarface.simulate.analyzers.SimulatedAnalyzers`;
            default ideal, today's bytes) and whether ``rig.json`` carries them (``docs/sensors.md``).
        rig_perturbation: how the rig the frames are rendered with differs from the nominal ``rig.json``
            the captures carry (:class:`polarface.simulate.rig_perturbation.RigPerturbation`; default:
            not at all); the true rig is written to ``ground_truth/rig.json`` (docs/calibration.md).
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
    single_scattering: bool = True
    analyzers: SimulatedAnalyzers = dataclasses.field(default_factory=SimulatedAnalyzers)
    rig_perturbation: RigPerturbation = dataclasses.field(default_factory=RigPerturbation)

    def __post_init__(self) -> None:
        """Check every field before any work (ValueError naming the argument)."""
        if not isinstance(self.analyzers, SimulatedAnalyzers):
            raise ValueError(f"argument 'analyzers' must be a SimulatedAnalyzers; got {self.analyzers!r}")
        if not isinstance(self.rig_perturbation, RigPerturbation):
            raise ValueError(f"argument 'rig_perturbation' must be a RigPerturbation; "
                             f"got {self.rig_perturbation!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int | np.integer) or self.seed < 0:
            raise ValueError(f"argument 'seed' must be an integer >= 0; got {self.seed!r}")
        get_preset(self.preset)
        get_skin_type(self.skin_type)
        bad = set(self.sequences) - set(SEQUENCE_NAMES)
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
        if not isinstance(self.single_scattering, bool):
            raise ValueError(f"argument 'single_scattering' must be a bool; got {self.single_scattering!r}")

    def to_json(self) -> dict:
        """The configuration as ``simulation.json`` records it (and as read back from it): the fields, the
        sequences as a list, the analyzers as :meth:`SimulatedAnalyzers.to_dict` (left out for the ideal
        sensor, the rig perturbation for the nominal rig and ``single_scattering`` when true: the
        configuration of older folders, which resume)."""
        config_dict = dataclasses.asdict(self)
        config_dict["sequences"] = list(self.sequences)
        if self.single_scattering:
            del config_dict["single_scattering"]
        if self.analyzers == SimulatedAnalyzers():  # ideal sensor: the configuration of older folders
            del config_dict["analyzers"]
        else:
            config_dict["analyzers"] = self.analyzers.to_dict()
        if self.rig_perturbation.is_nominal:  # the nominal rig: the configuration of older folders
            del config_dict["rig_perturbation"]
        else:
            config_dict["rig_perturbation"] = self.rig_perturbation.to_dict()
        return json.loads(json.dumps(config_dict))  # as read back from simulation.json


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
    #: camera id -> relative exposure, fixed by the first frame rendered (None: not yet;
    #: :func:`polarface.simulate.render.frame_exposure`)
    exposures: dict[str, float] | None = None
    #: arrays derived from the scene once, when a frame first needs them (e.g. the dynamic sequence's
    #: rest rho_sss_bar, :func:`polarface.simulate.sequences.with_c_h_out`); the scene's copies
    #: (``dataclasses.replace``) share it.
    derived: dict[str, Any] = dataclasses.field(default_factory=dict, repr=False)

    def true_rig(self) -> Rig:
        """The rig the frames are rendered with: ``rig`` (the nominal rig the captures carry, with the
        exposures) as ``config.rig_perturbation`` makes it (``rig`` itself when nothing is perturbed)."""
        return self.config.rig_perturbation.true_rig(self.rig)

    @classmethod
    def build(cls, config: SimulationConfig) -> SimulationScene:
        preset = get_preset(config.preset)
        if config.static_frames is not None:
            preset = dataclasses.replace(preset, static_frames=int(config.static_frames))
        rig = _with_stereo_resolution(
            paper_rig(width=preset.width, height=preset.height), preset.stereo_width, preset.stereo_height
        )
        rig = config.analyzers.rig_for_folder(rig)  # the true analyzers when the calibration is supplied
        if rig.spectral is None:  # pragma: no cover - the skin module is part of the package
            raise ValueError("the rig has no spectral calibration")
        calibration = config.rig_perturbation.true_rig(rig).spectral.to_calibration()  # the true channels
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
        if not config.single_scattering:
            maps = dataclasses.replace(maps, rho_ss=np.zeros_like(maps.rho_ss))
        subsurface = SubsurfaceModel.build(
            chromophore_maps(maps), raster, calibration.wavelengths_nm, per_texel_stretch=config.texel_stretch
        )
        return cls(config, preset, rig, asset, raster, maps, calibration, subsurface, head_placement())


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
