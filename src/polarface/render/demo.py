"""The bundled demo: an analytic skin-like sphere under the rig's 8 polarized LED modules.

:func:`render_demo` ray-traces the sphere with a pinhole camera at 1 m and evaluates the pBSSRDF forward
model (:func:`polarface.optics.render_polarimetric`) on the hit pixels. Defaults follow the paper's rig
(8 modules on a ~100 mm circle around the lens, subject at ~1000 mm: 5.72 deg off axis; light polarized
along the image x axis) and skin-like parameters (eta 1.44, alpha_s 0.45, alpha_ss 0.95).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from polarface.geometry.camera import PinholeCamera
from polarface.optics.image_formation import PolarimetricImages, render_polarimetric
from polarface.render.scene import SphereGeometry, ring_light_positions, trace_sphere

__all__ = ["DemoParameters", "DemoRender", "render_demo"]


@dataclass(frozen=True)
class DemoParameters:
    """Scene and material of the demo (defaults reproduce the paper's rig; 3 channels R, G, B).

    Attributes:
        width, height: image size in pixels. focal_px: focal length in pixels.
        sphere_radius_mm, subject_distance_mm: sphere radius and distance of its centre from the lens.
        ring_radius_mm, light_count: LED ring around the lens (mm) and number of modules.
        light_intensity: radiant intensity per module and channel (arbitrary unit; the default makes
            the total irradiance at the subject about pi per channel, so I_sss ~ rho_sss_bar T+^2).
        eta, alpha_s, alpha_ss, rho_s, rho_ss: pBSSRDF parameters (scalars).
        rho_sss_bar: subsurface albedo per channel, dimensionless in [0, 1].
    """

    width: int = 256
    height: int = 256
    focal_px: float = 1400.0
    sphere_radius_mm: float = 80.0
    subject_distance_mm: float = 1000.0
    ring_radius_mm: float = 100.0
    light_count: int = 8
    light_intensity: tuple[float, ...] = (math.pi * 1e6 / 8,) * 3
    eta: float = 1.44
    alpha_s: float = 0.45
    alpha_ss: float = 0.95
    rho_s: float = 1.0
    rho_ss: float = 0.3
    rho_sss_bar: tuple[float, ...] = (0.62, 0.42, 0.33)
    channel_names: tuple[str, ...] = field(default=("R", "G", "B"))

    def __post_init__(self) -> None:
        channels = len(self.rho_sss_bar)
        if len(self.light_intensity) != channels or len(self.channel_names) != channels:
            raise ValueError("arguments 'light_intensity', 'rho_sss_bar' and 'channel_names' must have the "
                             f"same length; got {len(self.light_intensity)}, {channels}, "
                             f"{len(self.channel_names)}")

    @property
    def off_axis_deg(self) -> float:
        """Angle between a light and the optical axis seen from the subject, degrees."""
        return math.degrees(math.atan2(self.ring_radius_mm, self.subject_distance_mm))


@dataclass(frozen=True)
class DemoRender:
    """Result of :func:`render_demo`.

    Attributes:
        images: :class:`PolarimetricImages` with ``(H, W, C)`` torch tensors (0 outside the sphere).
        geometry: the sphere's per-pixel geometry (mask, position mm, normal).
        camera: the pinhole camera. light_positions: ``(K, 3)`` mm.
    """

    images: PolarimetricImages
    geometry: SphereGeometry
    camera: PinholeCamera
    light_positions: torch.Tensor


def render_demo(params: DemoParameters | None = None, *, dtype: torch.dtype = torch.float32,
                **overrides: float) -> DemoRender:
    """Render the demo sphere; keyword ``overrides`` replace fields of ``params`` (e.g. ``rho_s=0``)."""
    params = params or DemoParameters()
    if overrides:
        params = DemoParameters(**{**params.__dict__, **overrides})
    camera = PinholeCamera.centred(params.width, params.height, params.focal_px)
    geometry = trace_sphere(camera, (0.0, 0.0, params.subject_distance_mm), params.sphere_radius_mm, dtype)
    lights = ring_light_positions(camera, params.ring_radius_mm, params.light_count, dtype=dtype)
    mask = geometry.mask
    intensity = torch.tensor(params.light_intensity, dtype=dtype).expand(params.light_count, -1)
    hit = render_polarimetric(
        geometry.normal[mask], geometry.position[mask], camera.center_tensor(dtype), camera.up_tensor(dtype),
        lights,
        intensity, params.eta, params.alpha_s, params.alpha_ss, params.rho_s, params.rho_ss,
        torch.tensor(params.rho_sss_bar, dtype=dtype),
    )

    def scatter(values: torch.Tensor) -> torch.Tensor:
        full = values.new_zeros(mask.shape + values.shape[1:])
        full[mask] = values
        return full

    images = PolarimetricImages(**{name: scatter(getattr(hit, name)) for name in
                                   ("i0", "i45", "i90", "i135", "stokes", "specular", "single_scattering",
                                    "subsurface")})
    return DemoRender(images=images, geometry=geometry, camera=camera, light_positions=lights)
