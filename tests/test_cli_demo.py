"""`polarface demo`: files exist, values finite, the cross-polarized image carries no specular."""

import json

import numpy as np
import pytest

from polarface.cli import main
from polarface.io import read_exr, read_png
from polarface.render.demo import DemoParameters, render_demo


@pytest.mark.slow
def test_demo_command_writes_everything(tmp_path):
    out = tmp_path / "demo"
    assert main(["demo", "--sphere", "--out", str(out), "--size", "96"]) == 0
    names = ["I0", "I45", "I90", "I135", "I_sss", "I_zeta", "I_s", "DoP", "AoLP"]
    images = {}
    for name in names:
        channels = read_exr(out / "exr" / f"{name}.exr")
        assert sorted(channels) == ["B", "G", "R"]
        images[name] = np.stack([channels[c] for c in "RGB"], -1)
        assert images[name].shape == (96, 96, 3)
        assert np.isfinite(images[name]).all(), name
        png = read_png(out / "png" / f"{name}.png")
        # analyzer images are pixel-exact; the colour-mapped ones are figures with a labelled colour bar
        exact = name in ("I0", "I45", "I90", "I135", "I_sss")
        assert png.shape[:2] == (96, 96) if exact else png.shape[1] > 96
    mask = read_exr(out / "exr" / "mask.exr")["Y"] > 0.5
    assert 0.3 < mask.mean() < 0.9
    np.testing.assert_allclose(images["I_sss"], 2 * images["I90"], rtol=1e-6)
    np.testing.assert_allclose(images["I_s"], images["I0"] - images["I90"], rtol=1e-5, atol=1e-7)
    assert images["DoP"].min() >= 0 and images["AoLP"].max() < np.pi
    # The specular highlight shows in I0 - I90 and not in I90: I90 equals a render without the
    # specular and single-scattering lobes to 0.5 %, while I0 differs from it at the highlight.
    no_specular = render_demo(
        DemoParameters(width=96, height=96, focal_px=1400.0 * 96 / 256), rho_s=0.0, rho_ss=0.0
    ).images
    reference_i90 = no_specular.i90.numpy()
    assert np.abs(images["I90"] - reference_i90).max() <= 0.005 * reference_i90.max()
    highlight = np.unravel_index(np.argmax(images["I_s"][..., 1]), mask.shape)
    assert images["I0"][highlight][1] > 1.05 * no_specular.i0.numpy()[highlight][1]
    html = (out / "index.html").read_text(encoding="utf-8")
    for name in names:
        assert f"png/{name}.png" in html
    assert "cross-polarized" in html
    parameters = json.loads((out / "parameters.json").read_text())
    assert parameters["eta"] == 1.44 and abs(parameters["off_axis_deg"] - 5.71) < 0.01
    assert not list(tmp_path.glob(".tmp-*"))


def test_demo_command_bad_arguments(tmp_path, capsys):
    assert main(["demo", "--sphere", "--out", str(tmp_path / "x"), "--eta", "0.9"]) == 2
    assert "--eta" in capsys.readouterr().err
    assert main(["demo", "--sphere", "--out", str(tmp_path / "x"), "--size", "2"]) == 2
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_demo_pipeline_tiny_end_to_end(tmp_path):
    """The README's main job in miniature: simulate -> reconstruct -> evaluate -> index.html."""
    out = tmp_path / "demo"
    assert main(["demo", "--preset", "tiny", "--out", str(out)]) == 0
    page = (out / "index.html").read_text(encoding="utf-8")
    assert "result/report.html" in page
    assert (out / "result" / "report.html").is_file()
    metrics = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
    assert {"polarimetric", "rerender", "biophysical"} <= set(metrics)
    assert metrics["polarimetric"]["eta"]["median_abs_error"] < 0.1
    assert metrics["biophysical"]["c_m"]["median_abs_error"] < 0.02
