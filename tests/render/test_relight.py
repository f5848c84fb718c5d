"""Tests of polarface.render.relight helpers: chromophore edits."""

from __future__ import annotations

import numpy as np
import pytest

from polarface.render.relight import apply_edits, parse_edits


def test_parse_edits():
    assert parse_edits("C_h_out=2x,C_m=4x") == {"c_h_out": 2.0, "c_m": 4.0}
    assert parse_edits(" beta_m = 0.5 ") == {"beta_m": 0.5}
    assert parse_edits(None) == {} and parse_edits("") == {}
    with pytest.raises(ValueError, match="unknown parameter"):
        parse_edits("eta=2x")
    with pytest.raises(ValueError, match="cannot parse"):
        parse_edits("C_m:2")
    with pytest.raises(ValueError, match="> 0"):
        parse_edits("C_m=0x")
    with pytest.raises(ValueError, match="argument 'edit': c_m is given more than once"):
        parse_edits("C_m=2x,c_m=3x")


def test_apply_edits_scales_and_clips():
    maps = {"c_m": np.full((2, 2), 0.2, np.float32), "c_h_out": np.full((2, 2), 0.1, np.float32)}
    edited = apply_edits(maps, {"c_m": 4.0, "c_h_out": 2.0})
    assert np.allclose(edited["c_m"], 0.5)  # clipped to PARAMETER_RANGES
    assert np.allclose(edited["c_h_out"], 0.2)
    assert np.allclose(maps["c_m"], 0.2)  # input untouched
