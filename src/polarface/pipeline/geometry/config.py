"""The geometry stage's configuration (the bottom module of :mod:`polarface.pipeline.geometry`)."""

from __future__ import annotations

import dataclasses
from typing import Any

from polarface.geometry.atlas import CylindricalAtlasConfig
from polarface.geometry.fusion import PoissonConfig
from polarface.geometry.registration import RegistrationConfig
from polarface.geometry.stereo import StereoConfig
from polarface.io import json_values
from polarface.texture.photometric import SurfaceRefinementConfig

__all__ = ["GeometryConfig"]


@dataclasses.dataclass(frozen=True)
class GeometryConfig:
    """Options of the geometry stage (defaults: the paper rig, module docstring).

    Attributes:
        stereo: dense stereo of each pair (:class:`polarface.geometry.stereo.StereoConfig`).
        frame_voxel_mm: the pairs' clouds of a frame are merged on this voxel grid, mm (0.75: the frame's
            Poisson mesh takes 2.0 s instead of 3.5 s at 0.5 mm, for a median distance to the truth
            0.003-0.007 mm larger; demo preset, measured).
        frame_poisson: screened Poisson meshing of each frame's cloud (``frame_meshes``); its
            ``min_confidence`` also sets which points count towards a frame's minimum of 16.
        frame_meshes: write each frame's own Poisson mesh (``frames/NNNNNN.ply``). Off by default:
            nothing downstream reads them (registration and fusion use the frames' clouds, the reference
            mesh is meshed from the fused cloud), and a frame's mesh took 1.7-2.3 s of its ~4 s (demo
            preset, measured). The dynamic stage meshes every frame regardless (tracking follows the
            frames' surfaces).
        registration: registration of the sequence
            (:class:`polarface.geometry.registration.RegistrationConfig`).
        reference_voxel_mm: the registered frames' clouds are merged on this voxel grid, mm.
        reference_poisson: meshing of the reference cloud; coarser than a frame's (cells of ~2.2 mm
            instead of ~1.1 mm): the base mesh carries the shape, the displacement map the detail, and
            the coarser mesh's normals are closer to the truth (demo preset, measured: median normal
            error 3.5 deg instead of 4.9 deg, surface distance 0.338 instead of 0.335 mm).
        surface_refinement: the reference mesh moved along its normals to where the views agree
            (:mod:`polarface.texture.photometric`; None: off). Demo preset, measured: the reference
            surface 0.307 -> 0.127 mm median from the truth, for about 60 s on an idle 2-core machine.
        texture_resolution: side of the reference mesh's UV atlas, texels.
        reference_frame: the capture frame whose rig world is the model frame (None: the middle frame).
    """

    stereo: StereoConfig = dataclasses.field(default_factory=StereoConfig)
    frame_voxel_mm: float = 0.75
    frame_poisson: PoissonConfig = dataclasses.field(default_factory=PoissonConfig)
    frame_meshes: bool = False
    registration: RegistrationConfig = dataclasses.field(default_factory=RegistrationConfig)
    reference_voxel_mm: float = 0.5
    reference_poisson: PoissonConfig = dataclasses.field(
        default_factory=lambda: PoissonConfig(resolution_mm=3.0)
    )
    surface_refinement: SurfaceRefinementConfig | None = dataclasses.field(
        default_factory=SurfaceRefinementConfig
    )
    texture_resolution: int = 512
    reference_frame: int | None = None

    def __post_init__(self) -> None:
        for name in ("frame_voxel_mm", "reference_voxel_mm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"argument '{name}' must be > 0; got {getattr(self, name)}")
        CylindricalAtlasConfig(resolution=int(self.texture_resolution))

    def to_json(self) -> dict[str, Any]:
        """The configuration as plain JSON values."""
        return json_values(dataclasses.asdict(self))
