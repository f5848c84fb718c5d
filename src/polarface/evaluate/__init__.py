"""The evaluation of a RESULT folder against the simulator's ground truth (``polarface evaluate``).

Between :mod:`polarface.inverse` and :mod:`polarface.export` in the layering: it reads RESULT and
simulation folders and writes nothing but its figures. By concept:

    alignment        the model frames of the RESULT and the ground truth and their alignment
    correspondence   RESULT texel -> ground-truth surface point (texel by texel, or closest point)
    appearance       the ``polarimetric`` and ``rerender`` groups (the static fit's maps)
    biophysical      the ``biophysical`` group (chromophore maps, rho_sss_bar re-render)
    geometry         the ``geometry`` group (surface accuracy, completeness, poses) and its heat map
    dynamic/         the ``dynamic`` group (tracking, per-frame maps, blood flow, flicker)
    groups           :data:`METRIC_GROUPS` (name -> function) and :func:`evaluate`, which runs them

A new metric goes into its group's module; a new group is one function and one entry of
:data:`METRIC_GROUPS`.
"""

from polarface.evaluate.appearance import polarimetric_metrics, rerender_metrics
from polarface.evaluate.biophysical import biophysical_metrics, check_ground_truth, evaluate_biophysical
from polarface.evaluate.correspondence import (
    CORRESPONDENCE_KINDS,
    GeometryEvaluationConfig,
    TexelCorrespondence,
    texel_correspondence,
)
from polarface.evaluate.dynamic import DynamicEvaluationConfig, dynamic_metrics
from polarface.evaluate.geometry import GEOMETRY_ERROR_PNG, geometry_metrics
from polarface.evaluate.groups import METRIC_GROUPS, evaluate, write_figures
from polarface.evaluate.validation import VALIDATION_FIGURE_PNG, validation_metrics

__all__ = [
    "CORRESPONDENCE_KINDS",
    "GEOMETRY_ERROR_PNG",
    "METRIC_GROUPS",
    "VALIDATION_FIGURE_PNG",
    "DynamicEvaluationConfig",
    "GeometryEvaluationConfig",
    "TexelCorrespondence",
    "biophysical_metrics",
    "check_ground_truth",
    "dynamic_metrics",
    "evaluate",
    "evaluate_biophysical",
    "geometry_metrics",
    "polarimetric_metrics",
    "rerender_metrics",
    "texel_correspondence",
    "validation_metrics",
    "write_figures",
]
