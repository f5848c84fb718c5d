"""The renderer: surface fragments -> polarimetric shading -> analyzer images of one camera view.

:func:`render_view` composes the stages. For every pixel of a camera the primary ray is cast against
the posed mesh with Embree (:func:`polarface.render.fragments.cast_fragments`); at each hit the UV
coordinate gives the per-texel parameters and the texture-space subsurface exitance
(:func:`polarface.render.shading.fragment_material`: bilinear lookups in textures whose empty texels
were filled from their nearest atlas texel, so seams do not darken); shadow rays decide which of the
LED modules see the point; the exit Fresnel transmission with its polarization is applied to the
diffused exitance (:func:`polarface.optics.subsurface_exit_stokes`) and the specular and
single-scattering lobes are added light by light (:func:`polarface.render.shading.lobe_stokes`). Only
the Stokes components a camera keeps are computed (``s0..s2`` for the analyzer images, ``s0`` for an RGB
camera), and a shadow ray is cast only towards the modules that light the fragment from the front
(elsewhere both lobes are exactly 0). The texture-space subsurface transport that produces the exitance
is :mod:`polarface.render.subsurface`.

Pixels are processed in chunks so memory stays bounded at 2448 x 2048.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from polarface._validation import trusted_inputs
from polarface.geometry.camera import PinholeCamera
from polarface.geometry.heights import normals_from_heights
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.raycast import RayCaster
from polarface.geometry.uv_raster import UVRaster
from polarface.optics.image_formation import subsurface_exit_stokes
from polarface.optics.lobes import ShadowTest
from polarface.render.fragments import cast_fragments
from polarface.render.shading import FrameTextures, fragment_material, lobe_stokes, module_intensities

__all__ = ["ViewRender", "analyzer_images", "render_view", "rig_lighting", "shading_normals"]


@dataclasses.dataclass(frozen=True, eq=False)
class ViewRender:
    """One camera's render of one frame.

    Attributes:
        images: name -> ``(h, w, C)`` float32 radiance images: ``i0``, ``i45``, ``i90``, ``i135`` for a
            polarization camera, ``s0`` (total intensity) for an RGB camera. Zero where no surface.
        mask: ``(h, w)`` bool, pixels whose ray hits the head.
        uv: ``(h, w, 2)`` float32 texture coordinates of the hit (0 where no hit).
        face_id: ``(h, w)`` int64 hit triangle (-1 where no hit).
        depth: ``(h, w)`` float32 distance along the ray in mm (inf where no hit).
    """

    images: dict[str, np.ndarray]
    mask: np.ndarray
    uv: np.ndarray
    face_id: np.ndarray
    depth: np.ndarray


def shading_normals(raster: UVRaster, displacement_mm: np.ndarray) -> np.ndarray:
    """``(Ht, Wt, 3)`` float64 world unit shading normals of a posed ``raster`` with the displacement
    map ``(Ht, Wt)`` (mm along the geometric normal) applied (:func:`normals_from_heights`).

    ``raster`` may also be a :class:`polarface.texture.TexelGeometry` (same per-texel fields; its
    frame, the model frame, is then the frame of the normals)."""
    as_tensor = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float64))  # noqa: E731
    return normals_from_heights(
        as_tensor(displacement_mm),
        as_tensor(raster.tangent_u),
        as_tensor(raster.tangent_v),
        as_tensor(raster.normal),
        as_tensor(raster.texel_size_u),
        as_tensor(raster.texel_size_v),
        torch.from_numpy(raster.mask),
    ).numpy()


def rig_lighting(rig) -> tuple[np.ndarray, np.ndarray]:
    """``(light positions (K, 3) float64 mm, radiant intensity of each module (K,) float64)`` of a rig
    (:class:`polarface.capture.rig.Rig`). The renderer's LEDs are spectrally flat (white-normalised
    channels, the rig's ``led_spd``): a module given six values (one per channel, as a calibration
    measures them) is rendered with their mean."""
    lights = np.array([light.position_mm for light in rig.lights], dtype=np.float64)
    intensity = np.array([float(np.mean(light.radiant_intensity)) for light in rig.lights], dtype=np.float64)
    return lights, intensity


def analyzer_images(stokes: torch.Tensor, polarization: bool) -> dict[str, torch.Tensor]:
    """Analyzer images ``(N, C)`` of Stokes ``(N, C, S)`` (camera frame): ``i0``, ``i45``, ``i90``,
    ``i135`` behind linear analyzers (``S >= 3``), or ``s0`` for an RGB camera (any ``S >= 1``)."""
    if not polarization:
        return {"s0": stokes[..., 0]}
    s0, s1, s2 = stokes[..., 0], stokes[..., 1], stokes[..., 2]
    return {
        "i0": 0.5 * (s0 + s1),
        "i45": 0.5 * (s0 + s2),
        "i90": 0.5 * (s0 - s1),
        "i135": 0.5 * (s0 - s2),
    }


def _shadow_test(
    caster: RayCaster, points: np.ndarray, normals: np.ndarray, lights: np.ndarray
) -> ShadowTest:
    """Lazy visibility of ``lights`` ``(K, 3)`` mm from fragments ``points`` with geometric ``normals``
    ``(N, 3)`` (float64): :meth:`RayCaster.shadow_rays_indexed` of module ``k`` from the asked rows."""
    return lambda module, rows: caster.shadow_rays_indexed(points, normals, lights, rows, module)


def render_view(
    caster: RayCaster,
    mesh: TriangleMesh,
    camera: PinholeCamera,
    textures: FrameTextures,
    light_positions: np.ndarray,
    light_intensity: float | np.ndarray,
    channels: tuple[int, ...],
    *,
    polarization: bool = True,
    chunk_pixels: int = 131072,
) -> ViewRender:
    """Render one camera view of the posed ``mesh`` (the mesh ``caster`` was built on).

    Args:
        caster: ray caster of ``mesh``.
        mesh: posed or deformed head, mm, world frame (its UVs index ``textures``).
        camera: the camera (OpenCV convention).
        textures: per-texel parameters, shading normals and diffused exitance of this frame.
        light_positions: ``(K, 3)`` LED module positions, mm.
        light_intensity: radiant intensity of every module, or ``(K,)`` one per module (spectrally
            flat; channel-normalised: :func:`~polarface.render.shading.module_intensities`).
        channels: indices into the six spectral channels that this camera records (e.g. ``(0, 2, 4)``).
        polarization: True for a polarization camera (four analyzer images), False for RGB (``s0``).
        chunk_pixels: pixels per chunk (memory bound).
    """
    height, width = camera.height, camera.width
    count = height * width
    origins, directions = camera.pixel_rays()
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
    names = ("i0", "i45", "i90", "i135") if polarization else ("s0",)
    out = {name: np.zeros((count, len(channels)), np.float32) for name in names}
    mask = np.zeros(count, bool)
    uv_out = np.zeros((count, 2), np.float32)
    face_out = np.full(count, -1, np.int64)
    depth_out = np.full(count, np.inf, np.float32)
    lights = np.asarray(light_positions, dtype=np.float64)
    # float32 throughout: positions at ~1 m keep ~1e-4 mm, ample for shading.
    centre = torch.from_numpy(camera.center.astype(np.float32))
    up = torch.from_numpy(camera.up_vector.astype(np.float32))
    unit_intensity = module_intensities(light_intensity, lights.shape[0], torch.float32)
    # the analyzer images need s0..s2, an RGB camera s0 alone: only those components are computed
    components = 3 if polarization else 1
    for start in range(0, count, chunk_pixels):
        stop = min(start + chunk_pixels, count)
        # camera rays and everything derived from them are valid by construction: the value checks of
        # the ray caster and the physics functions are skipped in this hot loop (shapes still checked)
        with trusted_inputs():
            fragments = cast_fragments(caster, mesh, origins[start:stop], directions[start:stop], start)
            if fragments.count == 0:
                continue
            index = fragments.pixel
            position = torch.from_numpy(fragments.position.astype(np.float32))
            material = fragment_material(
                textures,
                torch.from_numpy(fragments.uv.astype(np.float32)),
                torch.from_numpy(fragments.geometric_normal.astype(np.float32)),
                position,
                centre,
                channels,
            )
            shadow = _shadow_test(caster, fragments.position, fragments.geometric_normal, lights)
            # Subsurface: exit Fresnel transmission with its polarization applied to the exitance.
            exit_stokes = subsurface_exit_stokes(material.normal, position, centre, up, material.eta)
            stokes = material.exitance[..., None] * exit_stokes[..., :components]
            # Specular and single scattering: spectrally flat (white-normalised LEDs), so one channel
            # is computed and broadcast; each LED module times its shadow-ray visibility.
            stokes = lobe_stokes(material, position, centre, up, lights, shadow, unit_intensity, stokes)
        totals = analyzer_images(stokes, polarization)
        for name in names:
            out[name][index] = totals[name].float().numpy()
        mask[index] = True
        uv_out[index] = fragments.uv
        face_out[index] = fragments.face_id
        depth_out[index] = fragments.distance
    return ViewRender(
        images={name: image.reshape(height, width, len(channels)) for name, image in out.items()},
        mask=mask.reshape(height, width),
        uv=uv_out.reshape(height, width, 2),
        face_id=face_out.reshape(height, width),
        depth=depth_out.reshape(height, width),
    )
