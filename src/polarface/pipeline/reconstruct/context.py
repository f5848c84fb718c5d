"""What a reconstruction's stages share (the bottom module of :mod:`polarface.pipeline.reconstruct`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from polarface.results import ResultFolder

__all__ = ["ReconstructContext"]


@dataclasses.dataclass
class ReconstructContext:
    """What the stages share: inputs, options and the RESULT folder; ``executor`` runs the geometry stage's
    frames, the polarimetric stage's patches and the dynamic stage's frames
    (:class:`polarface.executors.Executor`; None: in this process). ``geometry_folder`` is the GEOM folder
    the run uses (``RESULT/geometry`` with stereo geometry, a given one, or None: known geometry).
    ``optimizer_given``: the user chose the optimiser in ``fit_options``; otherwise the polarimetric stage
    chooses it from the geometry (:func:`polarface.pipeline.reconstruct.options.surface_fit_options`)."""

    capture: Path
    out: Path
    mesh_path: Path
    poses_path: Path
    texture_resolution: int
    device: str
    resume: bool
    progress: bool
    holdout_every: int
    fit_options: dict = dataclasses.field(default_factory=dict)
    stop_after_patches: int | None = None
    threads: int | None = 1
    geometry_folder: Path | None = None
    stereo: bool = False
    dynamic: Path | None = None
    frames: str | None = None
    executor: Any = None
    view_check: bool = False
    optimizer_given: bool = False

    @property
    def folder(self) -> ResultFolder:
        """The RESULT folder."""
        return ResultFolder(self.out)
