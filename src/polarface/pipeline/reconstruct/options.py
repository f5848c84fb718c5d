"""The fit options a reconstruction runs with (:func:`polarface.pipeline.reconstruct.stages.reconstruct`): the
user's :class:`polarface.inverse.polarimetric.PolarimetricConfig` overrides, over the paper's optimiser
when the geometry comes from the stereo pairs, over the patch grid that the device (or a resumed
RESULT) chooses."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from polarface.results import ResultFolder

__all__ = ["resolve_fit_options"]

#: Fit options used with geometry reconstructed from the stereo pairs unless given: the paper's RMSprop
#: for 150 iterations. A converged L-BFGS fit moves eta and rho_s to the stereo geometry's biased minimum
#: (demo: eta 0.043 -> 0.055, rho_s 42 % -> 61 %); docs/reconstruct.md, "Optimiser and geometry".
_STEREO_FIT_DEFAULTS = {"optimizer": "rmsprop", "iterations": 150}

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


def resolve_fit_options(fit_options: dict[str, Any] | None, stereo: bool, device: str, executor: Any,
                        out: Path, resume: bool) -> dict[str, Any]:
    """``fit_options`` (None: none) over :data:`_STEREO_FIT_DEFAULTS` when ``stereo`` (geometry from the
    stereo pairs) and no ``optimizer`` is given, over :func:`_patch_grid` of ``device``, ``executor`` and
    the RESULT folder ``out`` (``resume``)."""
    options = dict(fit_options or {})
    if stereo and "optimizer" not in options:
        options = {**_STEREO_FIT_DEFAULTS, **options}
    return {**_patch_grid(device, executor, out, resume), **options}
