"""The offline 3D viewer page (docs/export.md, "Viewer"): its data, and the page in headless Chromium.

The page is written for the tiny RESULT (static + 2 dynamic frames) from a glb of its mesh, and loaded
from ``file://`` in Chromium driven over the DevTools pipe (``tests/chromium_pipe.py``): it must reach its
"ready" state with no console error, hold the glb's mesh, offer the map selector and both sliders, draw
a face (not a blank canvas) and, moved to another frame and map, change the picture without errors. Its
polarizer panel's mean ``I(theta)`` must match the renderer's own analyzer images. Skipped with a
reason where no Chromium is installed (a failure under ``CI``, where every oracle must run).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from chromium_pipe import CHROMIUM, ChromiumPipe
from polarface.export import ExportFormat, ExportOptions, ExportSource
from polarface.export.viewer_data import _companded, _vertex_alignment, glb_vertices
from polarface.geometry.mesh import TriangleMesh, load_mesh
from polarface.io import read_png
from polarface.pipeline.export import export_result

#: The stand-in glb's model -> glb transform (mm -> m and a turn), undone by the viewer's alignment.
_TURN = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])


def _standin_glb(mesh: TriangleMesh, image: np.ndarray, path: Path, order: np.ndarray | None = None) -> None:
    """A glb of ``mesh`` (vertices permuted by ``order``, turned, in m) textured with ``image``."""
    import trimesh
    from PIL import Image

    order = np.arange(len(mesh.vertices)) if order is None else order
    inverse = np.argsort(order)
    material = trimesh.visual.material.PBRMaterial(
        baseColorTexture=Image.fromarray(image), metallicFactor=0.0, roughnessFactor=0.6
    )
    shape = trimesh.Trimesh(
        mesh.vertices[order] @ _TURN.T / 1000.0, inverse[mesh.faces],
        vertex_normals=mesh.normals[order] @ _TURN.T,
        visual=trimesh.visual.TextureVisuals(uv=mesh.uv[order], material=material), process=False,
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    shape.export(path, file_type="glb")


def write_standin_gltf(source: ExportSource, out: Path, options: ExportOptions) -> dict:
    """A stand-in for the gltf writer (``face.glb`` of the mesh with the rho_sss_bar preview)."""
    image = read_png(source.folder.preview_path("rho_sss_bar_rgb"))
    image = (image * 255).astype(np.uint8) if image.dtype != np.uint8 else image
    _standin_glb(source.mesh, image[..., :3], out / "face.glb")
    return {"files": ["face.glb"]}


@pytest.fixture(scope="module")
def viewer_export(tiny_export, tmp_path_factory, request) -> Path:
    """``polarface export --format gltf`` of the tiny RESULT (the real gltf writer when it exists)."""
    _, result = tiny_export
    out = tmp_path_factory.mktemp("viewer") / "export"
    monkeypatch = pytest.MonkeyPatch()
    request.addfinalizer(monkeypatch.undo)
    if not _real_gltf():
        load_writer = ExportFormat.load_writer
        monkeypatch.setattr(ExportFormat, "load_writer",
                            lambda self: write_standin_gltf if self.name == "gltf" else load_writer(self))
    export_result(result, out, ExportOptions(formats=("gltf",)))
    return out


# ---- data, no browser ------------------------------------------------------------------------

def _grid_mesh(count: int = 12) -> TriangleMesh:
    """A wavy ``count`` x ``count`` height field (mm) whose UVs are its x, y."""
    u, v = np.meshgrid(np.linspace(0, 1, count), np.linspace(0, 1, count))
    vertices = np.column_stack([100 * u.ravel(), 100 * v.ravel(), 5 * np.sin(6 * u.ravel()) * v.ravel()])
    index = np.arange(count * count).reshape(count, count)
    corners = index[:-1, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, 1:].ravel(), index[1:, :-1].ravel()
    faces = np.concatenate([np.column_stack(corners[:3]), np.column_stack([corners[0], *corners[2:]])])
    return TriangleMesh.from_arrays(vertices, faces, np.column_stack([u.ravel(), v.ravel()]))


def test_alignment_recovers_a_shuffled_turned_glb(tmp_path):
    mesh = _grid_mesh()
    order = np.random.default_rng(1).permutation(len(mesh.vertices))
    _standin_glb(mesh, np.full((8, 8, 3), 128, np.uint8), tmp_path / "face.glb", order)
    glb = (tmp_path / "face.glb").read_bytes()
    positions, _ = glb_vertices(glb)
    found, linear, offset = _vertex_alignment(mesh, glb)
    np.testing.assert_array_equal(found, order)
    np.testing.assert_allclose(linear, _TURN / 1000.0, atol=1e-9)
    np.testing.assert_allclose(mesh.vertices[found] @ linear.T + offset, positions, atol=1e-6)


def test_alignment_refuses_a_glb_of_another_mesh(tmp_path, tiny_export):
    _, result = tiny_export
    mesh = load_mesh(result / "mesh.obj")
    moved = TriangleMesh.from_arrays(mesh.vertices, mesh.faces, np.clip(mesh.uv[::-1], 0, 1))
    _standin_glb(moved, np.full((8, 8, 3), 128, np.uint8), tmp_path / "face.glb")
    with pytest.raises(ValueError, match=r"glb's (UVs|positions)"):
        _vertex_alignment(mesh, (tmp_path / "face.glb").read_bytes())


def test_stokes_companding_decodes_within_a_quantization_step():
    import cv2

    scale = 2.0
    values = np.linspace(-scale, scale, 301)[None, :, None].repeat(3, axis=2)
    png = np.frombuffer(_companded(values, scale, signed=True), np.uint8)
    code = cv2.imdecode(png, cv2.IMREAD_UNCHANGED)[..., ::-1].astype(np.float64)
    t = 2 * code / 255 - 1
    decoded = scale * np.sign(t) * t * t  # the page's decoder (docs/export.md, "Viewer")
    step = scale * 2 * np.abs(values / scale) ** 0.5 / 255 + scale * (2 / 255) ** 2
    assert (np.abs(decoded - values) <= step + 1e-12).all()


def test_export_writes_the_viewer_beside_the_glb(viewer_export, tiny_export):
    _, result = tiny_export
    record = json.loads((viewer_export / "export.json").read_text())["formats"]["viewer"]
    viewer = viewer_export / "viewer"
    assert {"index.html", "viewer_data.js", "three/three.min.js", "three/LICENSE"} <= set(record["files"])
    assert all((viewer / f).is_file() for f in record["files"])
    assert "MIT" in (viewer / "three" / "LICENSE").read_text()
    assert record["frames"] == 2 and record["stokes"] and record["seconds"] > 0
    wanted = {"rho_sss_bar", "eta", "rho_s", "alpha_s", "displacement_mm", "c_h_out", "c_m"}
    assert wanted <= set(record["maps"])
    text = (viewer / "viewer_data.js").read_text()
    payload = json.loads(text[text.index("{"): text.rindex("}") + 1])
    assert 'type="module"' not in (viewer / "index.html").read_text()  # file:// needs classic scripts
    # frame positions in glb order are the tracked frame meshes under the glb's transform
    import base64

    positions, _ = glb_vertices(base64.b64decode(payload["glb"]))
    turn = _TURN / 1000.0 if not _real_gltf() else None
    for entry, index in zip(payload["frames"], (0, 1), strict=True):
        frame_positions = np.frombuffer(base64.b64decode(entry["positions"]), "<f4").reshape(-1, 3)
        assert frame_positions.shape == positions.shape
        if turn is not None:
            tracked = load_mesh(result / "frames" / f"{index:04d}" / "mesh.obj")
            np.testing.assert_allclose(frame_positions, tracked.vertices @ turn.T, atol=1e-6)
        assert set(entry["textures"]) == {"rho_sss_bar", "c_h_out"}


def _real_gltf() -> bool:
    try:
        import polarface.export.gltf  # noqa: F401
    except ImportError:
        return False
    return True


# ---- the page in Chromium --------------------------------------------------------------------

def _need_chromium() -> None:
    if CHROMIUM is None:
        reason = "headless Chromium is not installed (Debian package 'chromium'): viewer page not loaded"
        if os.environ.get("CI"):
            pytest.fail(reason)
        pytest.skip(reason)


_STATUS = "(n => n && n.textContent ? JSON.parse(n.textContent) : null)(document.getElementById('status'))"
_SETTLED = f"(s => s && (s.state === 'ready' || s.errors.length) ? s : null)({_STATUS})"


def _view_pixels(shot: Path) -> np.ndarray:
    """The 3D view's pixels of a screenshot (left of the 360 px control panel), float in [0, 1]."""
    image = read_png(shot)[..., :3].astype(np.float64)
    image = image / 255.0 if image.max() > 1.0 else image
    return image[:, : image.shape[1] - 380]


def test_viewer_page_loads_and_draws_in_chromium(viewer_export, tmp_path):
    _need_chromium()
    page = (viewer_export / "viewer" / "index.html").resolve().as_uri()
    record = json.loads((viewer_export / "export.json").read_text())["formats"]["viewer"]
    text = (viewer_export / "viewer" / "viewer_data.js").read_text()
    payload = json.loads(text[text.index("{"): text.rindex("}") + 1])
    with ChromiumPipe(tmp_path / "profile") as browser:
        browser.navigate(page)
        status = browser.wait_for(_SETTLED)
        assert status["errors"] == [] and status["state"] == "ready", status
        assert status["meshes"] >= 1 and status["vertices"] > 1000
        assert status["frames"] == record["frames"] == 2
        assert status["controls"] == ["map", "frame", "theta"]
        assert set(status["maps"]) == set(record["maps"])
        # the page's I(theta) from the decoded Stokes PNGs vs the renderer's analyzer images
        expected = payload["stokes"]["analyzer_means"]
        for angle in ("0", "45", "90", "135"):
            np.testing.assert_allclose(status["polarizer_means"][angle], expected[angle], rtol=0.01)
        first = _view_pixels(browser.screenshot(tmp_path / "static.png"))
        background = np.array([0x30, 0x34, 0x3A]) / 255.0
        drawn = np.abs(first - background).max(-1) > 0.03
        assert 0.03 < drawn.mean() < 0.9, f"{drawn.mean():.3f} of the 3D view differs from the background"
        assert first[drawn].std() > 0.02  # a textured, shaded face, not a flat silhouette
        # another frame and map, set through the controls as a user would
        for control, value, event in (("map", "c_h_out", "change"), ("frame", "2", "input"),
                                      ("theta", "90", "input")):
            browser.evaluate(f"(n => {{ n.value = '{value}'; n.dispatchEvent(new Event('{event}')); "
                             f"return 1; }})(document.getElementById('{control}'))")
        browser.wait_for("document.getElementById('frame-label').textContent.startsWith('frame 1')")
        browser.wait_for("!document.getElementById('legend').hidden")
        import time

        time.sleep(0.5)  # a few animation frames
        second = _view_pixels(browser.screenshot(tmp_path / "frame.png"))
        assert np.abs(second - first).mean() > 0.005, "moving the controls did not change the 3D view"
        status = browser.evaluate(_STATUS)
        assert status["errors"] == [], status["errors"]
        assert browser.console_errors() == []


def test_viewer_of_a_static_result_without_stokes_loads(viewer_export, tiny_export, tmp_path):
    """No frames and no polarizer render: the sliders are disabled, the page still gets ready."""
    _need_chromium()
    from polarface.export import build_viewer_data
    from polarface.report import write_viewer

    _, result = tiny_export
    data = build_viewer_data(ExportSource.open(result, frames=[]), viewer_export / "gltf" / "face.glb",
                             stokes=False)
    record = write_viewer(tmp_path / "viewer", data)
    assert record["frames"] == 0 and not record["stokes"] and record["notes"]
    with ChromiumPipe(tmp_path / "profile") as browser:
        browser.navigate((tmp_path / "viewer" / "index.html").as_uri())
        status = browser.wait_for(_SETTLED)
        assert status["errors"] == [] and status["state"] == "ready" and status["frames"] == 0, status
        assert browser.evaluate("document.getElementById('frame').disabled && "
                                "document.getElementById('theta').disabled")
        assert browser.console_errors() == []
