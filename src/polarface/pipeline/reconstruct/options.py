"""The fit options a reconstruction runs with (:func:`polarface.pipeline.reconstruct.run.reconstruct`): the
user's :class:`polarface.inverse.polarimetric.PolarimetricConfig` overrides over the patch grid that the
device (or a resumed RESULT) chooses. The optimiser is the same whatever the geometry's source
(docs/reconstruct.md, "Optimiser and geometry")."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from polarface.results import ResultFolder

__all__ = ["resolve_fit_options"]

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
