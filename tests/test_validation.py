"""Tests of the shared argument checks and the array-kind round trip."""

import numpy as np
import pytest
import torch

from polarface._validation import (
    array_api,
    as_float_tensor,
    broadcast_named,
    broadcast_shape,
    check_last_dim,
    check_range,
    check_unit_vectors,
)


@array_api("x", "y")
def _add(x, y):
    return x + y, {"prod": x * y}


def test_kind_round_trip():
    out, extra = _add(1.0, 2.0)
    assert isinstance(out, float) and out == 3.0
    out, extra = _add(np.array([1.0, 2.0], dtype=np.float32), 2.0)
    assert isinstance(out, np.ndarray) and out.dtype == np.float32
    out, extra = _add(torch.ones(3, dtype=torch.float64), np.ones(3))
    assert isinstance(out, torch.Tensor) and out.dtype == torch.float64
    assert isinstance(extra["prod"], torch.Tensor)


def test_nonfinite_named():
    with pytest.raises(ValueError, match="'y'"):
        _add(1.0, float("nan"))
    with pytest.raises(ValueError, match="'x'"):
        as_float_tensor(np.array([np.inf]), "x")
    with pytest.raises(ValueError, match="'x'"):
        as_float_tensor(["a"], "x")


def test_range_shape_checks():
    with pytest.raises(ValueError, match="'eta' must be > 1"):
        check_range(torch.tensor([1.0]), "eta", 1.0, low_inclusive=False)
    with pytest.raises(ValueError, match="'n'"):
        check_last_dim(torch.zeros(2, 4), "n", 3)
    with pytest.raises(ValueError, match="unit vectors"):
        check_unit_vectors(torch.ones(2, 3), "n")
    with pytest.raises(ValueError, match="'a' \\(2,\\), 'b' \\(3,\\)"):
        broadcast_named(("a", torch.zeros(2)), ("b", torch.zeros(3)))


@pytest.mark.parametrize(
    "shapes",
    [((4, 1), (1, 3)), ((), (2, 3)), ((5, 1, 3), (4, 1), (3,)), ((0, 3), (1, 3)), ((2,),), ()],
)
def test_broadcast_shape_is_torchs(shapes):
    shape = broadcast_shape(*shapes)
    assert isinstance(shape, torch.Size) and shape == torch.broadcast_shapes(*shapes)


def test_broadcast_shape_refuses_mismatch():
    with pytest.raises(RuntimeError):
        torch.broadcast_shapes((2,), (3,))
    with pytest.raises(ValueError):
        broadcast_shape((2,), (3,))
