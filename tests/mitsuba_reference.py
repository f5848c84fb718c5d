"""polarface's own renders of a Mitsuba capture's frames, to validate the Mitsuba path
(docs/mitsuba_captures.md, "Validation") and to render the control captures
(``MitsubaCaptureConfig(renderer="polarface")`` in :mod:`mitsuba_capture`)."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from mitsuba_capture import ANALYZER_ANGLES, MitsubaCaptureConfig, MitsubaScene, render_frame_views
from polarface.geometry.uv_raster import reposition
from polarface.render.renderer import shading_normals

__all__ = ["compare_views", "polarface_reference_views", "validate_against_polarface"]


def polarface_reference_views(scene: MitsubaScene, pose: np.ndarray) -> dict[str, dict[str, dict]]:
    """polarface's own noise-free renders of the same frame, for validating the Mitsuba path.

    Returns ``{"texture": views, "local": views}``, each ``camera id -> {"i0".."i135": (H, W, 3),
    "mask": (H, W)}``:

    * ``texture``: the simulator's ``--no-blur`` path (:func:`polarface.render.renderer.render_view`:
      the entering flux is computed per texel, ``E = rho_sss_bar Phi`` is read bilinearly at each
      pixel's UV);
    * ``local``: the same image formation evaluated at each pixel's own hit point
      (:func:`polarface.optics.render_polarimetric` per LED times its shadow ray), which is what the
      Mitsuba path computes.
    """
    from polarface.geometry.raycast import RayCaster
    from polarface.optics import render_polarimetric
    from polarface.render.fragments import cast_fragments
    from polarface.render.renderer import render_view, rig_lighting
    from polarface.render.shading import FrameTextures, fragment_material
    from polarface.render.subsurface import entering_flux

    mesh_world = scene.mesh.transformed(pose)
    caster = RayCaster(mesh_world)
    posed = reposition(scene.raster, mesh_world)
    normal_map = shading_normals(posed, scene.maps["displacement_mm"])
    lights, unit_intensity = rig_lighting(scene.rig)
    cameras = scene.rig.polarimetric_cameras()
    flux = entering_flux(
        caster, posed, normal_map, scene.maps["eta"], lights, unit_intensity, cameras[0].pinhole().up_vector
    )
    parameters = {k: scene.maps[k] for k in ("eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss")}
    textured = FrameTextures.build(
        parameters, normal_map, scene.maps["rho_sss_bar"] * flux[..., None], scene.mask
    )
    albedo = FrameTextures.build(parameters, normal_map, scene.maps["rho_sss_bar"], scene.mask)
    out: dict[str, dict] = {"texture": {}, "local": {}}
    for camera in cameras:
        pinhole = camera.pinhole()
        channels = tuple(camera.colour_channels[c] for c in ("R", "G", "B"))
        view = render_view(caster, mesh_world, pinhole, textured, lights, unit_intensity, channels)
        out["texture"][camera.id] = {**view.images, "mask": view.mask}
        origins, directions = pinhole.pixel_rays()
        fragments = cast_fragments(caster, mesh_world, origins.reshape(-1, 3), directions.reshape(-1, 3))
        position = torch.from_numpy(fragments.position)
        centre = torch.from_numpy(pinhole.center)
        material = fragment_material(
            albedo,
            torch.from_numpy(fragments.uv),
            torch.from_numpy(fragments.geometric_normal),
            position,
            centre,
            channels,
        )
        visible = caster.shadow_rays(fragments.position, fragments.geometric_normal, lights)
        images = {name: np.zeros((pinhole.height * pinhole.width, 3), np.float32) for name in ANALYZER_ANGLES}
        for k in range(len(lights)):
            rendered = render_polarimetric(
                material.normal,
                position,
                centre,
                torch.from_numpy(pinhole.up_vector),
                lights[k : k + 1],
                torch.from_numpy(unit_intensity[k : k + 1, None].copy()),
                material.eta,
                material.alpha_s,
                material.alpha_ss,
                material.rho_s,
                material.rho_ss,
                material.exitance,
            )
            lit = visible[:, k : k + 1]
            for name in ANALYZER_ANGLES:
                images[name][fragments.pixel] += lit * getattr(rendered, name).numpy()
        mask = np.zeros(pinhole.height * pinhole.width, bool)
        mask[fragments.pixel] = True
        shape = (pinhole.height, pinhole.width)
        out["local"][camera.id] = {
            **{k: v.reshape(*shape, 3) for k, v in images.items()},
            "mask": mask.reshape(shape),
        }
    return out


def compare_views(mitsuba_views: dict, reference_views: dict) -> dict[str, float]:
    """Relative differences of Mitsuba's analyzer images to a reference, over the pixels both hit.

    Returns:
        ``relative_l2``: ``||a - b|| / ||b||`` over all four analyzer images and cameras;
        ``median_relative``: median of ``|a - b| / max(|b|, 1e-3 p99(b))``;
        ``fraction_above_1e-3``: fraction of pixel-channel values whose relative difference exceeds 1e-3;
        ``mask_mismatch``: pixels hit in one render only.
    """
    differences, norms, relative, mismatch = [], [], [], 0
    for camera_id, ours in mitsuba_views.items():
        reference = reference_views[camera_id]
        both = ours["mask"] & reference["mask"]
        mismatch += int((ours["mask"] ^ reference["mask"]).sum())
        floor = 1e-3 * float(np.percentile(reference["i0"][both], 99))
        for name in ANALYZER_ANGLES:
            a, b = ours[name][both].astype(np.float64), reference[name][both].astype(np.float64)
            differences.append(a - b)
            norms.append(b)
            relative.append(np.abs(a - b) / np.maximum(np.abs(b), floor))
    relative_all = np.concatenate([r.ravel() for r in relative])
    return {
        "relative_l2": float(
            np.sqrt(sum((d**2).sum() for d in differences) / sum((b**2).sum() for b in norms))
        ),
        "median_relative": float(np.median(relative_all)),
        "fraction_above_1e-3": float((relative_all > 1e-3).mean()),
        "mask_mismatch": mismatch,
    }


def validate_against_polarface(config: MitsubaCaptureConfig, frame: int = 0) -> dict:
    """Frame ``frame``'s noise-free Mitsuba images against polarface's two reference renders
    (:func:`polarface_reference_views`, :func:`compare_views`); also returns the render time."""
    scene = MitsubaScene.build(config)
    with tempfile.TemporaryDirectory() as folder:
        started = time.perf_counter()
        views = render_frame_views(scene, scene.poses[frame], Path(folder) / "mesh.ply")
        render_s = time.perf_counter() - started
    references = polarface_reference_views(scene, scene.poses[frame])
    return {
        "render_s": render_s,
        "local": compare_views(views, references["local"]),
        "texture": compare_views(views, references["texture"]),
    }
