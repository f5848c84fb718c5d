"""`polarface demo`: files exist, values finite, the cross-polarized image carries no specular."""

import html.parser
import json
import os
import subprocess
import sys
import urllib.parse
from pathlib import Path

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


def _polarface(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """The ``polarface`` entry point of this environment run as a user types it, in ``cwd``."""
    command = Path(sys.executable).with_name("polarface")
    return subprocess.run([str(command), *args], cwd=cwd, capture_output=True, text=True, check=False)


class _Links(html.parser.HTMLParser):
    """The ``href`` and ``src`` attributes of a page."""

    def __init__(self) -> None:
        super().__init__()
        self.targets: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.targets += [value for name, value in attrs if name in ("href", "src") and value]


def _broken_links(page: Path) -> list[str]:
    """The page's links to local files that do not exist (URLs, anchors and data URIs are not files)."""
    parser = _Links()
    parser.feed(page.read_text(encoding="utf-8"))
    local = [t for t in parser.targets if not t.startswith(("http:", "https:", "mailto:", "data:", "#"))]
    files = {t: urllib.parse.unquote(t.split("#")[0].split("?")[0]) for t in local}
    return [t for t, name in files.items() if not (page.parent / name).exists()]


def _check_demo_folder(out: Path) -> dict:
    """The landing page, the report, the metrics and the exports of a finished demo folder, every link of
    the two pages resolving; returns the metrics."""
    page = (out / "index.html").read_text(encoding="utf-8")
    assert "result/report.html" in page and "result/exports/viewer/index.html" in page
    assert _broken_links(out / "index.html") == [] and _broken_links(out / "result" / "report.html") == []
    exports = json.loads((out / "result" / "exports" / "export.json").read_text(encoding="utf-8"))
    assert {"mitsuba", "gltf", "viewer", "usd", "kernels"} <= set(exports["formats"])
    return json.loads((out / "metrics.json").read_text(encoding="utf-8"))


@pytest.mark.slow
def test_the_readme_main_job_as_a_user_types_it(tmp_path):
    """`polarface demo --preset tiny` as a subprocess in a scratch directory with the default relative
    --out: the landing page, the report, the metrics and the exports, every link resolving; rerun on its
    finished folder it redoes nothing; moved elsewhere, its folders work from another directory through
    relative paths (evaluate, export, render, info, dynamic and reconstruct --resume); and a new run with
    a relative --out into a sub-folder."""
    user = tmp_path / "user"
    user.mkdir()
    run = _polarface(["demo", "--preset", "tiny"], user)
    assert run.returncode == 0, run.stderr[-3000:]
    out = user / "demo_out"
    metrics = _check_demo_folder(out)
    assert {"polarimetric", "rerender", "biophysical"} <= set(metrics)
    # the tiny frames' stereo surface is 1.2 mm (median) and its normals 9 deg from the truth, and eta
    # rides on them: measured 0.079 while the simulated stereo cameras were saturated, 0.106 since each
    # camera is exposed for itself (the demo preset's fit did not change: docs/dynamic.md)
    assert metrics["polarimetric"]["eta"]["median_abs_error"] < 0.13
    assert metrics["biophysical"]["c_m"]["median_abs_error"] < 0.02
    # the tiny frames do not resolve the surface, which is left unrefined, so the fit runs the paper's
    # RMSprop for 150 steps rather than L-BFGS (docs/reconstruct.md, "Optimiser and geometry")
    record = json.loads((out / "result" / "result.json").read_text(encoding="utf-8"))
    assert record["fingerprint"]["optimizer_given"] is False
    polarimetric = record["stages"]["polarimetric"]
    assert (polarimetric["config"]["optimizer"], polarimetric["config"]["iterations"]) == ("rmsprop", 150)
    assert polarimetric["optimizer_choice"].startswith("stereo surface not refined")
    # paths inside the RESULT are recorded relative to it, inputs outside it absolute
    prepare = record["stages"]["prepare"]
    assert (prepare["poses"], prepare["mesh"], prepare["geometry"]) == (
        "geometry/poses.json", "geometry/mesh.obj", "geometry")
    assert prepare["capture"] == (out / "sim" / "static").as_posix()
    # the report, written on a worker after the export, recorded as a stage
    assert record["stages"]["report"]["complete"] and record["stages"]["report"]["timings"]["report_s"] > 0

    # the same command on its finished folder: nothing is redone
    written = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    again = _polarface(["demo", "--preset", "tiny"], user)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "up to date" in again.stdout
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()} == written

    # moved (the old place gone), then used from another directory by relative paths
    moved = tmp_path / "elsewhere" / "runs" / "moved"
    moved.parent.mkdir(parents=True)
    out.rename(moved)
    other = tmp_path / "other"
    other.mkdir()
    rel = os.path.relpath(moved, other)
    for args in (
        ["demo", "--preset", "tiny", "--out", rel],
        ["info", f"{rel}/result"],
        ["info", f"{rel}/sim"],
        ["evaluate", f"{rel}/result", "--gt", f"{rel}/sim", "--out", "metrics.json"],
        ["export", f"{rel}/result", "--format", "mitsuba", "--out", "exports"],
        ["render", f"{rel}/result", "--out", "render"],
        ["dynamic", f"{rel}/result", f"{rel}/sim"],
        ["reconstruct", f"{rel}/sim", "--dynamic", f"{rel}/sim", "--out", f"{rel}/result", "--resume"],
    ):
        run = _polarface(args, other)
        assert run.returncode == 0, (args, run.stderr[-3000:])
    assert json.loads((other / "metrics.json").read_text(encoding="utf-8"))["polarimetric"] == \
        metrics["polarimetric"]
    assert (other / "exports" / "mitsuba").is_dir() and (other / "render").is_dir()

    # a new run with a relative --out into a sub-folder (created), then evaluated from elsewhere
    run = _polarface(["demo", "--preset", "tiny", "--out", "runs/fresh"], other)
    assert run.returncode == 0, run.stderr[-3000:]
    _check_demo_folder(other / "runs" / "fresh")
    run = _polarface(["evaluate", "other/runs/fresh/result", "--gt", "other/runs/fresh/sim", "--groups",
                      "geometry"], tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    fresh_metrics = json.loads((other / "runs" / "fresh" / "metrics.json").read_text(encoding="utf-8"))
    assert json.loads(run.stdout)["geometry"] == fresh_metrics["geometry"]


def test_sphere_demo_never_deletes_user_data(tmp_path, capsys):
    """``mkdir d; echo x > d/notes.txt; polarface demo --sphere --out d`` is refused; nothing renamed."""
    folder = tmp_path / "d"
    folder.mkdir()
    (folder / "notes.txt").write_text("x")
    assert main(["demo", "--sphere", "--size", "16", "--out", str(folder)]) == 2
    err = capsys.readouterr().err
    assert "not written by 'polarface demo --sphere'" in err and "--force" in err
    assert [p.name for p in folder.iterdir()] == ["notes.txt"]
    a_file = tmp_path / "f.txt"
    a_file.write_text("mine")
    assert main(["demo", "--sphere", "--size", "16", "--out", str(a_file)]) == 2
    assert "is a file" in capsys.readouterr().err
    assert a_file.read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d", "f.txt"]  # no hidden .old-* / .tmp-*


def test_sphere_demo_reruns_in_its_own_folder_and_force_replaces(tmp_path):
    out = tmp_path / "sphere"
    assert main(["demo", "--sphere", "--size", "16", "--out", str(out)]) == 0
    (out / "my_notes.txt").write_text("kept")
    assert main(["demo", "--sphere", "--size", "16", "--out", str(out)]) == 0  # its own folder
    assert (out / "my_notes.txt").read_text() == "kept" and (out / "exr" / "I0.exr").is_file()
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("x")
    assert main(["demo", "--sphere", "--size", "16", "--force", "--out", str(foreign)]) == 0
    assert not (foreign / "notes.txt").exists() and (foreign / "index.html").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["foreign", "sphere"]


def test_sphere_demo_default_folder_is_not_the_pipeline_demo(tmp_path, monkeypatch):
    import polarface.pipeline

    seen = []
    monkeypatch.setattr(polarface.pipeline, "run_sphere_demo", lambda out, *a, **k: seen.append(out) or 0.0)
    monkeypatch.setattr(polarface.pipeline, "run_demo_pipeline", lambda out, *a, **k: seen.append(out))
    monkeypatch.chdir(tmp_path)
    assert main(["demo", "--sphere"]) == 0
    assert main(["demo", "--preset", "tiny"]) == 0
    assert [str(path) for path in seen] == ["demo_sphere", "demo_out"]
