"""Tests of ``polarface render``: outputs, Stokes consistency, and the direction of chromophore edits."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from polarface.capture.rig import paper_rig
from polarface.cli import main
from polarface.geometry.mesh import TriangleMesh, save_obj
from polarface.io import read_exr, write_exr, write_png

RESOLUTION = 32


def _plane_result(root: Path) -> Path:
    """A RESULT of a 60 mm skin plane facing the polarimetric module (maps without sog.json)."""
    cells = 8
    u = np.linspace(0.0, 1.0, cells + 1)
    uu, vv = np.meshgrid(u, u, indexing="xy")
    vertices = np.stack([(uu - 0.5) * 60.0, (vv - 0.5) * 60.0, np.full_like(uu, 90.0)], -1).reshape(-1, 3)
    faces = []
    for row in range(cells):
        for col in range(cells):
            a = row * (cells + 1) + col
            faces += [(a, a + 1, a + cells + 2), (a, a + cells + 2, a + cells + 1)]
    mesh = TriangleMesh.from_arrays(vertices, np.array(faces), np.stack([uu, vv], -1).reshape(-1, 2))
    values = {
        "eta": 1.42,
        "alpha_s": 0.5,
        "alpha_ss": 0.95,
        "rho_s": 0.5,
        "rho_ss": 0.25,
        "displacement_mm": 0.0,
        "c_m": 0.05,
        "beta_m": 0.1,
        "c_h_in": 0.03,
        "c_h_out": 0.05,
    }
    for name, value in values.items():
        write_exr(root / "maps" / f"{name}.exr", {"Y": np.full((RESOLUTION, RESOLUTION), value, np.float32)})
    write_png(root / "maps" / "mask.png", np.full((RESOLUTION, RESOLUTION), 255, np.uint8))
    save_obj(root / "mesh.obj", mesh)
    paper_rig(width=96, height=80).save(root / "rig.json")
    return root


@pytest.mark.slow
def test_render_writes_everything(tmp_path, capsys):
    result = _plane_result(tmp_path / "result")
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
    result = _plane_result(tmp_path / "result")
    out = tmp_path / "render"
    args = ["render", str(result), "--out", str(out), "--edit", edit, "--no-mueller", "--no-strip"]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out)
    change = summary["lab_edited"][channel] - summary["lab_unedited"][channel]
    assert sign * change > 0.5, summary
    assert (out / "srgb_unedited.png").is_file()


def test_render_bad_input(tmp_path, capsys):
    assert main(["render", str(tmp_path / "missing")]) == 2
    result = _plane_result(tmp_path / "result")
    assert main(["render", str(result), "--edit", "eta=2x"]) == 2
    assert "unknown parameter" in capsys.readouterr().err
    rig = json.loads((result / "rig.json").read_text())
    rig["spectral"] = None
    (result / "rig.json").write_text(json.dumps(rig))
    assert main(["render", str(result)]) == 2
    assert "spectral calibration" in capsys.readouterr().err
