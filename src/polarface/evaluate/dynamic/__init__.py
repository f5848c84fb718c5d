"""The dynamic sequence against its ground truth: tracking, per-frame map and normal errors, blood-flow
recovery and flicker (``polarface evaluate``'s ``dynamic`` group).

    inputs     what the metrics read besides the maps: the RESULT's dynamic record, the per-frame truth
    measures   the measures themselves on arrays (pressed patch, recovery time constant, material points)
    metrics    the group: :func:`dynamic_metrics` over a RESULT and a ground-truth folder
"""

from polarface.evaluate.dynamic.inputs import DynamicInputs, load_dynamic_inputs
from polarface.evaluate.dynamic.measures import (
    fit_recovery_time_constant,
    material_point_errors,
    material_point_tracking,
    pressed_patch_weight,
)
from polarface.evaluate.dynamic.metrics import (
    DYNAMIC_METRIC_KEYS,
    DynamicEvaluationConfig,
    dynamic_group,
    dynamic_metrics,
)

__all__ = [
    "DYNAMIC_METRIC_KEYS",
    "DynamicEvaluationConfig",
    "DynamicInputs",
    "dynamic_group",
    "dynamic_metrics",
    "fit_recovery_time_constant",
    "load_dynamic_inputs",
    "material_point_errors",
    "material_point_tracking",
    "pressed_patch_weight",
]
