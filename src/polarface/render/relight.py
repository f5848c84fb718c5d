"""Render reconstructed appearance maps: polarimetric views, Mueller images, strip light, editing.

Paper Figs. "Mueller", "strip" and "editing". The renderer is :mod:`polarface.render.renderer`
(with :mod:`polarface.render.subsurface`, the simulator's too): Embree ray casting of the
(posed) rest mesh, entry flux per texel under the rig's polarized LEDs, heterogeneous two-layer
texture-space diffusion with the RESULT's SoG shapes (``maps/sog.json``) and chromophore maps, exit
Fresnel with polarization, GGX specular and single-scattering lobes through full Mueller matrices.

* :func:`render_result_view` - analyzer images of all six channels at a camera of the rig.
* :func:`mueller_images` - per-pixel 3x3 linear Mueller matrix of the surface under the rig's LEDs:
  the lobes are evaluated for the incident states ``[1, +-1, 0]`` and ``[1, 0, 1]`` (each LED's own
  frame) and combined column by column; the diffused subsurface term enters the first column only
  (the entry polarization changes the entering flux by ``T-/T+``, a few percent at the rig's
  near-normal incidence: neglected, documented).
* strip light - the entering flux is kept only in a band of ``strip_width_mm`` around a plane through
  the head (structured-light stripe); specular lobes are omitted so the image shows how far light
  travels under the skin.
* :func:`apply_edits` - scale chromophore maps (``C_h_out=2x,C_m=4x``), clipped to the physical ranges.

Frames and units: world mm, OpenCV cameras; images are linear radiance (LED intensity unit per mm^2
per sr), channels-last ``(h, w, C)``. Stokes in the camera frame (``docs/conventions.md``).
"""

from __future__ import annotations

import dataclasses
import re
from typing import Any

import numpy as np
import torch

from polarface.geometry.raycast import RayCaster
from polarface.geometry.uv_raster import UVRaster, rasterize_uv, reposition
from polarface.optics.image_formation import subsurface_exit_stokes
from polarface.render.renderer import render_view, rig_lighting, shading_normals
from polarface.render.shading import FrameTextures, fragment_material, lobe_stokes, module_intensities
from polarface.render.subsurface import SubsurfaceModel, entering_flux, texture_space_exitance
from polarface.results import ResultAppearance
from polarface.skin.layers import CHROMOPHORE_NAMES, PARAMETER_RANGES

__all__ = [
    "ResultScene",
    "apply_edits",
    "mueller_images",
    "parse_edits",
    "render_result_view",
    "result_scene",
]

_EDIT_NAMES = {"c_m": "c_m", "beta_m": "beta_m", "c_h_in": "c_h_in", "c_h_out": "c_h_out"}


def parse_edits(text: str | None) -> dict[str, float]:
    """Parse ``"C_h_out=2x,C_m=4x"`` into ``{"c_h_out": 2.0, "c_m": 4.0}`` (factors > 0; ``x`` optional).

    Raises:
        ValueError: unknown parameter, malformed factor or a parameter given twice (naming it).
    """
    edits: dict[str, float] = {}
    if not text:
        return edits
    for item in text.split(","):
        item = item.strip()
        if not item:
            continue
        match = re.fullmatch(r"([A-Za-z_]+)\s*=\s*([0-9.eE+-]+)\s*[xX]?", item)
        if match is None:
            raise ValueError(f"argument 'edit': cannot parse {item!r}; use NAME=FACTORx, e.g. C_h_out=2x")
        key = match.group(1).lower()
        if key not in _EDIT_NAMES:
            raise ValueError(
                f"argument 'edit': unknown parameter {match.group(1)!r}; choose from C_m, beta_m, "
                "C_h_in, C_h_out"
            )
        try:
            factor = float(match.group(2))
        except ValueError:
            raise ValueError(f"argument 'edit': bad factor in {item!r}") from None
        if not (np.isfinite(factor) and factor > 0):
            raise ValueError(f"argument 'edit': factor of {key} must be finite and > 0; got {factor}")
        if _EDIT_NAMES[key] in edits:
            raise ValueError(f"argument 'edit': {match.group(1)} is given more than once in {text!r}")
        edits[_EDIT_NAMES[key]] = factor
    return edits


def apply_edits(chromophores: dict[str, np.ndarray], edits: dict[str, float]) -> dict[str, np.ndarray]:
    """Chromophore maps scaled by ``edits`` and clipped to ``PARAMETER_RANGES`` (``c_m + c_h_out <= 1``)."""
    out = {k: np.asarray(v, dtype=np.float32).copy() for k, v in chromophores.items()}
    for name, factor in edits.items():
        low, high = PARAMETER_RANGES[name]
        out[name] = np.clip(out[name] * factor, low, high).astype(np.float32)
    return out




@dataclasses.dataclass(frozen=True, eq=False)
class RenderedResult:
    """One rendered view.

    Attributes:
        images: ``i0``, ``i45``, ``i90``, ``i135`` ``(h, w, 6)`` float32 analyzer images (all six channels);
            ``s0`` alone, the total intensity, when rendered with ``polarization=False``.
        mask, uv, face_id, depth: as :class:`polarface.render.renderer.ViewRender`.
        textures: the :class:`polarface.render.shading.FrameTextures` used (for Mueller images).
        mesh_world, caster, camera, lights, intensity: the scene (``intensity``: ``(L,)`` per LED module).
        spectral_albedo: ``(L, Ht, Wt)`` float32 diffused subsurface exitance per unit flux (texture).
    """

    images: dict[str, np.ndarray]
    mask: np.ndarray
    uv: np.ndarray
    face_id: np.ndarray
    depth: np.ndarray
    textures: Any
    mesh_world: Any
    caster: Any
    camera: Any
    lights: np.ndarray
    intensity: np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class ResultScene:
    """A RESULT placed in the rig world under the rig's LEDs, ready to render at any camera
    (:func:`polarface.render.renderer.render_view` with these fields).

    Attributes:
        mesh_world: the RESULT's mesh in the rig world (mm); caster: its Embree scene.
        textures: the frame textures (parameters, shading normals, diffused subsurface exitance);
            ``textures.without_subsurface()`` gives the surface reflection alone.
        lights: ``(L, 3)`` LED positions (mm); intensity: ``(L,)`` their radiant intensities.
    """

    mesh_world: Any
    caster: RayCaster
    textures: FrameTextures
    lights: np.ndarray
    intensity: np.ndarray


def result_scene(
    appearance: ResultAppearance,
    pose: np.ndarray | None = None,
    *,
    edits: dict[str, float] | None = None,
    strip: tuple[np.ndarray, float, float] | None = None,
) -> ResultScene:
    """The RESULT posed by ``pose`` (``(4, 4)`` model -> rig world; default ``appearance.placement``) with
    its subsurface light diffused once, for rendering any number of cameras.

    ``edits``: chromophore scale factors (:func:`parse_edits`); ``strip``: ``(right vector, width mm,
    offset mm)``: light enters only in that band and the specular lobes are off (:func:`render_result_view`).
    """
    transform = appearance.placement if pose is None else np.asarray(pose, dtype=np.float64)
    if transform.shape != (4, 4) or not np.isfinite(transform).all():
        raise ValueError(f"argument 'pose' must be a finite 4x4 matrix; got shape {transform.shape}")
    mesh_world = appearance.mesh.transformed(transform)
    caster = RayCaster(mesh_world)
    raster = reposition(rasterize_uv(appearance.mesh, appearance.mask.shape), mesh_world)
    lights, intensity = rig_lighting(appearance.rig)
    textures = _result_textures(appearance, caster, raster, lights, intensity, edits or {}, strip)
    return ResultScene(mesh_world, caster, textures, lights, intensity)


def render_result_view(
    appearance: ResultAppearance,
    camera_id: str | None = None,
    pose: np.ndarray | None = None,
    *,
    edits: dict[str, float] | None = None,
    strip_width_mm: float | None = None,
    strip_offset_mm: float = 0.0,
    polarization: bool = True,
) -> RenderedResult:
    """Render the RESULT at one camera of its rig.

    Args:
        appearance: :class:`ResultAppearance`.
        camera_id: a camera of the rig (default: the first polarimetric camera).
        pose: ``(4, 4)`` model -> rig-world transform (default: ``appearance.placement``, the head facing
            the polarimetric module: identity for stereo geometry, else the simulator's rest placement).
        edits: chromophore scale factors (:func:`parse_edits`).
        strip_width_mm: if given, light enters only within this band (mm) around the plane through the
            head centre spanned by the camera's up and viewing axes (shifted by ``strip_offset_mm``
            along the camera's right vector); specular lobes are switched off.
        polarization: False renders the total intensity ``s0`` alone (``I0 + I90`` to float rounding):
            only the first row of the Mueller chain is evaluated, as for the rig's RGB cameras.

    Returns:
        :class:`RenderedResult` with six-channel analyzer images (``s0`` alone without
        ``polarization``).
    """
    rig = appearance.rig
    camera = rig.camera(camera_id) if camera_id else rig.polarimetric_cameras()[0]
    pinhole = camera.pinhole()
    if strip_width_mm is not None and not strip_width_mm > 0:
        raise ValueError(f"argument 'strip_width_mm' must be > 0; got {strip_width_mm}")
    strip = None if strip_width_mm is None else (pinhole.right_vector, strip_width_mm, strip_offset_mm)
    scene = result_scene(appearance, pose, edits=edits, strip=strip)
    view = render_view(scene.caster, scene.mesh_world, pinhole, scene.textures, scene.lights, scene.intensity,
                       tuple(range(6)), polarization=polarization)
    return RenderedResult(
        view.images,
        view.mask,
        view.uv,
        view.face_id,
        view.depth,
        scene.textures,
        scene.mesh_world,
        scene.caster,
        pinhole,
        scene.lights,
        scene.intensity,
    )


def _result_textures(
    appearance: ResultAppearance,
    caster: RayCaster,
    raster: UVRaster,
    lights: np.ndarray,
    intensity: np.ndarray,
    edits: dict[str, float],
    strip: tuple[np.ndarray, float, float] | None,
) -> FrameTextures:
    """The frame textures of a RESULT on the posed ``raster``: entry flux under the rig's LEDs (only
    in the band ``strip = (right vector, width mm, offset mm)`` when given, without specular lobes),
    diffused with the (edited) chromophores and the RESULT's SoG shapes."""
    maps = appearance.maps
    rig = appearance.rig
    mask = raster.mask & appearance.mask
    shading = shading_normals(raster, maps["displacement_mm"])
    reference = rig.polarimetric_cameras()[0].pinhole()
    eta = np.where(mask, maps["eta"], 1.4).astype(np.float32)
    flux = entering_flux(caster, raster, shading, eta, lights, intensity, reference.up_vector)
    chromophores = apply_edits({k: maps[k] for k in CHROMOPHORE_NAMES}, edits)
    calibration = rig.spectral.to_calibration()
    params = {
        k: np.where(mask, maps[k], 0.0).astype(np.float32) for k in ("alpha_s", "alpha_ss", "rho_s", "rho_ss")
    }
    params["eta"] = eta
    if strip is not None:
        right_vector, width_mm, offset_mm = strip
        centre = raster.position[mask].mean(axis=0)
        offset = (raster.position - centre) @ right_vector - offset_mm
        flux = np.where(np.abs(offset) <= 0.5 * width_mm, flux, 0.0).astype(np.float32)
        params["rho_s"] = np.zeros_like(params["rho_s"])
        params["rho_ss"] = np.zeros_like(params["rho_ss"])
    raster_masked = dataclasses.replace(raster, mask=mask) if dataclasses.is_dataclass(raster) else raster
    model = SubsurfaceModel.build(
        chromophores, raster_masked, calibration.wavelengths_nm, shapes=appearance.shapes
    )
    exitance = texture_space_exitance(flux, model, calibration, blur=True)
    return FrameTextures.build(params, shading, exitance, mask)


def mueller_images(rendered: RenderedResult, chunk_pixels: int = 131072) -> np.ndarray:
    """Per-pixel 3x3 linear Mueller matrices ``(h, w, 6, 3, 3)`` float32 of a rendered view.

    Columns from the lobes under incident states ``[1, 1, 0]``, ``[1, -1, 0]``, ``[1, 0, 1]`` (camera
    frame convention of each LED, see module docstring); the diffused subsurface term (depolarised on
    entry) adds ``exit_stokes * exitance`` to the first column. Zero where no surface. Shaded in
    float64 with :mod:`polarface.render.shading`.
    """
    camera, mesh = rendered.camera, rendered.mesh_world
    height, width = rendered.mask.shape
    out = np.zeros((height * width, 6, 3, 3), np.float32)
    origins, directions = camera.pixel_rays()
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
    hit_index = np.nonzero(rendered.mask.reshape(-1))[0]
    centre = torch.from_numpy(camera.center.astype(np.float64))
    up = torch.from_numpy(camera.up_vector.astype(np.float64))
    states = torch.tensor(
        [[1.0, 1.0, 0.0, 0.0], [1.0, -1.0, 0.0, 0.0], [1.0, 0.0, 1.0, 0.0]], dtype=torch.float64
    )
    intensity = module_intensities(rendered.intensity, len(rendered.lights))
    face_normals = mesh.face_normals()
    for start in range(0, hit_index.size, chunk_pixels):
        index = hit_index[start : start + chunk_pixels]
        points = origins[index] + directions[index] * rendered.depth.reshape(-1)[index, None].astype(
            np.float64
        )
        position = torch.from_numpy(points)
        material = fragment_material(
            rendered.textures,
            torch.from_numpy(rendered.uv.reshape(-1, 2)[index]),
            torch.from_numpy(face_normals[rendered.face_id.reshape(-1)[index]].astype(np.float64)),
            position,
            centre,
            tuple(range(6)),
            trusted=False,
        )
        visible = rendered.caster.shadow_rays(points, material.geometric_normal.numpy(), rendered.lights)
        columns = []
        for state in states:
            zero = torch.zeros(len(index), 6, 4, dtype=torch.float64)
            total = lobe_stokes(
                material, position, centre, up, rendered.lights, visible, intensity, zero,
                light_stokes=state, skip_unlit=False,
            )
            columns.append(total[..., :3])
        m0 = 0.5 * (columns[0] + columns[1])
        m1 = 0.5 * (columns[0] - columns[1])
        m2 = columns[2] - m0
        exit_stokes = subsurface_exit_stokes(material.normal, position, centre, up, material.eta)
        m0 = m0 + material.exitance[..., None] * exit_stokes[..., :3]
        out[index] = torch.stack([m0, m1, m2], dim=-1).float().numpy()
    return out.reshape(height, width, 6, 3, 3)
