"""The ``validation`` metric group: the RESULT rendered at the simulator's validation camera, novel
viewpoints the reconstruction never saw (:mod:`polarface.simulate.validation`), against the true images.

The paper's validation (Sec. 6): "we use a completely novel viewpoint of an RGB camera to render and
validate the results", reporting the RMSE of the full render and of the specular image, and the degree
of polarization against a reference polarization camera. Here the RESULT is posed at the validation
views' head pose through the model alignment of :mod:`polarface.evaluate.alignment`
(``head_pose @ A``), rendered with polarface's renderer (:func:`polarface.render.relight.result_scene`,
the RESULT's maps, mesh, displacement and diffusion profiles) in all six channels, and compared on the
pixels that both images cover and whose surface point the RESULT reconstructed (its mask). Keys:

* ``views``, ``pixels`` (compared, all views), ``coverage`` (compared / the true images' head pixels);
* ``full_rmse``: RMSE of ``s0`` (the unfiltered camera's image) over the compared pixels and six
  channels, divided by the mean true ``s0`` there;
* ``specular_rmse``: RMSE of the surface reflection alone (specular and single-scattering lobes, no
  subsurface light), divided by the same mean true ``s0`` (so the two add up on one scale);
* ``specular_rmse_over_mean_specular``: the same RMSE divided by the mean true specular image;
* ``dop``: ``median_abs_error`` and ``mean_abs_error`` of the degree of linear polarization over the
  compared pixels and channels (the issue's ``dop_abs_error``, in the groups' naming scheme);
* ``per_view``: ``full_rmse`` and ``specular_rmse`` per view, in the order of ``validation.json``.

Skipped (``{"skipped": reason}``) when the ground truth has no validation folder (a simulation made
before the validation camera).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from polarface.evaluate.alignment import model_alignment
from polarface.geometry.camera import PinholeCamera
from polarface.geometry.uv_raster import sample_texture
from polarface.io import agg_figure, read_exr, read_json_object, write_figure_png
from polarface.render.colour import encode_srgb, linear_rgb_from_channels
from polarface.render.relight import ResultScene, result_scene
from polarface.render.renderer import ViewRender, render_view
from polarface.results import ResultAppearance, ResultFolder
from polarface.simulate.layout import ground_truth_folder
from polarface.simulate.validation import VALIDATION_FOLDER, VALIDATION_FORMAT, VALIDATION_JSON

__all__ = [
    "VALIDATION_FIGURE_PNG",
    "ValidationView",
    "render_validation_view",
    "validation_metrics",
    "validation_views",
    "write_validation_figure",
]

#: File name of the validation figure under ``evaluate``'s ``figures_dir``.
VALIDATION_FIGURE_PNG = "validation_views.png"

#: True ``s0`` below this fraction of the views' median is left out of the DoP comparison (DoP of
#: near-black pixels is noise of the renderers' float rounding).
DOP_MIN_RELATIVE_S0 = 0.05


@dataclass(frozen=True)
class ValidationView:
    """One validation view: its id, camera and true images (``(h, w, 6)`` float32 ``s0``, ``s1``, ``s2``,
    ``specular``; ``mask`` ``(h, w)`` bool)."""

    id: str
    camera: PinholeCamera
    truth: dict[str, np.ndarray] = field(repr=False)
    mask: np.ndarray = field(repr=False)


def validation_views(gt_dir: str | Path) -> tuple[dict, list[ValidationView]] | None:
    """The validation index (``validation.json``) and its views under the ground truth of ``gt_dir``
    (``SIM`` or ``SIM/ground_truth``), or None when there is none.

    Raises:
        ValueError: an index of another format, or an image without the index's channels (naming the file).
    """
    folder = ground_truth_folder(gt_dir) / VALIDATION_FOLDER
    index_path = folder / VALIDATION_JSON
    if not index_path.is_file():
        return None
    index = read_json_object(index_path)
    if index.get("format") != VALIDATION_FORMAT:
        raise ValueError(f"'{index_path}': format must be {VALIDATION_FORMAT!r}; got {index.get('format')!r}")
    names = list(index["channel_names"])
    views = []
    for entry in index["views"]:
        path = folder / entry["file"]
        channels = read_exr(path)
        wanted = [f"{kind}.{name}" for kind in ("s0", "s1", "s2", "specular") for name in names] + ["mask"]
        missing = [name for name in wanted if name not in channels]
        if missing:
            raise ValueError(f"'{path}' lacks the channels {missing}")
        truth = {kind: np.stack([channels[f"{kind}.{name}"] for name in names], axis=-1)
                 for kind in ("s0", "s1", "s2", "specular")}
        views.append(ValidationView(entry["id"], PinholeCamera.from_dict(entry["camera"]), truth,
                                    channels["mask"] > 0.5))
    return index, views


def render_validation_view(scene: ResultScene, camera: PinholeCamera) -> tuple[ViewRender, ViewRender]:
    """The RESULT ``scene`` at ``camera``: the full polarized render (six channels) and the surface
    reflection alone (``s0``)."""
    channels = tuple(range(6))
    full = render_view(scene.caster, scene.mesh_world, camera, scene.textures, scene.lights, scene.intensity,
                       channels, polarization=True)
    surface = render_view(scene.caster, scene.mesh_world, camera, scene.textures.without_subsurface(),
                          scene.lights, scene.intensity, channels, polarization=False)
    return full, surface


def _reconstructed(view: ViewRender, mask: np.ndarray) -> np.ndarray:
    """Pixels of ``view`` whose surface point lies in the RESULT's ``mask`` (bilinear lookup > 0.999)."""
    inside = sample_texture(torch.from_numpy(mask.astype(np.float32)), torch.from_numpy(view.uv)).numpy()
    return view.mask & (inside > 0.999)


def _dop(s0: np.ndarray, s1: np.ndarray, s2: np.ndarray) -> np.ndarray:
    return np.hypot(s1, s2) / np.maximum(s0, 1e-12)


@dataclass
class _Sums:
    """Running sums over the views' compared pixels and channels."""

    values: int = 0
    pixels: int = 0
    head_pixels: int = 0
    full_sq: float = 0.0
    specular_sq: float = 0.0
    truth_s0: float = 0.0
    truth_specular: float = 0.0
    dop_errors: list[np.ndarray] = field(default_factory=list)
    per_view: dict[str, list[float | None]] = field(
        default_factory=lambda: {"full_rmse": [], "specular_rmse": []}
    )

    def add(self, view: ValidationView, full: ViewRender, surface: ViewRender, compared: np.ndarray) -> None:
        truth = {kind: image[compared].astype(np.float64) for kind, image in view.truth.items()}
        images = {name: image[compared].astype(np.float64) for name, image in full.images.items()}
        s0 = images["i0"] + images["i90"]
        full_sq = float(((s0 - truth["s0"]) ** 2).sum())
        specular_sq = float(((surface.images["s0"][compared] - truth["specular"]) ** 2).sum())
        self.values += truth["s0"].size
        self.pixels += int(compared.sum())
        self.head_pixels += int(view.mask.sum())
        self.full_sq += full_sq
        self.specular_sq += specular_sq
        self.truth_s0 += float(truth["s0"].sum())
        self.truth_specular += float(truth["specular"].sum())
        mean_s0 = float(truth["s0"].mean()) if truth["s0"].size else 0.0
        for key, sq in (("full_rmse", full_sq), ("specular_rmse", specular_sq)):
            self.per_view[key].append(math.sqrt(sq / truth["s0"].size) / mean_s0 if mean_s0 > 0 else None)
        if truth["s0"].size:
            dop_true = _dop(truth["s0"], truth["s1"], truth["s2"])
            dop_result = _dop(s0, images["i0"] - images["i90"], images["i45"] - images["i135"])
            bright = truth["s0"] > DOP_MIN_RELATIVE_S0 * float(np.median(truth["s0"]))
            self.dop_errors.append(np.abs(dop_result - dop_true)[bright].astype(np.float32))

    def summary(self) -> dict:
        if self.values == 0:
            raise ValueError("no validation pixel shows a reconstructed texel: the RESULT does not cover the "
                             "head the validation camera sees")
        rmse_full = math.sqrt(self.full_sq / self.values)
        rmse_specular = math.sqrt(self.specular_sq / self.values)
        mean_s0 = self.truth_s0 / self.values
        dop = np.concatenate(self.dop_errors) if self.dop_errors else np.zeros(0, np.float32)
        return {
            "views": len(self.per_view["full_rmse"]),
            "pixels": self.pixels,
            "coverage": self.pixels / max(self.head_pixels, 1),
            "full_rmse": rmse_full / mean_s0,
            "specular_rmse": rmse_specular / mean_s0,
            "specular_rmse_over_mean_specular": rmse_specular / max(self.truth_specular / self.values, 1e-12),
            "dop": {
                "median_abs_error": float(np.median(dop)) if dop.size else None,
                "mean_abs_error": float(dop.mean()) if dop.size else None,
            },
            "per_view": self.per_view,
            "normalisation": "RMSE over the compared pixels and six channels / mean true s0 there",
        }


def _posed_result(
    result_dir: str | Path, gt_dir: str | Path, index: dict
) -> tuple[ResultAppearance, ResultScene]:
    """The RESULT's appearance and its scene at the validation views' head pose (``head_pose @ A``)."""
    appearance = ResultAppearance.load(ResultFolder(result_dir))
    names = list(appearance.rig.spectral.channel_names)
    if names != list(index["channel_names"]):
        raise ValueError(f"the RESULT's channels {names} are not the validation images' "
                         f"{index['channel_names']}")
    pose = np.asarray(index["head_pose"], dtype=np.float64) @ model_alignment(result_dir, gt_dir)
    return appearance, result_scene(appearance, pose)


def validation_metrics(result_dir: str | Path, gt_dir: str | Path) -> dict:
    """The ``validation`` group (module docstring) of the RESULT at ``result_dir`` against ``gt_dir``.

    Raises:
        FileNotFoundError: a file the RESULT's render or the alignment needs (naming it).
        ValueError: a malformed validation folder, a RESULT whose channels are not the validation's, or
            one that covers none of the validation pixels.
    """
    loaded = validation_views(gt_dir)
    if loaded is None:
        folder = ground_truth_folder(gt_dir) / VALIDATION_FOLDER
        return {"skipped": f"'{folder}' does not exist (a simulation made before the validation camera)"}
    index, views = loaded
    appearance, scene = _posed_result(result_dir, gt_dir, index)
    sums = _Sums()
    for view in views:
        full, surface = render_validation_view(scene, view.camera)
        sums.add(view, full, surface, view.mask & _reconstructed(full, appearance.mask))
    return sums.summary()


def write_validation_figure(result_dir: str | Path, gt_dir: str | Path, path: str | Path) -> Path | None:
    """Write the validation figure to ``path``: for three views (the middle third's first, middle and last:
    left, front and right at the middle elevation for the presets' grids) the true image, the RESULT's
    render (sRGB of the unfiltered camera, one exposure) and the absolute error of ``s0`` relative to the
    mean true ``s0`` over the compared pixels. None (nothing written) without a validation folder."""
    loaded = validation_views(gt_dir)
    if loaded is None:
        return None
    index, views = loaded
    appearance, scene = _posed_result(result_dir, gt_dir, index)
    count = len(views)
    chosen = sorted({count // 3, count // 2, max(2 * count // 3 - 1, 0)})
    figure, axes = agg_figure(len(chosen), 3, figsize=(9.0, 2.6 * len(chosen)), squeeze=False,
                              layout="constrained")
    exposure = None
    for row, number in enumerate(chosen):
        view = views[number]
        full, _ = render_validation_view(scene, view.camera)
        s0 = full.images["i0"] + full.images["i90"]
        compared = view.mask & _reconstructed(full, appearance.mask)
        truth_rgb = linear_rgb_from_channels(view.truth["s0"], appearance.rig)
        if exposure is None:
            exposure = 0.85 / max(float(np.percentile(truth_rgb[view.mask], 99)), 1e-12)
        mean_s0 = max(float(view.truth["s0"][compared].mean()) if compared.any() else 1.0, 1e-12)
        error = np.where(compared, np.abs(s0 - view.truth["s0"]).mean(axis=-1) / mean_s0, np.nan)
        axes[row, 0].imshow(encode_srgb(truth_rgb * exposure))
        axes[row, 1].imshow(encode_srgb(linear_rgb_from_channels(s0, appearance.rig) * exposure))
        shown = axes[row, 2].imshow(error, cmap="magma", vmin=0.0, vmax=0.3)
        figure.colorbar(shown, ax=axes[row, 2], fraction=0.046)
        for column, title in enumerate(("truth", "RESULT rendered", "|error| / mean s0")):
            axes[row, column].set_title(f"{view.id}: {title}", fontsize=8)
            axes[row, column].set_axis_off()
    return Path(str(write_figure_png(path, figure, dpi=100)))
