"""Tests of polarface.render.relight helpers: edits, colour conversions, channel mapping."""

from __future__ import annotations

import numpy as np
import pytest

from polarface.capture.rig import paper_rig
from polarface.render.relight import (
    apply_edits,
    encode_srgb,
    linear_rgb_from_channels,
    linear_srgb_to_lab,
    parse_edits,
)


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


def test_apply_edits_scales_and_clips():
    maps = {"c_m": np.full((2, 2), 0.2, np.float32), "c_h_out": np.full((2, 2), 0.1, np.float32)}
    edited = apply_edits(maps, {"c_m": 4.0, "c_h_out": 2.0})
    assert np.allclose(edited["c_m"], 0.5)  # clipped to PARAMETER_RANGES
    assert np.allclose(edited["c_h_out"], 0.2)
    assert np.allclose(maps["c_m"], 0.2)  # input untouched


def test_lab_reference_values():
    lab = linear_srgb_to_lab(np.array([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
    assert np.allclose(lab[0], [100.0, 0.0, 0.0], atol=0.05)
    assert np.allclose(lab[1], [0.0, 0.0, 0.0], atol=1e-6)
    # sRGB red: L* 53.24, a* 80.09, b* 67.20 (CIE 1976 with the sRGB matrix, D65)
    assert np.allclose(lab[2], [53.24, 80.09, 67.20], atol=0.1)


def test_encode_srgb():
    values = encode_srgb(np.array([-1.0, 0.0, 0.0031308, 0.5, 1.0, 2.0]))
    assert np.allclose(values[[0, 1, 4, 5]], [0.0, 0.0, 1.0, 1.0])
    assert values[3] == pytest.approx(0.7354, abs=1e-3)


def test_linear_rgb_from_channels_means_half_bands():
    rig = paper_rig(width=64, height=48)
    six = np.arange(6, dtype=np.float64)[None, :]
    rgb = linear_rgb_from_channels(six, rig)
    upper, lower = rig.polarimetric_cameras()[:2]
    expected = [0.5 * (upper.colour_channels[c] + lower.colour_channels[c]) for c in "RGB"]
    assert np.allclose(rgb[0], expected)
