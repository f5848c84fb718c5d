"""Metrics of a RESULT folder against simulator ground truth (``polarface evaluate``).

Metric groups (:data:`METRIC_GROUPS`, name -> function(result_dir, gt_dir) -> dict; downstream stages
add theirs). One naming scheme: an error statistic is ``<statistic>_<kind>_error`` (``median_abs_error``,
``mean_abs_error``, ``p95_abs_error``, ``median_relative_error``), a normalised RMSE ends in ``_rmse``,
and no value appears under two keys (keys listed in ``docs/reconstruct.md``, "evaluate"):

* ``polarimetric``, ``rerender``: the static fit's maps and their re-rendering on held-out views
  (:mod:`polarface.evaluate.appearance`);
* ``biophysical``: :func:`polarface.evaluate.biophysical.evaluate_biophysical` (same naming scheme:
  ``median_abs_error`` ...); skipped when the RESULT or the ground truth has no chromophore maps;
* ``geometry``: :func:`polarface.evaluate.geometry.geometry_metrics` (surface accuracy,
  completeness and pose errors of the stereo geometry stage); skipped in known-geometry mode;
* ``dynamic``: :func:`polarface.evaluate.dynamic.dynamic_metrics` (tracking, per-frame map and
  normal errors, blood-flow recovery, flicker of a dynamic sequence); skipped when the RESULT has no
  per-frame folders or the ground truth no ``dynamic/``;
* ``validation``: :func:`polarface.evaluate.validation.validation_metrics` (the RESULT rendered at the
  simulator's validation camera, novel viewpoints never fitted: full-render and specular RMSE, DoP
  error); skipped when the ground truth has no ``validation/``.

The ground truth (``SIM/ground_truth`` or that folder itself: one resolver,
:func:`polarface.simulate.layout.ground_truth_folder`) has the RESULT's ``maps/`` layout, its rest mesh
``mesh_rest.obj`` and poses ``static/poses.json``. Map metrics (``polarimetric``, ``biophysical``) go
through one :class:`~polarface.evaluate.correspondence.TexelCorrespondence`: texel by texel when the
RESULT's mesh and model frame are the ground truth's (known geometry), else each RESULT texel's closest
point on the ground-truth surface after aligning the model frames through the reference frame's poses
(texels more than 2 mm away excluded and counted); the ``correspondence`` key says which.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from polarface.evaluate.appearance import polarimetric_metrics, rerender_metrics
from polarface.evaluate.biophysical import biophysical_metrics
from polarface.evaluate.correspondence import texel_correspondence
from polarface.evaluate.dynamic import dynamic_group
from polarface.evaluate.geometry import GEOMETRY_ERROR_PNG, geometry_metrics, write_geometry_error_map
from polarface.evaluate.validation import VALIDATION_FIGURE_PNG, validation_metrics, write_validation_figure
from polarface.io import storage_path
from polarface.results import ResultFolder
from polarface.simulate.layout import ground_truth_folder

__all__ = ["METRIC_GROUPS", "evaluate", "write_figures"]

#: Metric groups: name -> function(result_dir, gt_dir) -> dict.
METRIC_GROUPS: dict[str, Callable[[Path, Path], dict]] = {
    "polarimetric": polarimetric_metrics,
    "rerender": rerender_metrics,
    "biophysical": biophysical_metrics,
    "geometry": geometry_metrics,
    "dynamic": dynamic_group,
    "validation": validation_metrics,
}


_LONGEST_GROUPS = ("dynamic", "validation", "rerender")  # submitted first: 8-30 s each on the demo


def evaluate(
    result_dir: str | Path,
    gt_dir: str | Path,
    groups: list[str] | None = None,
    figures_dir: str | Path | None = None,
) -> dict[str, Any]:
    """All requested metric groups (default all) as one dict ``{group: metrics}``.

    Args:
        result_dir: the RESULT folder; gt_dir: ``SIM`` or ``SIM/ground_truth``; groups: names of
            :data:`METRIC_GROUPS` (None or empty: all); they run side by side in threads.
        figures_dir: when given, the figures are written there (:func:`write_figures`): the geometry
            error heat map ``GEOMETRY_ERROR_PNG`` (:func:`write_geometry_error_map`; only with the
            closest-point correspondence, whose distances are not zero by construction) and the
            validation views ``VALIDATION_FIGURE_PNG``.

    Raises:
        FileNotFoundError: ``result_dir`` has no ``result.json`` or ``gt_dir`` no ground-truth maps;
            a map or mask the ``polarimetric``/``rerender`` groups read is missing (in either folder);
            a file of the closest-point correspondence or the ``geometry`` group (naming it).
        ValueError: an unknown group name, a malformed ``result.json``, a map whose shape is not the
            mask's or that holds NaN/inf inside the mask (each naming the file).
    """
    result_dir, gt_dir = storage_path(result_dir), Path(gt_dir)
    if not ResultFolder(result_dir).result_json_path.is_file():
        raise FileNotFoundError(f"'{result_dir}' is not a RESULT folder (no result.json)")
    ground_truth_folder(gt_dir, require="maps")
    names = list(METRIC_GROUPS) if not groups else groups
    unknown = [g for g in names if g not in METRIC_GROUPS]
    if unknown:
        raise ValueError(f"argument '--groups': unknown {unknown}; choose from {list(METRIC_GROUPS)}")
    # The groups read their own files: they run side by side (demo, 2 cores: 20.8 -> 15.1 s, the same
    # metrics), the longest first; an error is raised as a one-by-one run would raise it.
    workers = max(1, min(len(names), os.cpu_count() or 1))
    with ThreadPoolExecutor(max_workers=workers) as pool:
        futures = {name: pool.submit(METRIC_GROUPS[name], result_dir, gt_dir)
                   for name in sorted(names, key=lambda name: name not in _LONGEST_GROUPS)}
        metrics = {name: futures[name].result() for name in names}
    if figures_dir is not None:
        write_figures(result_dir, gt_dir, figures_dir)
    return metrics


def write_figures(result_dir: str | Path, gt_dir: str | Path, figures_dir: str | Path) -> list[Path]:
    """Write ``evaluate``'s figures into ``figures_dir`` (created); returns the paths written.

    The geometry error heat map ``figures_dir/geometry_error_mm.png`` over the RESULT's mask
    (closest-point correspondence only) and the validation camera's views, true, rendered and their
    error, ``figures_dir/validation_views.png`` (when the ground truth has a validation folder).
    """
    folder = ResultFolder(result_dir)
    mask = folder.read_mask()
    correspondence = texel_correspondence(result_dir, ground_truth_folder(gt_dir, require="maps"), mask.shape)
    written = [
        write_geometry_error_map(Path(figures_dir) / GEOMETRY_ERROR_PNG, correspondence, mask),
        write_validation_figure(result_dir, gt_dir, Path(figures_dir) / VALIDATION_FIGURE_PNG),
    ]
    return [path for path in written if path is not None]
