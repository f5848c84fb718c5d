"""Per-frame work the simulator skips gives the same frame as computing everything (bit for bit)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from polarface.geometry.raycast import RayCaster
from polarface.geometry.uv_raster import reposition
from polarface.render.subsurface import SubsurfaceModel
from polarface.simulate.ground_truth import chromophore_maps
from polarface.simulate.ground_truth_store import texel_visibility
from polarface.simulate.render import exposure_from, frame_exposure, render_frame, stereo_rgb
from polarface.simulate.scene import SimulationConfig, SimulationScene
from polarface.simulate.sequences import sequence_frame
from polarface.skin.layers import subsurface_albedo


@pytest.fixture(scope="module")
def scene():
    return SimulationScene.build(SimulationConfig(preset="tiny"))


def test_dynamic_frame_equals_every_texel_recomputed(scene):
    for index in (1, 0):  # the cached rest rho_sss_bar is made by the first frame asked for
        _, _, _, maps, subsurface = sequence_frame(scene, "dynamic", index)
        mask = maps.mask
        r_bar = subsurface_albedo(
            *(torch.from_numpy(m[mask].astype(np.float64)) for m in (maps.c_m, maps.beta_m, maps.c_h_in)),
            torch.from_numpy(maps.c_h_out[mask].astype(np.float64)),
            scene.calibration.wavelengths_nm,
        )
        rho = np.zeros_like(scene.maps.rho_sss_bar)
        rho[mask] = scene.calibration.integrate(r_bar).float().numpy()
        assert np.array_equal(maps.rho_sss_bar.view(np.uint8), rho.view(np.uint8))
        full = SubsurfaceModel.build(chromophore_maps(maps), scene.raster, scene.calibration.wavelengths_nm,
                                     shapes=scene.subsurface.shapes)
        for a, b in zip(full.totals, subsurface.totals, strict=True):
            assert torch.equal(a, b)
        assert (maps.c_h_out != scene.maps.c_h_out).any()


def test_texel_visibility_equals_every_ray(scene):
    _, _, mesh, _, _ = sequence_frame(scene, "static", 1)
    caster, raster = RayCaster(mesh), reposition(scene.raster, mesh)
    camera = scene.rig.polarimetric_cameras()[0].pinhole()
    visible, pixel = texel_visibility(caster, raster, camera)
    points = raster.position[raster.mask].astype(np.float64)
    rays = points - camera.center
    distance = np.linalg.norm(rays, axis=1)
    directions = rays / distance[:, None]
    hits = caster.first_hits(np.repeat(camera.center[None], len(points), axis=0), directions)
    projected, depth = camera.project(points)
    inside = (depth > 0) & (projected >= -0.5).all(1) & (projected[:, 0] <= camera.width - 0.5) & (
        projected[:, 1] <= camera.height - 0.5)
    facing = np.einsum("nc,nc->n", raster.normal[raster.mask], -directions) > 0.0
    expected = facing & inside & hits.hit & (np.abs(hits.distance - distance) < 0.5)
    assert np.array_equal(visible[raster.mask], expected)
    assert 0 < expected.sum() < expected.size
    assert np.array_equal(pixel[raster.mask], projected.astype(np.float32))


def test_units_read_the_submitting_process_scene_instead_of_building_it(scene, tmp_path, monkeypatch):
    """``scene_for`` reads the scene the submitting process pickled (``write_scene_file``) for its config,
    and builds its own for another configuration or without a file."""
    import dataclasses

    from polarface.simulate import frames

    exposed = dataclasses.replace(scene, exposures={"pol_upper": 2.0})
    path = frames.write_scene_file(tmp_path / ".scene.pkl", exposed)
    built = []
    fake_build = classmethod(lambda cls, config: built.append(config) or "built")
    monkeypatch.setattr(SimulationScene, "build", fake_build)
    monkeypatch.setattr(frames, "_SCENES", {})
    read = frames.scene_for(scene.config, path)
    assert built == [] and read.config == scene.config and read.exposures is None  # as built, no exposures
    assert np.array_equal(read.maps.rho_sss_bar, scene.maps.rho_sss_bar)
    assert torch.equal(read.subsurface.totals[0], scene.subsurface.totals[0])
    other = dataclasses.replace(scene.config, seed=1)
    monkeypatch.setattr(frames, "_SCENES", {})
    assert frames.scene_for(other, path) == "built" and built == [other]
    monkeypatch.setattr(frames, "_SCENES", {})
    assert frames.scene_for(scene.config, tmp_path / "missing.pkl") == "built"


def test_exposure_from_the_views_it_reads_equals_the_full_frame(scene):
    """The submitting process fixes the exposures from frame 0's first polarimetric view and its stereo
    views alone: the same pixels, hence the same exposures, as the frame's full render of every camera.
    The polarimetric cameras share one exposure; each stereo camera's puts its own brightest colour
    channel's 99.5th percentile at the fill level (not the polarimetric camera's, which saturated them)."""
    _, _, mesh, maps, subsurface = sequence_frame(scene, "static", 0)
    full = render_frame(scene, mesh, maps, subsurface)
    first = scene.rig.polarimetric_cameras()[0].id
    one = render_frame(scene, mesh, maps, subsurface, cameras=(first,))
    assert list(one.views) == [first] and len(full.views) == len(scene.rig.cameras)
    for name, image in full.views[first].images.items():
        np.testing.assert_array_equal(one.views[first].images[name], image)
    exposures = exposure_from(full, scene)
    assert frame_exposure(scene, "static", 0) == exposures
    assert set(exposures) == {camera.id for camera in scene.rig.cameras}
    polarimetric = [exposures[camera.id] for camera in scene.rig.polarimetric_cameras()]
    assert len(set(polarimetric)) == 1
    fill = scene.config.exposure_fill
    for camera in scene.rig.cameras:
        if camera.role == "polarimetric":
            continue
        view = full.views[camera.id]
        brightest = stereo_rgb(view.images["s0"], scene.rig)[view.mask].max(axis=-1)
        assert np.percentile(brightest, 99.5) * exposures[camera.id] == pytest.approx(fill, rel=1e-6)
        # the unpolarized stereo image is about twice the co-polarized one: its exposure is lower
        assert exposures[camera.id] < 0.75 * polarimetric[0]
