"""The fit options a reconstruction runs with (:func:`polarface.pipeline.reconstruct.run.reconstruct`): the
user's :class:`polarface.inverse.polarimetric.PolarimetricConfig` overrides over the patch grid that the
device (or a resumed RESULT) chooses (:func:`resolve_fit_options`), and, unless the user chose the
optimiser, the optimiser that the reference surface's quality calls for (:func:`surface_fit_options`;
docs/reconstruct.md, "Optimiser and geometry")."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from polarface.results import ResultFolder

__all__ = ["UNVERIFIED_SURFACE_FIT_OPTIONS", "resolve_fit_options", "surface_fit_options"]

#: Fit options used, unless the optimiser is given, on a reference surface from the stereo pairs that
#: the images did not verify (``geometry.json`` ``surface_refinement`` off or not applied: frames too
#: coarse to say where the surface is, as on the tiny preset). A converged L-BFGS fit walks to such a
#: surface's biased minimum (tiny: eta 0.079 -> 0.118, rho_s 65 -> 105 %), the paper's RMSprop for 150
#: steps stays near the closed-form starts. On a refined or known surface L-BFGS (the config's default)
#: is better on eta, the normals and rho_sss_bar.
UNVERIFIED_SURFACE_FIT_OPTIONS = {"optimizer": "rmsprop", "iterations": 150}

_PATCH_GRID = ("patch", "sample_budget")  # the fit options that a device chooses (device_fit_options)


def _units_per_gpu(executor: Any) -> int:
    """How many patches may share one GPU at a time: a process executor's workers, Ray's
    ``1 / gpus_per_unit`` for a fraction of a GPU per task (1 for whole GPUs); 1 in this process."""
    gpus = getattr(executor, "gpus_per_unit", None)
    if gpus:
        return max(1, int(1.0 / gpus)) if gpus < 1 else 1
    return max(1, int(getattr(executor, "workers", None) or 1))


def _patch_grid(device: str, executor: Any, out: Path, resume: bool) -> dict[str, int]:
    """``patch`` and ``sample_budget`` where the user gave none: on a resume those the RESULT recorded
    (its fingerprint), so that it goes on with the grid it started with on any device; otherwise
    :func:`polarface.inverse.polarimetric.device_fit_options` of the device resolved here (``"auto"``:
    this machine's), its GPU memory shared by the patches that :func:`_units_per_gpu` may run at once."""
    from polarface.device import resolve_device
    from polarface.inverse.polarimetric import device_fit_options

    if resume:
        recorded = ResultFolder(out).read_result().get("fingerprint")
        options = recorded.get("options") if isinstance(recorded, dict) else None
        if isinstance(options, dict) and all(isinstance(options.get(k), int) for k in _PATCH_GRID):
            return {k: options[k] for k in _PATCH_GRID}
    return device_fit_options(resolve_device(device), units_per_gpu=_units_per_gpu(executor))


def resolve_fit_options(fit_options: dict[str, Any] | None, device: str, executor: Any, out: Path,
                        resume: bool) -> dict[str, Any]:
    """``fit_options`` (None: none) over :func:`_patch_grid` of ``device``, ``executor`` and the RESULT
    folder ``out`` (``resume``)."""
    return {**_patch_grid(device, executor, out, resume), **(fit_options or {})}


def surface_fit_options(fit_options: dict[str, Any], optimizer_given: bool,
                        geometry_record: dict[str, Any]) -> tuple[dict[str, Any], str]:
    """The polarimetric stage's fit options and why its optimiser was chosen.

    Args:
        fit_options: the run's options (:func:`resolve_fit_options`).
        optimizer_given: the user chose the optimiser (then ``fit_options`` are used as they are).
        geometry_record: the GEOM folder's ``geometry.json`` (empty: known geometry, e.g. a simulation's
            ground truth or ``--mesh``/``--poses``).

    Returns:
        ``(options, choice)``: :data:`UNVERIFIED_SURFACE_FIT_OPTIONS` under ``fit_options`` when the
        record's surface was not verified by the images, and a one-line reason (``result.json``
        ``stages.polarimetric.optimizer_choice``).
    """
    if optimizer_given:
        return dict(fit_options), "given"
    if not geometry_record:
        return dict(fit_options), "known geometry"
    refinement = geometry_record.get("surface_refinement")
    if isinstance(refinement, dict) and refinement.get("applied"):
        return dict(fit_options), "stereo surface refined against the images"
    why = (refinement or {}).get("not_applied_reason") if isinstance(refinement, dict) else None
    return ({**UNVERIFIED_SURFACE_FIT_OPTIONS, **fit_options},
            f"stereo surface not refined ({why or 'refinement off'}): RMSprop for 150 steps")
