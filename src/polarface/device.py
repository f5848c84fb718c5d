"""Device selection: CUDA when available, else CPU; overridable by ``POLARFACE_DEVICE`` or argument."""

from __future__ import annotations

import os

import torch

__all__ = ["resolve_device"]


def resolve_device(device: str | torch.device | None = None) -> torch.device:
    """Return the torch device to compute on.

    Args:
        device: ``"cpu"``, ``"cuda"``, ``"cuda:1"``, ``"auto"`` or None. None and ``"auto"`` read the
            ``POLARFACE_DEVICE`` environment variable, then pick CUDA if available, else CPU.

    Raises:
        ValueError: if CUDA is requested but not available, a GPU index this machine does not have, or
            the string is not a device.
    """
    if device is None or (isinstance(device, str) and device == "auto"):
        device = os.environ.get("POLARFACE_DEVICE") or ("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(device)
    except RuntimeError as exc:
        raise ValueError(f"argument 'device': {device!r} is not a torch device ({exc})") from exc
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("argument 'device': CUDA was requested but torch.cuda.is_available() is False")
    if resolved.type == "cuda" and resolved.index is not None and resolved.index >= torch.cuda.device_count():
        raise ValueError(
            f"argument 'device': {device!r} names GPU {resolved.index}, but this machine has "
            f"{torch.cuda.device_count()} (cuda:0 to cuda:{torch.cuda.device_count() - 1})"
        )
    return resolved
