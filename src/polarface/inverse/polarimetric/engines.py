"""Registry of the implementations ("engines") of the polarimetric patch loss, in the manner of a
``*_METHODS`` mapping: :data:`POLARIMETRIC_ENGINES` maps a name to a :class:`PolarimetricEngine` and
:func:`resolve_engine` turns a user's choice (a name or ``"auto"``) into one of them.

* ``fused``: the numba kernel with analytic gradients (:mod:`polarface.inverse.polarimetric.kernel`),
  on compact per-texel samples (:class:`~polarface.inverse.polarimetric.fused.FusedSamples`); CPU only;
  the whole objective and its gradient run in numba (:mod:`polarface.inverse.polarimetric.step`), and
  RMSprop's update too.
* ``torch``: the vectorised torch autograd reference (:mod:`polarface.inverse.polarimetric.model`,
  :mod:`polarface.inverse.polarimetric.losses`); any device.

Both give the same loss and gradient (tests/inverse/polarimetric/test_kernel.py).
"""

from __future__ import annotations

import dataclasses

import torch

__all__ = ["POLARIMETRIC_ENGINES", "PolarimetricEngine", "resolve_engine"]


@dataclasses.dataclass(frozen=True)
class PolarimetricEngine:
    """One implementation of the patch loss.

    Attributes:
        name: registry key.
        fused_samples: whether a patch's
            :class:`~polarface.inverse.polarimetric.problem.PatchProblem` carries
            :class:`~polarface.inverse.polarimetric.fused.FusedSamples` (the fused kernel's input) besides
            its :class:`~polarface.inverse.polarimetric.model.SampleBatch`.
        device_types: torch device types it runs on (empty: any).
        description: one line for help texts.
    """

    name: str
    fused_samples: bool
    device_types: tuple[str, ...]
    description: str

    def supports(self, device: torch.device | str) -> bool:
        """Whether the engine runs on ``device``."""
        return not self.device_types or torch.device(device).type in self.device_types


#: Engine name -> engine.
POLARIMETRIC_ENGINES: dict[str, PolarimetricEngine] = {
    "fused": PolarimetricEngine("fused", True, ("cpu",), "numba kernel with analytic gradients (CPU)"),
    "torch": PolarimetricEngine("torch", False, (), "vectorised torch autograd reference (any device)"),
}


def resolve_engine(engine: str, device: torch.device | str) -> PolarimetricEngine:
    """The engine named ``engine``; ``"auto"``: ``fused`` on the CPU, ``torch`` on other devices.

    Raises:
        ValueError: unknown name.
    """
    if engine == "auto":
        return POLARIMETRIC_ENGINES["fused" if torch.device(device).type == "cpu" else "torch"]
    if engine not in POLARIMETRIC_ENGINES:
        names = ["auto", *POLARIMETRIC_ENGINES]
        listed = ", ".join(repr(n) for n in names[:-1]) + f" or {names[-1]!r}"
        raise ValueError(f"argument 'engine' must be {listed}; got {engine!r}")
    return POLARIMETRIC_ENGINES[engine]
