"""The dynamic stage's configuration (the bottom module of :mod:`polarface.pipeline.dynamic`)."""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

from polarface.geometry.registration import RegistrationConfig
from polarface.geometry.tracking import TrackingConfig
from polarface.inverse.polarimetric.dynamic import DynamicConfig
from polarface.io import json_values
from polarface.pipeline.geometry import GeometryConfig

__all__ = ["DynamicStageConfig"]


@dataclasses.dataclass(frozen=True)
class DynamicStageConfig:
    """Options of the dynamic stage (defaults: the paper's weights, module docstring).

    Attributes:
        geometry: the per-frame stereo and meshing (only its ``stereo``, ``frame_voxel_mm`` and
            ``frame_poisson`` are used).
        alignment: ICP of the reference mesh onto the first frame's stereo surface.
        min_alignment_fitness: fraction of the first frame's stereo surface within the finest ICP
            distance of the aligned reference mesh; below it the alignment is refused (another subject,
            or the subject far from where the static capture had them). Measured: 0.98 (demo), 0.60 (tiny);
            median distance of the reference to the truth after alignment 0.31 mm (1.38 mm before).
        tracking: :class:`polarface.geometry.tracking.TrackingConfig`.
        fit: :class:`polarface.inverse.polarimetric.dynamic.DynamicConfig`.
        biophysical: run the chromophore fit per frame.
        biophysical_start: where a frame's chromophore fit starts. ``"static"`` (default): from the
            static RESULT's maps (chromophores and SoG shapes), which also regularise it, with no
            coarse search (paper, main text: over a short sequence mainly the haemoglobin changes;
            ``polarface.inverse.biophysical.warm_start``); ``"scratch"``: the static stage's full fit
            of each frame (coarse multi-start search, shape rounds). Recorded per frame in
            ``frames/NNNN/result.json`` (``stages.biophysical.start``). Measured in docs/dynamic.md.
        min_tracking_confidence: a frame's texels whose tracking confidence (the smallest over its
            triangle's corners of the :class:`~polarface.geometry.tracking.TrackedSequence` vertex
            confidences, in [0, 1], 0 where no camera tracked a vertex, averaged over
            ``tracking_support_rings`` rings; :func:`polarface.pipeline.dynamic.texel_tracking_confidence`)
            is below this are flagged: left out of the frame's mask and shown in its
            ``tracking_confidence`` map (docs/dynamic.md, "Texels the tracking could not follow"). 0 flags
            nothing.
        tracking_support_rings: the vertex confidences are averaged over this many rings of neighbours
            first (:func:`polarface.geometry.tracking.tracking_support`), so that a vertex missed amid
            tracked ones is kept and an untracked region wider than the rings is flagged.
    """

    geometry: GeometryConfig = dataclasses.field(default_factory=GeometryConfig)
    alignment: RegistrationConfig = dataclasses.field(default_factory=RegistrationConfig)
    min_alignment_fitness: float = 0.4
    tracking: TrackingConfig = dataclasses.field(default_factory=TrackingConfig)
    fit: DynamicConfig = dataclasses.field(default_factory=DynamicConfig)
    biophysical: bool = True
    biophysical_start: Literal["static", "scratch"] = "static"
    min_tracking_confidence: float = 0.05
    tracking_support_rings: int = 4

    def __post_init__(self) -> None:
        value = self.min_tracking_confidence
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
            raise ValueError(f"min_tracking_confidence must be a number in [0, 1]; got {value!r}")
        rings = self.tracking_support_rings
        if isinstance(rings, bool) or not isinstance(rings, int) or rings < 0:
            raise ValueError(f"tracking_support_rings must be an integer >= 0; got {rings!r}")
        if self.biophysical_start not in ("static", "scratch"):
            raise ValueError(
                f"biophysical_start must be 'static' or 'scratch'; got {self.biophysical_start!r}"
            )

    def to_json(self) -> dict[str, Any]:
        """The configuration as plain JSON values."""
        return json_values(dataclasses.asdict(self))
