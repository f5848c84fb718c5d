"""``polarface biophysical``'s numeric options, refused as the user typed them (issue 47).

The held-out bad-input campaign against 13019e4 saw ``biophysical RESULT --coarse-factor 100000`` end in
an IndexError traceback (a median over no coarse texel): the factor's upper bound depends on the texture.
"""

from __future__ import annotations

import numpy as np
import pytest

from command_fixtures import RESOLUTION, error_lines, files
from polarface.cli import main
from polarface.io import write_png
from polarface.pipeline.biophysical import check_coarse_factor, largest_coarse_factor


def _small_mask(result) -> np.ndarray:
    """A 4 x 4 texel patch of the 16 x 16 texture: a sixteenth of it, as a face's mask is a part."""
    mask = np.zeros((RESOLUTION, RESOLUTION), bool)
    mask[5:9, 5:9] = True
    write_png(result / "maps" / "mask.png", mask.astype(np.uint8) * 255)
    return mask


def test_largest_coarse_factor_keeps_a_coarse_texel(plane_result):
    mask = _small_mask(plane_result)
    largest = largest_coarse_factor(mask)
    assert 4 <= largest < RESOLUTION  # a coarse cell larger than 8 texels is covered less than a quarter
    check_coarse_factor(largest, mask)
    with pytest.raises(ValueError, match=rf"argument '--coarse-factor' must lie in \[1, {largest}\] for this "
                                         rf"RESULT's 16 x 16 texture .* got {largest + 1}"):
        check_coarse_factor(largest + 1, mask)
    assert largest_coarse_factor(np.ones((16, 16), bool)) == 16


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--coarse-factor", "100000"], "argument '--coarse-factor' must lie in [1, "),
        (["--coarse-factor", "0"], "argument '--coarse-factor' must be >= 1"),
        (["--shape-rounds", "0"], "argument '--shape-rounds' must lie in [1, 20]"),
        (["--shape-rounds", "100000"], "argument '--shape-rounds' must lie in [1, 20]"),
        (["--gamut-tolerance", "nan"], "argument '--gamut-tolerance' must be > 0"),
        (["--gamut-tolerance", "-1"], "argument '--gamut-tolerance' must be > 0"),
        (["--threads", "0"], "argument '--threads' must lie in [1, "),
        (["--threads", "100000"], "argument '--threads' must lie in [1, "),
    ],
)
def test_bad_numeric_options_are_one_line_naming_them(plane_result, capsys, argv, needle):
    _small_mask(plane_result)
    before = files(plane_result)
    assert main(["biophysical", str(plane_result), "--no-progress", *argv]) == 2
    lines = error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and lines[0].startswith("polarface biophysical: error: "), lines
    assert needle in lines[0], lines[0]
    assert files(plane_result) == before
