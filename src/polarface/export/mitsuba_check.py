"""Render an exported Mitsuba scene and polarface's same view, split into I_sss and I_s, and compare.

The round trip of ``docs/export.md`` (section "Mitsuba 3"): the scene written by
:func:`polarface.export.mitsuba.write_mitsuba_scene` is loaded by Mitsuba 3 (``mitsuba`` is imported
only here; a ``*_polarized`` variant) and rendered twice, once with its specular reflectance texture set
to zero (``I_sss``: the diffuse lobe) and once with the diffuse one at zero (``I_s``). polarface renders
the same camera (:func:`polarface.render.render_view`) twice:

* ``exported``: the exported parameters (constant eta and alpha_s, RGB rho_sss_bar, rho_ss = 0) with
  the *local* subsurface term, exitance ``rho_sss_bar x`` entering flux per texel (the model pplastic
  evaluates, up to polarface's per-texel flux);
* ``full``: the RESULT as :func:`polarface.render.render_result_view` renders it (per-texel eta and
  alpha_s, the single-scattering lobe in ``I_s``, texture-space diffusion with the chromophores and SoG
  kernels in ``I_sss``), six channels reduced to RGB as the exported albedo is.

Images are Stokes ``(H, W, 3, 4)`` (RGB, S0..S3) of linear radiance in the camera's Stokes frame
(``docs/conventions.md``), LED intensity unit per mm^2 per sr.
"""

from __future__ import annotations

import dataclasses
import json
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage

from polarface.export.mitsuba_maps import rgb_albedo
from polarface.export.source import ExportSource
from polarface.geometry.uv_raster import rasterize_uv, reposition
from polarface.render.colour import linear_rgb_from_channels
from polarface.render.relight import render_result_view
from polarface.render.renderer import render_view, rig_lighting, shading_normals
from polarface.render.shading import EXITANCE_CHANNEL, PARAMETER_ORDER, FrameTextures
from polarface.render.subsurface import entering_flux
from polarface.results import ResultAppearance, layout

__all__ = ["MitsubaComparison", "compare_mitsuba_scene", "polarface_parts", "render_mitsuba_parts"]

_PARTS = ("sss", "s")


def render_mitsuba_parts(
    scene_xml: str | Path, sensor: int = 0, spp: int = 64, seed: int = 0, variant: str | None = None
) -> dict[str, np.ndarray]:
    """``{"sss", "s"}`` -> ``(H, W, 3, 4)`` float32 Stokes of Mitsuba's render of ``sensor``.

    Args:
        scene_xml: the exported ``scene.xml``.
        sensor: sensor index (0: the first polarimetric camera).
        spp: samples per pixel; seed: the sampler's seed.
        variant: a polarized Mitsuba variant (default ``scalar_spectral_polarized``).
    """
    import mitsuba as mi

    mi.set_variant(variant or "scalar_spectral_polarized")
    if not mi.is_polarized:
        raise ValueError(f"argument 'variant': '{mi.variant()}' is not a polarized Mitsuba variant")
    scene_xml = Path(scene_xml)
    resolver = mi.file_resolver()
    resolver.prepend(str(scene_xml.parent.resolve()))
    out = {}
    for part, dropped in (("sss", "specular_reflectance"), ("s", "diffuse_reflectance")):
        scene = mi.load_string(_without_texture(scene_xml, dropped), spp=int(spp))
        image = np.asarray(mi.render(scene, sensor=sensor, spp=int(spp), seed=seed), np.float32)
        # channels: RGB, then S0..S3 with R, G, B each.
        out[part] = image[..., 3:15].reshape(*image.shape[:2], 4, 3).transpose(0, 1, 3, 2).copy()
    return out


def _without_texture(scene_xml: Path, name: str) -> str:
    """The text of ``scene_xml`` with the texture ``name`` of its ``pplastic`` replaced by 0."""
    root = ElementTree.parse(scene_xml).getroot()
    for plastic in root.iter("bsdf"):
        if plastic.get("type") != "pplastic":
            continue
        for child in list(plastic):
            if child.get("name") == name:
                plastic.remove(child)
                ElementTree.SubElement(plastic, "float", {"name": name, "value": "0"})
    return ElementTree.tostring(root, encoding="unicode")


def _stokes_of(images: dict[str, np.ndarray]) -> np.ndarray:
    """``(H, W, C, 4)`` Stokes of analyzer images (``i0``..``i135``, ``(H, W, C)``), S3 = 0."""
    s0 = images["i0"] + images["i90"]
    return np.stack(
        [s0, images["i0"] - images["i90"], images["i45"] - images["i135"], np.zeros_like(s0)], axis=-1
    )


def polarface_parts(source: ExportSource, constants: dict[str, float]) -> dict[str, dict[str, np.ndarray]]:
    """polarface's renders of the first polarimetric camera: ``{"exported", "full"}`` -> ``{"sss", "s",
    "mask"}`` (module docstring), Stokes ``(H, W, 3, 4)`` float32 and the hit mask ``(H, W)`` bool.

    ``constants``: the exported ``eta``, ``alpha_s`` and ``placement`` (the writer's record).
    """
    appearance = ResultAppearance.load(source.folder)
    rig = appearance.rig
    full = render_result_view(appearance, pose=np.asarray(constants["placement"]))
    camera, caster, mesh_world = full.camera, full.caster, full.mesh_world
    lights, intensity = full.lights, full.intensity
    out: dict[str, dict[str, np.ndarray]] = {}
    stack = full.textures.stack.numpy()
    rho = [PARAMETER_ORDER.index("rho_s"), PARAMETER_ORDER.index("rho_ss")]
    parts = {"sss": stack.copy(), "s": stack.copy()}
    parts["sss"][..., rho] = 0.0
    parts["s"][..., EXITANCE_CHANNEL:] = 0.0
    out["full"] = {"mask": full.mask}
    for part, values in parts.items():
        textures = dataclasses.replace(full.textures, stack=torch.from_numpy(values))
        view = render_view(caster, mesh_world, camera, textures, lights, intensity, tuple(range(6)))
        six = _stokes_of(view.images)  # (H, W, 6, 4)
        out["full"][part] = np.moveaxis(linear_rgb_from_channels(np.moveaxis(six, -2, -1), rig), -1, -2)
    out["exported"] = _exported_parts(source, constants, caster, mesh_world, camera)
    return out


def _exported_parts(source: ExportSource, constants, caster, mesh_world, camera) -> dict[str, np.ndarray]:
    """polarface's render of the exported parameters with the local subsurface term."""
    rig = source.rig
    mask = source.mask
    raster = reposition(rasterize_uv(source.mesh, mask.shape), mesh_world)
    mask = mask & raster.mask
    normals = shading_normals(raster, np.where(mask, source.scalar_map("displacement_mm"), 0.0))
    lights, intensity = rig_lighting(rig)
    eta = np.full(mask.shape, constants["eta"], np.float32)
    flux = entering_flux(caster, raster, normals, eta, lights, intensity, camera.up_vector)
    albedo = rgb_albedo(source.channel_map(layout.RHO_SSS_BAR), rig, mask)
    params = {
        "eta": eta,
        "alpha_s": np.full(mask.shape, constants["alpha_s"], np.float32),
        "alpha_ss": np.full(mask.shape, 0.5, np.float32),
        "rho_s": np.maximum(np.where(mask, source.scalar_map("rho_s"), 0.0), 0.0).astype(np.float32),
        "rho_ss": np.zeros(mask.shape, np.float32),
    }
    exitance = albedo * flux[..., None]
    out = {}
    for part in _PARTS:
        values = dict(params)
        if part == "sss":
            values["rho_s"] = np.zeros_like(params["rho_s"])
        textures = FrameTextures.build(values, normals, exitance if part == "sss" else 0 * exitance, mask)
        view = render_view(caster, mesh_world, camera, textures, lights, intensity, (0, 1, 2))
        out[part] = _stokes_of(view.images)
        out["mask"] = view.mask
    return out


def relative_rmse(test: np.ndarray, reference: np.ndarray, pixels: np.ndarray) -> float:
    """``sqrt(mean((test - reference)^2) / mean(reference^2))`` over ``pixels`` ``(H, W)`` bool and the
    remaining axes."""
    a, b = test[pixels].astype(np.float64), reference[pixels].astype(np.float64)
    return float(np.sqrt(np.mean((a - b) ** 2) / max(np.mean(b**2), 1e-30)))


@dataclasses.dataclass(frozen=True, eq=False)
class MitsubaComparison:
    """One round trip.

    Attributes:
        mitsuba: ``{"sss", "s"}`` Stokes ``(H, W, 3, 4)`` of Mitsuba.
        polarface: ``{"exported", "full"}`` -> ``{"sss", "s", "mask"}`` of polarface.
        face: ``(H, W)`` bool compared pixels: polarface's hit mask eroded by ``erode`` pixels.
        metrics: ``"<reference>.<part>.<S0|S1>"`` -> relative RMSE over ``face`` and RGB.
    """

    mitsuba: dict
    polarface: dict
    face: np.ndarray
    metrics: dict


def compare_mitsuba_scene(
    source: ExportSource, scene_dir: str | Path, spp: int = 64, erode: int = 2, variant: str | None = None
) -> MitsubaComparison:
    """Render ``scene_dir/scene.xml`` (the export of ``source``) and polarface's same view; compare.

    The relative RMSE of S0 (intensity) and S1 (co- minus cross-polarized, which polarization frames
    and the LED polarizers decide) of each part, against both polarface references.
    """
    scene_dir = Path(scene_dir)
    mapping = json.loads((scene_dir / "cameras.json").read_text())
    constants = {**mapping["constants"], "placement": mapping["placement"]}
    references = polarface_parts(source, constants)
    mitsuba = render_mitsuba_parts(scene_dir / "scene.xml", spp=spp, variant=variant)
    face = ndimage.binary_erosion(references["full"]["mask"], iterations=erode)
    metrics = {}
    for reference, parts in references.items():
        for part in _PARTS:
            for index, name in enumerate(("S0", "S1")):
                metrics[f"{reference}.{part}.{name}"] = relative_rmse(
                    mitsuba[part][..., index], parts[part][..., index], face
                )
    return MitsubaComparison(mitsuba, references, face, metrics)
