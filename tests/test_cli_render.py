"""Tests of ``polarface render``: outputs, Stokes consistency, and the direction of chromophore edits."""

from __future__ import annotations

import json

import numpy as np
import pytest

from disk_fixtures import write_plane_result
from polarface.cli import main
from polarface.io import read_exr

RESOLUTION = 32


@pytest.mark.slow
def test_render_writes_everything(tmp_path, capsys):
    result = write_plane_result(tmp_path / "result", resolution=RESOLUTION)
    out = tmp_path / "render"
    assert main(["render", str(result), "--out", str(out), "--polarizer-deg", "90"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["pixels"] > 100
    for name in (
        "polarizer.exr",
        "stokes.exr",
        "dop.exr",
        "aolp.exr",
        "mueller.exr",
        "srgb.png",
        "strip.exr",
    ):
        assert (out / name).is_file(), name
    for name in ("mueller.png", "strip.png", "strip_profile.png", "dop.png", "aolp.png"):
        assert (out / "previews" / name).is_file(), name
    stokes = read_exr(out / "stokes.exr")
    polarizer = read_exr(out / "polarizer.exr")
    name = "green_upper"
    expected = 0.5 * (stokes[f"s0_{name}"] - stokes[f"s1_{name}"])  # analyzer at 90 deg
    assert np.allclose(polarizer[name], expected, atol=1e-6 * max(1.0, float(expected.max())))
    dop = read_exr(out / "dop.exr")[name]
    assert np.isfinite(dop).all() and dop.min() >= 0 and dop.max() <= 1.0
    aolp = read_exr(out / "aolp.exr")[name]
    assert aolp.min() >= 0 and aolp.max() < np.pi
    mueller = read_exr(out / "mueller.exr")
    lit = stokes[f"s0_{name}"] > 0.05 * stokes[f"s0_{name}"].max()
    # The rig's state [1, 1, 0] through the Mueller images reproduces the rendered Stokes vector.
    for i, s in enumerate("012"):
        predicted = mueller[f"m{i}0_{name}"] + mueller[f"m{i}1_{name}"]
        rendered = stokes[f"s{s}_{name}"]
        scale = float(np.abs(stokes[f"s0_{name}"][lit]).max())
        assert np.abs(predicted - rendered)[lit].max() < 0.02 * scale
    strip = read_exr(out / "strip.exr")[name]
    assert strip.max() > 0 and (strip == 0).sum() > 0  # light only near the stripe


@pytest.mark.slow
@pytest.mark.parametrize(("edit", "channel", "sign"), [("C_h_out=2x", 1, +1), ("C_m=4x", 0, -1)])
def test_edit_direction(tmp_path, capsys, edit, channel, sign):
    """More outer haemoglobin: redder (a* up); more melanin: darker (L* down)."""
    result = write_plane_result(tmp_path / "result", resolution=RESOLUTION)
    out = tmp_path / "render"
    args = ["render", str(result), "--out", str(out), "--edit", edit, "--no-mueller", "--no-strip"]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out)
    change = summary["lab_edited"][channel] - summary["lab_unedited"][channel]
    assert sign * change > 0.5, summary
    assert (out / "srgb_unedited.png").is_file()


def test_render_bad_input(tmp_path, capsys):
    assert main(["render", str(tmp_path / "missing")]) == 2
    result = write_plane_result(tmp_path / "result", resolution=RESOLUTION)
    assert main(["render", str(result), "--edit", "eta=2x"]) == 2
    assert "unknown parameter" in capsys.readouterr().err
    rig = json.loads((result / "rig.json").read_text())
    rig["spectral"] = None
    (result / "rig.json").write_text(json.dumps(rig))
    assert main(["render", str(result)]) == 2
    assert "spectral calibration" in capsys.readouterr().err
