"""The Mitsuba 3 export: the scene loads in Mitsuba with every file it names, and Mitsuba's render of it
matches polarface's render of the same view (docs/export.md, section "Mitsuba 3")."""

from __future__ import annotations

import xml.etree.ElementTree as ElementTree

import numpy as np
import pytest

from polarface.export import ExportOptions, ExportSource
from polarface.export.mitsuba import write_mitsuba_scene

mi = pytest.importorskip("mitsuba")

#: Mitsuba samples per pixel of the round trip (tiny film, 256 x 212).
ROUND_TRIP_SPP = 16


@pytest.fixture(scope="module")
def exported(tiny_export, tmp_path_factory):
    """``(source, scene folder, record)`` of the tiny RESULT's Mitsuba export."""
    _, result = tiny_export
    source = ExportSource.open(result)
    out = tmp_path_factory.mktemp("mitsuba")
    record = write_mitsuba_scene(source, out, ExportOptions(formats=("mitsuba",)))
    return source, out, record


def test_scene_loads_with_every_referenced_file(exported):
    source, out, record = exported
    assert all((out / name).is_file() for name in record["files"])
    root = ElementTree.parse(out / "scene.xml").getroot()
    assert root.get("version") == "3.0.0"
    referenced = {e.get("value") for e in root.iter("string") if e.get("name") == "filename"}
    assert referenced == {
        "meshes/face.ply",
        "textures/normal.exr",
        "textures/rho_s.exr",
        "textures/rho_sss_bar.exr",
    }
    assert all((out / name).is_file() for name in referenced)
    mi.set_variant("scalar_spectral_polarized")
    scene = mi.load_file(str(out / "scene.xml"), spp=1)
    rig = source.rig
    sensors = scene.sensors()
    assert len(sensors) == len(rig.cameras)
    assert sensors[0].id() == rig.polarimetric_cameras()[0].id
    first = rig.polarimetric_cameras()[0]
    assert tuple(sensors[0].film().size()) == (first.width, first.height)
    assert len(scene.emitters()) == len(rig.lights)
    assert "face" in {shape.id() for shape in scene.shapes()}
    assert any("rho_ss" in note for note in record["lost"])
    assert {"eta", "alpha_s"} <= set(record["constants"])


def test_rejects_a_rig_without_two_polarimetric_cameras(exported, tmp_path):
    source, _, _ = exported
    data = source.rig.model_dump(mode="json")
    data["cameras"] = [c for c in data["cameras"] if c["id"] != "pol_lower"]
    data["stereo_pairs"] = data.get("stereo_pairs", [])
    crippled = ExportSource(source.folder)
    crippled.__dict__["rig"] = type(source.rig).model_validate(data)  # the cached rig, replaced
    with pytest.raises(ValueError, match=r"rig\.json.*two polarimetric cameras"):
        write_mitsuba_scene(crippled, tmp_path, ExportOptions(formats=("mitsuba",)))


def test_rejects_an_unpolarized_variant(exported):
    from polarface.export.mitsuba_check import render_mitsuba_parts

    _, out, _ = exported
    with pytest.raises(ValueError, match=r"argument 'variant'.*not a polarized"):
        render_mitsuba_parts(out / "scene.xml", spp=1, variant="scalar_rgb")


def test_mitsuba_render_matches_polarface(exported):
    """Mitsuba vs polarface at the first polarimetric camera, I_sss and I_s separately.

    Against the exported parameters with polarface's local subsurface term (the model pplastic
    evaluates), what remains is Monte Carlo noise at 16 spp (one of 8 LEDs chosen per sample, 4
    wavelengths, box-filtered pixel footprint: ~10 % per pixel), spectral upsampling of the RGB albedo
    (~1-3 % per colour) and polarface's per-texel entering flux: relative RMSE <= 0.2, face means
    within 5 %. Against the full RESULT render, I_sss adds the diffusion blur (<= 0.25) and I_s the
    single-scattering lobe and per-texel eta/alpha_s that the export replaces by medians (<= 0.8).
    """
    from polarface.export.mitsuba_check import compare_mitsuba_scene

    source, out, _ = exported
    comparison = compare_mitsuba_scene(source, out, spp=ROUND_TRIP_SPP)
    metrics = comparison.metrics
    face = comparison.face
    assert face.sum() > 2000
    for part in ("sss", "s"):
        assert metrics[f"exported.{part}.S0"] < 0.2, metrics
        assert metrics[f"exported.{part}.S1"] < 0.35, metrics
        mitsuba_mean = comparison.mitsuba[part][face][..., 0].mean(0)
        polarface_mean = comparison.polarface["exported"][part][face][..., 0].mean(0)
        np.testing.assert_allclose(mitsuba_mean, polarface_mean, rtol=0.05)
    assert metrics["full.sss.S0"] < 0.25, metrics
    assert metrics["full.s.S0"] < 0.8, metrics
    # The LED polarizers: the specular reflection stays co-polarized (S1 = S0 in the camera frame).
    specular = comparison.mitsuba["s"][face]
    assert specular[..., 1].sum() > 0.97 * specular[..., 0].sum()
    assert abs(specular[..., 2].sum()) < 0.02 * specular[..., 0].sum()
