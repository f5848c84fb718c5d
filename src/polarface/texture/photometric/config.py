"""Options of the photometric refinements (the bottom module of :mod:`polarface.texture.photometric`)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

__all__ = ["ROLES", "SurfaceRefinementConfig", "ViewSampling"]

#: Camera roles whose images the refinements may use.
ROLES = ("polarimetric", "stereo")


def _positive(owner: str, **values: float) -> None:
    for name, value in values.items():
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{owner}.{name} must be a finite number > 0; got {value!r}")


@dataclasses.dataclass(frozen=True)
class ViewSampling:
    """How the refinements sample the views in texture space.

    Attributes:
        patch_texels: side of the square window of the local normalisation and correlation (odd, texels;
            demo preset, measured: 3 gave a surface 0.160 mm median from the truth, 5 0.173 mm).
        cos_view_min: a camera sees a texel when the cosine between its normal and the view exceeds this.
        occlusion_tolerance_mm: a texel is hidden when its camera ray hits the surface this far before it.
        roles: the camera roles whose images are used (``polarimetric``: the cross-polarized ``I_sss``;
            ``stereo``: the raw frames).
        resolution: texture resolution of the sampling (None: ``scale`` times that of the caller's atlas).
        scale: the sampling's texture side over the caller's atlas's when ``resolution`` is None. Finer
            texels than the atlas's resolve the skin's texture better: demo preset, measured (the surface
            refinement, 3 x 3 windows): 512^2 -> 0.160 mm median vertex distance from the truth, 768^2
            -> 0.129 mm, 1024^2 -> 0.140 mm in 1.6 x the time of 768^2.
    """

    patch_texels: int = 3
    cos_view_min: float = 0.3
    occlusion_tolerance_mm: float = 1.0
    roles: tuple[str, ...] = ROLES
    resolution: int | None = None
    scale: float = 1.5

    def __post_init__(self) -> None:
        _positive("ViewSampling", occlusion_tolerance_mm=self.occlusion_tolerance_mm, scale=self.scale)
        if not isinstance(self.patch_texels, int) or self.patch_texels < 3 or self.patch_texels % 2 == 0:
            raise ValueError(
                f"ViewSampling.patch_texels must be an odd integer >= 3; got {self.patch_texels!r}"
            )
        if not -1.0 < self.cos_view_min < 1.0:
            raise ValueError(f"ViewSampling.cos_view_min must lie in (-1, 1); got {self.cos_view_min!r}")
        unknown = [role for role in self.roles if role not in ROLES]
        if not self.roles or unknown:
            raise ValueError(f"ViewSampling.roles must be a non-empty subset of {ROLES}; got {self.roles!r}")
        if self.resolution is not None and not (isinstance(self.resolution, int) and self.resolution >= 16):
            raise ValueError(
                f"ViewSampling.resolution must be None or an integer >= 16; got {self.resolution!r}"
            )

    def texture_size(self, atlas: int | None) -> int:
        """The sampling's texture side: ``resolution``, else ``scale`` x ``atlas`` (None: 512), rounded to an
        even number."""
        if self.resolution is not None:
            return int(self.resolution)
        return max(16, 2 * round(0.5 * self.scale * (atlas or 512)))


@dataclasses.dataclass(frozen=True)
class SurfaceRefinementConfig:
    """Options of :func:`polarface.texture.photometric.refine_surface` (``surface`` module docstring).

    Attributes:
        search_mm: offsets searched on either side of the surface, along its normal, mm.
        step_mm: spacing of the searched offsets, mm (the peak is found between them by a parabola; demo
            preset, measured: 0.2 mm gives the same surface as 0.1 mm, 0.178 mm median from the truth, in
            17 instead of 31 samplings per view).
        smoothing_texels: Gaussian sigma of the cost aggregation across the atlas, texels of the sampling
            (demo preset, 768^2, measured: 3 -> 0.126 mm, 4 -> 0.129 mm median vertex distance and 3.15
            vs 2.99 deg median vertex normal error, 6 -> 0.141 mm).
        fill_texels: Gaussian sigma of the normalised convolution filling the gaps, texels of the sampling.
        min_views: views (frame x camera) a texel needs to be refined.
        agreement_mm: a texel is refined only where the peaks of the even-numbered and of the
            odd-numbered frames (two independent measurements) lie this close (with a single frame: not
            tested).
        min_measured_fraction: the refinement is applied only when at least this fraction of the texels
            seen by ``min_views`` views were measured (the halves agree); below it the images do not
            resolve the surface better than it is (e.g. the tiny preset's 256 x 212 px frames, where a
            true surface would be moved by ~0.2 mm) and the mesh is returned unchanged.
        min_frame_score: a frame is flagged and left out of the sweep when its score (the mean over its
            texels of the best pairwise correlation of its views) is below this fraction of the median
            frame's: its cameras do not agree on any surface, e.g. a wrong pose. Demo preset, measured:
            the true frames >= 0.92, a frame turned 10 deg and shifted 20 mm 0.65 (flagged), turned 4
            deg and shifted 3 mm 0.83 (not: registration's residual tests catch such frames).
        sampling: how the views are sampled (:class:`ViewSampling`).
    """

    search_mm: float = 1.6
    step_mm: float = 0.2
    smoothing_texels: float = 4.0
    fill_texels: float = 12.0
    min_views: int = 4
    agreement_mm: float = 0.25
    min_measured_fraction: float = 0.5
    min_frame_score: float = 0.75
    sampling: ViewSampling = dataclasses.field(default_factory=ViewSampling)

    def __post_init__(self) -> None:
        _positive(
            "SurfaceRefinementConfig",
            search_mm=self.search_mm,
            step_mm=self.step_mm,
            agreement_mm=self.agreement_mm,
        )
        if self.step_mm > self.search_mm:
            raise ValueError(
                f"SurfaceRefinementConfig.step_mm ({self.step_mm}) must not exceed search_mm "
                f"({self.search_mm})"
            )
        for name in ("smoothing_texels", "fill_texels"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and value >= 0):
                raise ValueError(f"SurfaceRefinementConfig.{name} must be >= 0; got {value!r}")
        for name in ("min_measured_fraction", "min_frame_score"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0.0 <= value <= 1.0):
                raise ValueError(f"SurfaceRefinementConfig.{name} must lie in [0, 1]; got {value!r}")
        if not isinstance(self.min_views, int) or self.min_views < 2:
            raise ValueError(
                f"SurfaceRefinementConfig.min_views must be an integer >= 2; got {self.min_views!r}"
            )

    @property
    def offsets(self) -> np.ndarray:
        """``(J,)`` float64 searched offsets, mm, symmetric about 0."""
        half = round(self.search_mm / self.step_mm)
        return np.arange(-half, half + 1) * self.step_mm

    def to_json(self) -> dict[str, Any]:
        payload = dataclasses.asdict(self)
        payload["sampling"]["roles"] = list(self.sampling.roles)
        return payload
