"""Tests of polarface.render.colour: CIE L*a*b* reference values, the sRGB curve, half-band RGB."""

from __future__ import annotations

import numpy as np
import pytest

from polarface.capture.rig import paper_rig
from polarface.render.colour import encode_srgb, linear_rgb_from_channels, linear_srgb_to_lab


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
