"""Orchestration over RESULT folders: the reconstruct stages and checkpoints, the biophysical stage's
files, the evaluation against ground truth and the demo jobs. Commands call one function of here."""

from polarface.pipeline.biophysical import load_stage_inputs, run_biophysical_stage
from polarface.pipeline.demo import reconstruct_summary_line, run_demo_pipeline, run_sphere_demo
from polarface.pipeline.evaluate import (
    METRIC_GROUPS,
    biophysical_metrics,
    evaluate,
    ground_truth_root,
    polarimetric_metrics,
    rerender_metrics,
)
from polarface.pipeline.evaluate_biophysical import evaluate_biophysical
from polarface.pipeline.reconstruct import (
    STAGES,
    ReconstructContext,
    ReconstructInputs,
    reconstruct,
    resolve_reconstruct_inputs,
    run_stages,
)

__all__ = [
    "METRIC_GROUPS",
    "STAGES",
    "ReconstructContext",
    "ReconstructInputs",
    "biophysical_metrics",
    "evaluate",
    "evaluate_biophysical",
    "ground_truth_root",
    "load_stage_inputs",
    "polarimetric_metrics",
    "reconstruct",
    "reconstruct_summary_line",
    "rerender_metrics",
    "resolve_reconstruct_inputs",
    "run_biophysical_stage",
    "run_demo_pipeline",
    "run_sphere_demo",
    "run_stages",
]
