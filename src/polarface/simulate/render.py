"""Per-camera rendering of the simulator: ray casting, shadows, pBSSRDF shading, analyzer images.

For every pixel of a camera: the primary ray is cast against the posed mesh with Embree
(:class:`polarface.geometry.raycast.RayCaster`); at the hit the UV coordinate gives the per-texel
parameters and the texture-space subsurface exitance (bilinear lookups in textures whose empty texels
were filled from their nearest atlas texel, so seams do not darken); shadow rays decide which of the
8 LED modules see the point; :func:`polarface.optics.render_polarimetric` evaluates the specular and
single-scattering lobes through the full Mueller matrices and applies the exit Fresnel transmission
with its polarization to the diffused exitance. Lights are summed one by one, each multiplied by its
per-pixel visibility (the image formation is linear in the lights).

Pixels are processed in chunks so memory stays bounded at 2448 x 2048.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from scipy import ndimage

from polarface._validation import trusted_inputs
from polarface.geometry.camera import PinholeCamera
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.raycast import RayCaster
from polarface.geometry.uv_raster import sample_texture
from polarface.optics.image_formation import render_polarimetric, subsurface_exit_stokes

__all__ = ["FrameTextures", "ViewRender", "fill_empty_texels", "render_view"]

#: Order of the parameter channels stacked in :attr:`FrameTextures.stack`.
PARAMETER_ORDER = ("eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss")


def fill_empty_texels(texture: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Copy of ``texture`` ``(H, W[, C])`` whose texels outside ``mask`` take their nearest valid value.

    Keeps bilinear lookups near atlas seams from blending in empty (zero) texels.
    """
    if mask.all():
        return texture.copy()
    _, (rows, cols) = ndimage.distance_transform_edt(~mask, return_indices=True)
    return texture[rows, cols]


@dataclasses.dataclass(frozen=True, eq=False)
class FrameTextures:
    """Everything a camera needs per texel for one frame, as one stacked float32 tensor.

    Attributes:
        stack: ``(Ht, Wt, 5 + 3 + 6)``: the parameters in :data:`PARAMETER_ORDER`, the world-space
            unit shading normal of the posed frame (from the displacement map), and the six-channel
            diffused subsurface exitance (light intensity unit per mm^2) — empty texels filled.
    """

    stack: torch.Tensor

    @classmethod
    def build(
        cls,
        parameters: dict[str, np.ndarray],
        shading_normal: np.ndarray,
        exitance: np.ndarray,
        mask: np.ndarray,
    ) -> FrameTextures:
        """Stack and fill ``parameters`` (name -> ``(Ht, Wt)``), normals ``(Ht, Wt, 3)`` and the
        exitance ``(Ht, Wt, 6)``."""
        layers = [parameters[name][..., None] for name in PARAMETER_ORDER]
        stack = np.concatenate([*layers, shading_normal, exitance], axis=-1).astype(np.float32)
        return cls(torch.from_numpy(fill_empty_texels(stack, mask)))


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


def render_view(
    caster: RayCaster,
    mesh: TriangleMesh,
    camera: PinholeCamera,
    textures: FrameTextures,
    light_positions: np.ndarray,
    light_intensity: float,
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
        light_intensity: radiant intensity of each module (spectrally flat; channel-normalised).
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
    unit_intensity = torch.full((1, 1), float(light_intensity), dtype=torch.float32)
    channel_index = torch.tensor([5 + 3 + c for c in channels])
    for start in range(0, count, chunk_pixels):
        stop = min(start + chunk_pixels, count)
        hits = caster.first_hits(origins[start:stop], directions[start:stop])
        if not hits.hit.any():
            continue
        local = np.nonzero(hits.hit)[0]
        index = start + local
        face = hits.face_id[local]
        corner_uv = mesh.uv[mesh.faces[face]]
        uv = np.einsum("rk,rkc->rc", hits.barycentric[local], corner_uv)
        with trusted_inputs():  # the texture stack is built and filled by FrameTextures.build
            sampled = sample_texture(textures.stack, torch.from_numpy(uv.astype(np.float32)))
        normal = sampled[:, 5:8]
        normal = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        position = torch.from_numpy(hits.point[local].astype(np.float32))
        # The shading normal may tilt past the view direction at silhouettes; keep it facing the camera.
        to_camera = centre - position
        to_camera = to_camera / to_camera.norm(dim=-1, keepdim=True)
        facing = (normal * to_camera).sum(-1, keepdim=True)
        geometric = torch.from_numpy(hits.geometric_normal[local].astype(np.float32))
        geometric = geometric * torch.where((geometric * to_camera).sum(-1, keepdim=True) < 0, -1.0, 1.0)
        normal = torch.where(facing > 1e-3, normal, geometric)
        params = {name: sampled[:, i : i + 1] for i, name in enumerate(PARAMETER_ORDER)}
        exitance = sampled[:, channel_index]
        eta = params["eta"].clamp_min(1.0 + 1e-6)
        visible = caster.shadow_rays(hits.point[local], hits.geometric_normal[local], lights)  # (N, K)
        with trusted_inputs():  # validated once above; skip per-call value checks in the hot loop
            # Subsurface: exit Fresnel transmission with its polarization applied to the exitance.
            stokes = exitance[..., None] * subsurface_exit_stokes(normal, position, centre, up, eta)
            # Specular and single scattering: spectrally flat (white-normalised LEDs), so one channel
            # is computed and broadcast; each LED module times its shadow-ray visibility.
            no_exitance = torch.zeros_like(exitance[:, :1])
            for k in range(lights.shape[0]):
                lit = torch.from_numpy(visible[:, k].astype(np.float32))[:, None, None]
                if not bool(lit.any()):
                    continue
                images = render_polarimetric(
                    normal,
                    position,
                    centre,
                    up,
                    torch.from_numpy(lights[k : k + 1].astype(np.float32)),
                    unit_intensity,
                    eta,
                    params["alpha_s"].clamp_min(1e-3),
                    params["alpha_ss"].clamp_min(1e-3),
                    params["rho_s"].clamp_min(0.0),
                    params["rho_ss"].clamp_min(0.0),
                    0.0,
                    diffused_exitance=no_exitance,
                )
                stokes = stokes + lit * images.stokes
        s0, s1, s2 = stokes[..., 0], stokes[..., 1], stokes[..., 2]
        if polarization:
            totals = {
                "i0": 0.5 * (s0 + s1),
                "i45": 0.5 * (s0 + s2),
                "i90": 0.5 * (s0 - s1),
                "i135": 0.5 * (s0 - s2),
            }
        else:
            totals = {"s0": s0}
        for name in names:
            out[name][index] = totals[name].float().numpy()
        mask[index] = True
        uv_out[index] = uv
        face_out[index] = face
        depth_out[index] = hits.distance[local]
    return ViewRender(
        images={name: image.reshape(height, width, len(channels)) for name, image in out.items()},
        mask=mask.reshape(height, width),
        uv=uv_out.reshape(height, width, 2),
        face_id=face_out.reshape(height, width),
        depth=depth_out.reshape(height, width),
    )
