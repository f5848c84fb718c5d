"""Argument checking and array-kind handling shared by every physics module.

Conventions (see ``docs/conventions.md``):

* Public physics functions accept torch tensors, numpy arrays or Python floats and return the same
  kind they were given (``@array_api`` below). Internally everything is a torch tensor.
* Bad input raises :class:`ValueError` whose message names the argument, never a silent NaN.
* Floating dtypes are kept: float32 stays float32, float64 stays float64. Python floats and integer
  inputs become float64 when no tensor decides otherwise (numpy's default).
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import numpy as np
import torch

__all__ = [
    "array_api",
    "as_float_tensor",
    "broadcast_named",
    "broadcast_shape",
    "check_finite",
    "check_last_dim",
    "check_range",
    "check_shape_tail",
    "check_unit_vectors",
    "inputs_trusted",
    "trusted_inputs",
]

_TRUSTED = contextvars.ContextVar("polarface_trusted_inputs", default=False)


@contextlib.contextmanager
def trusted_inputs():
    """Skip the value checks (finite, range, unit length) inside this block.

    For internal hot loops whose inputs were validated once upstream (the simulator's per-light
    rendering, the inverse stage's iterations). Shape checks and dtype conversion still run.
    """
    token = _TRUSTED.set(True)
    try:
        yield
    finally:
        _TRUSTED.reset(token)


def inputs_trusted() -> bool:
    """True inside a :func:`trusted_inputs` block (for checks written outside this module, e.g. the
    ray caster's numpy validation, to skip the same value checks)."""
    return _TRUSTED.get()


F = TypeVar("F", bound=Callable[..., Any])

_ARRAY_TYPES = (np.ndarray, np.generic, float, int, list, tuple)


def _result_dtype(values: Sequence[Any]) -> torch.dtype:
    """The floating dtype that the given inputs promote to (torch's rules, floats at least float32)."""
    dtype: torch.dtype | None = None
    for value in values:
        if isinstance(value, torch.Tensor):
            candidate = value.dtype if value.is_floating_point() else torch.float32
        elif isinstance(value, np.ndarray | np.generic):
            candidate = torch.float32 if value.dtype == np.float32 else torch.float64
        elif isinstance(value, float | int):
            continue
        else:
            candidate = torch.float64
        dtype = candidate if dtype is None else torch.promote_types(dtype, candidate)
    return dtype if dtype is not None else torch.float64


def as_float_tensor(
    value: Any,
    name: str,
    *,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
    allow_nonfinite: bool = False,
) -> torch.Tensor:
    """Convert ``value`` to a floating torch tensor, checking it is finite.

    Args:
        value: tensor, numpy array, Python number or nested sequence.
        name: argument name used in error messages.
        dtype: target floating dtype; default keeps a floating tensor's dtype, float64 otherwise.
        device: target device; default keeps a tensor's device (CPU for other inputs).
        allow_nonfinite: accept NaN and +-inf.

    Raises:
        ValueError: if ``value`` cannot be converted or holds NaN/inf (naming ``name``).
    """
    if isinstance(value, torch.Tensor):
        tensor = value
        if not tensor.is_floating_point():
            tensor = tensor.to(dtype or torch.float32)
    else:
        try:
            array = np.asarray(value)
        except Exception as exc:  # pragma: no cover - numpy raises many kinds
            raise ValueError(f"argument '{name}' cannot be converted to an array: {exc}") from exc
        if array.dtype == object or not np.issubdtype(array.dtype, np.number):
            raise ValueError(f"argument '{name}' must be numeric, got dtype {array.dtype}")
        if np.iscomplexobj(array):
            raise ValueError(f"argument '{name}' must be real-valued, got a complex array")
        target = np.float32 if array.dtype == np.float32 else np.float64
        tensor = torch.from_numpy(np.array(array, dtype=target, order="C"))
    if dtype is not None and tensor.dtype != dtype:
        tensor = tensor.to(dtype)
    if device is not None:
        tensor = tensor.to(device)
    if not allow_nonfinite:
        check_finite(tensor, name)
    return tensor


def check_finite(tensor: torch.Tensor, name: str) -> torch.Tensor:
    """Raise ``ValueError`` naming ``name`` if ``tensor`` holds NaN or inf."""
    if _TRUSTED.get():
        return tensor
    if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
        bad = int((~torch.isfinite(tensor)).sum())
        raise ValueError(f"argument '{name}' contains {bad} NaN or infinite value(s)")
    return tensor


def check_range(
    tensor: torch.Tensor,
    name: str,
    low: float | None = None,
    high: float | None = None,
    *,
    low_inclusive: bool = True,
    high_inclusive: bool = True,
) -> torch.Tensor:
    """Raise ``ValueError`` naming ``name`` if any value lies outside ``[low, high]``.

    The bounds are open instead of closed where ``low_inclusive``/``high_inclusive`` is False.
    """
    if _TRUSTED.get():
        return tensor
    if low is not None:
        bad = tensor < low if low_inclusive else tensor <= low
        if bool(bad.any()):
            op = ">=" if low_inclusive else ">"
            raise ValueError(f"argument '{name}' must be {op} {low}; got min {float(tensor.min()):.6g}")
    if high is not None:
        bad = tensor > high if high_inclusive else tensor >= high
        if bool(bad.any()):
            op = "<=" if high_inclusive else "<"
            raise ValueError(f"argument '{name}' must be {op} {high}; got max {float(tensor.max()):.6g}")
    return tensor


def check_last_dim(tensor: torch.Tensor, name: str, size: int) -> torch.Tensor:
    """Raise ``ValueError`` if the last axis of ``tensor`` is not ``size`` long."""
    if tensor.ndim == 0 or tensor.shape[-1] != size:
        raise ValueError(
            f"argument '{name}' must have a last axis of size {size}; got shape {tuple(tensor.shape)}"
        )
    return tensor


def check_shape_tail(tensor: torch.Tensor, name: str, tail: Sequence[int]) -> torch.Tensor:
    """Raise ``ValueError`` if ``tensor.shape`` does not end with ``tail`` (e.g. ``(4, 4)``)."""
    tail = tuple(tail)
    if tensor.ndim < len(tail) or tuple(tensor.shape[-len(tail) :]) != tail:
        raise ValueError(
            f"argument '{name}' must have shape (..., {', '.join(map(str, tail))}); got {tuple(tensor.shape)}"
        )
    return tensor


def check_unit_vectors(tensor: torch.Tensor, name: str, atol: float = 1e-3) -> torch.Tensor:
    """Raise ``ValueError`` if vectors on the last axis (size 3) are not unit length within ``atol``."""
    check_last_dim(tensor, name, 3)
    if _TRUSTED.get():
        return tensor
    norm = torch.linalg.vector_norm(tensor.detach(), dim=-1)
    if bool(((norm - 1.0).abs() > atol).any()):
        raise ValueError(
            f"argument '{name}' must hold unit vectors; norms range "
            f"{float(norm.min()):.4g}..{float(norm.max()):.4g}"
        )
    return tensor


def broadcast_shape(*shapes: tuple[int, ...]) -> torch.Size:
    """The broadcast of ``shapes`` (``torch.broadcast_shapes``'s result, by numpy's rules, which are
    torch's). ValueError where they do not broadcast.

    ``torch.broadcast_shapes`` imports torch's symbolic-shape machinery (sympy) on its first call, about
    0.6 s in every process (measured); numpy's function is a plain computation.
    """
    return torch.Size(np.broadcast_shapes(*(tuple(shape) for shape in shapes)))


def broadcast_named(*named: tuple[str, torch.Tensor]) -> list[torch.Tensor]:
    """Broadcast tensors to one shape; on failure name the arguments and their shapes.

    Example: ``a, b = broadcast_named(("cos_theta_i", c), ("eta", e))``.
    """
    try:
        shape = broadcast_shape(*(t.shape for _, t in named))
    except ValueError as exc:
        desc = ", ".join(f"'{n}' {tuple(t.shape)}" for n, t in named)
        raise ValueError(f"arguments have shapes that do not broadcast: {desc}") from exc
    return [t.expand(shape) for _, t in named]


def _to_kind(value: Any, kind: str) -> Any:
    if isinstance(value, torch.Tensor):
        if kind == "torch":
            return value
        array = value.detach().cpu().numpy()
        if kind == "float" and array.ndim == 0:
            return float(array)
        return array
    if isinstance(value, tuple):
        converted = [_to_kind(v, kind) for v in value]
        return type(value)(*converted) if hasattr(value, "_fields") else tuple(converted)
    if isinstance(value, list):
        return [_to_kind(v, kind) for v in value]
    if isinstance(value, dict):
        return {k: _to_kind(v, kind) for k, v in value.items()}
    return value


def array_api(*array_args: str) -> Callable[[F], F]:
    """Decorator: accept torch / numpy / float for the named arguments, return the same kind.

    The named arguments are converted with :func:`as_float_tensor` (finite check included) to a
    common floating dtype and device. If any of them was a torch tensor, outputs are returned as
    tensors; else if any was a numpy array, as numpy arrays; else (all Python numbers) 0-d results
    come back as Python floats. Outputs may be tensors or tuples/lists/dicts of tensors.

    Arguments that are ``None`` are passed through untouched.
    """

    def decorator(func: F) -> F:
        import inspect

        signature = inspect.signature(func)
        missing = [a for a in array_args if a not in signature.parameters]
        if missing:  # pragma: no cover - programming error
            raise TypeError(f"{func.__name__}: array_api names unknown arguments {missing}")

        @functools.wraps(func)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            bound = signature.bind(*args, **kwargs)
            present = [(n, bound.arguments[n]) for n in array_args if bound.arguments.get(n) is not None]
            values = [v for _, v in present]
            if any(isinstance(v, torch.Tensor) for v in values):
                kind = "torch"
                device = next(v.device for v in values if isinstance(v, torch.Tensor))
            else:
                kind = "numpy" if any(isinstance(v, np.ndarray | list | tuple) for v in values) else "float"
                device = None
            dtype = _result_dtype(values)
            for name, value in present:
                bound.arguments[name] = as_float_tensor(value, name, dtype=dtype, device=device)
            result = func(*bound.args, **bound.kwargs)
            return _to_kind(result, kind)

        return wrapper  # type: ignore[return-value]

    return decorator
