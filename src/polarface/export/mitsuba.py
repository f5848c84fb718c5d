"""Mitsuba 3 scene of a static RESULT: the head under the rig's polarized LEDs, seen by the rig's cameras.

``write_mitsuba_scene`` writes (``docs/export.md``, section "Mitsuba 3", has the full mapping)::

    out/scene.xml              Mitsuba 3 scene (version 3.0.0), lengths in mm (rig world)
    out/meshes/face.ply        the RESULT mesh at polarface's render placement, vertex normals, uv
    out/textures/*.exr         rho_sss_bar (RGB), rho_s, normal (tangent space, raw)
    out/cameras.json           what maps to what: cameras, LEDs, constants, placement

Material: ``normalmap`` around ``pplastic`` (GGX specular with the full Fresnel Mueller matrix plus the
Fresnel-transmission diffuse lobe; the pBSSRDF with ``rho_ss = 0`` and local subsurface transport):
``int_ior = eta``, ``alpha = alpha_s`` (GGX alpha as polarface uses it, not squared) as the medians over
the mask (pplastic takes no texture for them), ``specular_reflectance = rho_s`` and
``diffuse_reflectance = rho_sss_bar`` (RGB: mean of the two half bands per colour) as textures.

LEDs: polarface's point light of radiant intensity ``I_L`` and Stokes ``[1, 1, 0, 0]`` becomes a Mitsuba
``point`` emitter of intensity ``2 I_L`` (white, D65-normalised RGB) behind a ``polarizer`` sheet (an
ideal linear polarizer passes half of unpolarized light). The sheet is a null-BSDF surface, which only
the ``volpath`` integrator lets shadow rays pass, so the scene's integrator is ``stokes`` around
``volpath`` with ``max_depth`` 2 (direct light only, like polarface's renderer).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ElementTree
from pathlib import Path
from typing import Any

import numpy as np

from polarface.export.formats import ExportOptions
from polarface.export.mitsuba_maps import mitsuba_mesh, rgb_albedo, tangent_space_normals
from polarface.export.source import ExportSource
from polarface.geometry.mesh import save_ply
from polarface.geometry.uv_raster import rasterize_uv, reposition
from polarface.io import atomic_path, write_exr, write_json_atomic
from polarface.optics import stokes_frame
from polarface.render.colour import linear_rgb_from_channels
from polarface.render.shading import fill_empty_texels
from polarface.results import layout

__all__ = [
    "MITSUBA_LOST",
    "SHEET_DISTANCE_MM",
    "SHEET_HALF_SIZE_MM",
    "scene_placement",
    "write_mitsuba_scene",
]

#: Distance (mm) of each LED's polarizer sheet from the LED, along the direction to the face centre.
SHEET_DISTANCE_MM = 5.0
#: Half side (mm) of the square polarizer sheet (covers +-45 deg around the face direction).
SHEET_HALF_SIZE_MM = 5.0

#: What the scene cannot carry (also ``record["lost"]``; constants are added per export).
MITSUBA_LOST = (
    "rho_ss, alpha_ss: pplastic has one specular lobe; the single-scattering lobe is dropped",
    "subsurface diffusion (chromophores, SoG kernels): pplastic's diffuse lobe is local "
    "(rho_sss_bar / pi with Fresnel transmission in and out), no blur under the skin",
    "six spectral channels: textures are RGB, each colour the mean of its two half bands; Mitsuba "
    "upsamples RGB to spectra",
    "camera distortion and skew: Mitsuba's perspective sensor is an ideal pinhole with square pixels",
)


def scene_placement(source: ExportSource) -> np.ndarray:
    """``(4, 4)`` model -> rig-world transform of the exported head: polarface's render placement
    (:meth:`polarface.results.ResultFolder.rest_placement`: identity for stereo geometry, whose model frame
    is the rig world of its reference frame; else the bundled head's rest placement)."""
    return source.folder.rest_placement()


def write_mitsuba_scene(source: ExportSource, out: Path, options: ExportOptions) -> dict[str, Any]:
    """Write the Mitsuba 3 scene of ``source``'s static result into the empty folder ``out``.

    Args:
        source: the RESULT (maps checked by the caller: ``EXPORT_FORMATS["mitsuba"].maps``).
        out: this format's folder.
        options: export options (none concern this format).

    Returns:
        The record: ``files`` (relative to ``out``), ``units``, ``variant``, ``integrator``,
        ``default_sensor``, ``constants`` (medians over the mask), ``lost``.

    Raises:
        ValueError: the rig has fewer than two polarimetric cameras (the RGB reduction needs both half
            bands), or the mask is empty.
    """
    del options
    out = Path(out)
    rig = source.rig
    if len(rig.polarimetric_cameras()) < 2:
        raise ValueError(f"'{source.folder.rig_path}': the Mitsuba export needs two polarimetric cameras")
    mask = source.mask
    if not mask.any():
        raise ValueError(f"'{source.map_file(layout.MASK)}': the mask is empty")
    placement = scene_placement(source)
    mesh_world = mitsuba_mesh(source.mesh.transformed(placement))
    raster = reposition(rasterize_uv(source.mesh, mask.shape), source.mesh.transformed(placement))
    texture_mask = mask & raster.mask
    constants = {name: float(np.median(source.scalar_map(name)[texture_mask])) for name in ("eta", "alpha_s")}
    constants["eta"] = max(constants["eta"], 1.0 + 1e-4)
    constants["alpha_s"] = min(max(constants["alpha_s"], 1e-3), 1.0)
    files = _write_textures(source, out, raster, mesh_world, texture_mask)
    save_ply(out / "meshes" / "face.ply", mesh_world)
    cameras = _camera_records(rig)
    lights = _light_records(rig, mesh_world.vertices.mean(axis=0))
    scene = _scene_xml(cameras, lights, constants)
    ElementTree.indent(scene)
    with atomic_path(out / "scene.xml") as tmp:
        ElementTree.ElementTree(scene).write(tmp, encoding="utf-8", xml_declaration=True)
    lost = [*MITSUBA_LOST]
    lost += [
        f"{name} map: the constant {value:.6g} (median over the mask)" for name, value in constants.items()
    ]
    lost += [f"camera {c['id']}: {note}" for c in cameras for note in c["lost"]]
    mapping = {
        "units": "mm (rig world: the RESULT's mesh.obj under 'placement', model -> rig world)",
        "placement": placement.tolist(),
        "cameras": cameras,
        "lights": lights,
        "constants": constants,
        "textures": {
            "rho_sss_bar": "textures/rho_sss_bar.exr",
            "rho_s": "textures/rho_s.exr",
            "normal": "textures/normal.exr",
        },
    }
    write_json_atomic(out / "cameras.json", mapping)
    files += ["meshes/face.ply", "cameras.json", "scene.xml"]
    return {
        "files": sorted(files),
        "units": "mm",
        "variant": "scalar_spectral_polarized (or any *_polarized variant)",
        "integrator": "stokes(volpath, max_depth=2)",
        "default_sensor": cameras[0]["id"],
        "constants": constants,
        "placement": placement.tolist(),
        "lost": lost,
    }


def _write_textures(source: ExportSource, out: Path, raster, mesh_world, mask: np.ndarray) -> list[str]:
    """The EXR textures (module docstring); returns their paths relative to ``out``."""
    rig = source.rig
    albedo = rgb_albedo(source.channel_map(layout.RHO_SSS_BAR), rig, mask)
    write_exr(out / "textures" / "rho_sss_bar.exr", albedo, ["R", "G", "B"])
    rho_s = np.maximum(np.where(mask, source.scalar_map("rho_s"), 0.0), 0.0).astype(np.float32)
    write_exr(out / "textures" / "rho_s.exr", fill_empty_texels(rho_s, mask).astype(np.float32), ["Y"])
    encoded, _ = tangent_space_normals(raster, mesh_world, source.scalar_map("displacement_mm"))
    write_exr(out / "textures" / "normal.exr", encoded, ["R", "G", "B"])
    return ["textures/normal.exr", "textures/rho_s.exr", "textures/rho_sss_bar.exr"]


def _camera_records(rig) -> list[dict[str, Any]]:
    """Per camera (polarimetric first): Mitsuba ``to_world``, field of view, principal point offsets."""
    ordered = rig.polarimetric_cameras() + [c for c in rig.cameras if c.role != "polarimetric"]
    records = []
    for camera in ordered:
        pinhole = camera.pinhole()
        K = pinhole.K
        camera_to_world = np.linalg.inv(pinhole.world_to_camera)
        # OpenCV (x right, y down, z forward) -> Mitsuba's camera (x left, y up, z forward).
        to_world = camera_to_world @ np.diag([-1.0, -1.0, 1.0, 1.0])
        lost = []
        if abs(K[0, 0] - K[1, 1]) > 1e-6 * K[0, 0]:
            lost.append(f"fy {K[1, 1]:.6g} != fx {K[0, 0]:.6g}: the field of view follows fx")
        if abs(K[0, 1]) > 0:
            lost.append(f"skew {K[0, 1]:.6g} dropped")
        if np.any(pinhole.distortion != 0):
            lost.append(f"distortion {pinhole.distortion.tolist()} dropped")
        records.append(
            {
                "id": camera.id,
                "role": camera.role,
                "width": pinhole.width,
                "height": pinhole.height,
                "to_world": to_world.tolist(),
                "fov_x_deg": math.degrees(2.0 * math.atan(0.5 * pinhole.width / K[0, 0])),
                # OpenCV pixel centres are integers; Mitsuba's film pixel i spans [i, i + 1].
                "principal_point_offset_x": (K[0, 2] + 0.5 - 0.5 * pinhole.width) / pinhole.width,
                "principal_point_offset_y": (K[1, 2] + 0.5 - 0.5 * pinhole.height) / pinhole.height,
                "lost": lost,
            }
        )
    return records


def _light_records(rig, face_centre: np.ndarray) -> list[dict[str, Any]]:
    """Per LED: position, Mitsuba intensity (RGB, 2 I_L) and the polarizer sheet's ``to_world``.

    The sheet faces the face centre; its transmission axis (local x) is the LED's polarizer axis in the
    light's Stokes frame (:func:`polarface.optics.stokes_frame` of the direction to the face centre with
    the first polarimetric camera's up), rotated by ``polarizer_angle`` from its x axis towards its y axis.
    """
    up = rig.polarimetric_cameras()[0].pinhole().up_vector
    records = []
    for light in rig.lights:
        position = np.asarray(light.position_mm, np.float64)
        direction = face_centre - position
        direction /= np.linalg.norm(direction)
        x_axis, y_axis = (np.asarray(a, np.float64) for a in stokes_frame(direction, np.asarray(up, float)))
        angle = float(light.polarizer_angle)
        transmit = math.cos(angle) * x_axis + math.sin(angle) * y_axis
        absorb = np.cross(direction, transmit)
        to_world = np.eye(4)
        to_world[:3, 0] = transmit * SHEET_HALF_SIZE_MM
        to_world[:3, 1] = absorb * SHEET_HALF_SIZE_MM
        to_world[:3, 2] = direction
        to_world[:3, 3] = position + SHEET_DISTANCE_MM * direction
        six = np.broadcast_to(np.asarray(light.radiant_intensity, np.float64), (6,))
        rgb = 2.0 * linear_rgb_from_channels(six, rig)
        records.append(
            {
                "id": light.id,
                "position_mm": position.tolist(),
                "radiant_intensity_rgb": (0.5 * rgb).tolist(),
                "mitsuba_intensity_rgb": rgb.tolist(),
                "polarizer_angle": angle,
                "sheet_to_world": to_world.tolist(),
            }
        )
    return records


def _add(parent: ElementTree.Element, tag: str, **attributes: Any) -> ElementTree.Element:
    return ElementTree.SubElement(parent, tag, {k: str(v) for k, v in attributes.items()})


def _matrix(parent: ElementTree.Element, matrix: list[list[float]]) -> None:
    transform = _add(parent, "transform", name="to_world")
    _add(transform, "matrix", value=" ".join(f"{v:.12g}" for row in matrix for v in row))


def _bitmap(parent: ElementTree.Element, name: str, filename: str, raw: bool) -> None:
    texture = _add(parent, "texture", type="bitmap", name=name)
    _add(texture, "string", name="filename", value=filename)
    _add(texture, "boolean", name="raw", value=str(raw).lower())
    _add(texture, "string", name="filter_type", value="bilinear")
    _add(texture, "string", name="wrap_mode", value="clamp")


def _scene_xml(cameras: list[dict], lights: list[dict], constants: dict[str, float]) -> ElementTree.Element:
    scene = ElementTree.Element("scene", version="3.0.0")
    scene.append(ElementTree.Comment(" polarface export: lengths in mm, rig world; docs/export.md "))
    _add(scene, "default", name="spp", value=64)
    integrator = _add(scene, "integrator", type="stokes")
    nested = _add(integrator, "integrator", type="volpath")
    _add(nested, "integer", name="max_depth", value=2)
    for camera in cameras:
        scene.append(ElementTree.Comment(f" camera {camera['id']} ({camera['role']}) "))
        sensor = _add(scene, "sensor", type="perspective", id=camera["id"])
        _add(sensor, "string", name="fov_axis", value="x")
        _add(sensor, "float", name="fov", value=f"{camera['fov_x_deg']:.12g}")
        for axis in ("x", "y"):
            key = f"principal_point_offset_{axis}"
            _add(sensor, "float", name=key, value=f"{camera[key]:.12g}")
        _add(sensor, "float", name="near_clip", value=10.0)
        _add(sensor, "float", name="far_clip", value=100000.0)
        _matrix(sensor, camera["to_world"])
        film = _add(sensor, "film", type="hdrfilm")
        _add(film, "integer", name="width", value=camera["width"])
        _add(film, "integer", name="height", value=camera["height"])
        _add(film, "rfilter", type="box")
        sampler = _add(sensor, "sampler", type="independent")
        _add(sampler, "integer", name="sample_count", value="$spp")
    for light in lights:
        scene.append(ElementTree.Comment(f" LED {light['id']}: point light behind a linear polarizer "))
        emitter = _add(scene, "emitter", type="point", id=light["id"])
        _add(emitter, "point", name="position", value=", ".join(f"{v:.12g}" for v in light["position_mm"]))
        rgb = ", ".join(f"{v:.12g}" for v in light["mitsuba_intensity_rgb"])
        _add(emitter, "rgb", name="intensity", value=rgb)
        sheet = _add(scene, "shape", type="rectangle", id=f"{light['id']}_polarizer")
        _matrix(sheet, light["sheet_to_world"])
        _add(sheet, "bsdf", type="polarizer")
    shape = _add(scene, "shape", type="ply", id="face")
    _add(shape, "string", name="filename", value="meshes/face.ply")
    normalmap = _add(shape, "bsdf", type="normalmap", id="skin")
    _bitmap(normalmap, "normalmap", "textures/normal.exr", raw=True)
    plastic = _add(normalmap, "bsdf", type="pplastic")
    _add(plastic, "string", name="distribution", value="ggx")
    _add(plastic, "float", name="alpha", value=f"{constants['alpha_s']:.9g}")
    _add(plastic, "float", name="int_ior", value=f"{constants['eta']:.9g}")
    _add(plastic, "float", name="ext_ior", value=1.0)
    _bitmap(plastic, "diffuse_reflectance", "textures/rho_sss_bar.exr", raw=False)
    # one channel, raw: used as a flat spectrum without upsampling, so values above 1 survive.
    _bitmap(plastic, "specular_reflectance", "textures/rho_s.exr", raw=True)
    return scene
