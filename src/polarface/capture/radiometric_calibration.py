"""LED module intensities and polarization camera gains from a white diffuse sphere (``polarface
calibrate-rig``, its ``radiometric`` step; docs/calibration.md).

A white diffuse (Spectralon-like) sphere of known radius and albedo is placed where the face will be and
lit by one LED module at a time. Where module ``k`` lights it, a Lambertian sphere's radiance is

    L = albedo / pi * I_k * cos(theta) / d^2

(:func:`lambertian_sphere`: ``theta`` between the normal and the module, ``d`` the distance to it), the
same in every channel of white-normalised channels. A camera records ``g L`` in each colour, ``g`` its
gain, so each frame gives one product ``P = g_c I_k,c`` per channel ``c`` (:func:`channel_products`, a
least-squares ratio over the sphere's pixels). Only the products are measurable: multiplying a channel's
gain and dividing every module's intensity in it by one factor changes no image. The calibration fixes
that factor by keeping the modules' mean intensity per channel at the nominal rig's
(:func:`split_products`), so the gains put the two polarization cameras (three channels each) on one
scale and the intensities say how the modules differ.
"""

from __future__ import annotations

import numpy as np

from polarface.geometry.camera import PinholeCamera

__all__ = ["channel_products", "lambertian_sphere", "split_products"]


def lambertian_sphere(camera: PinholeCamera, centre_mm: np.ndarray, radius_mm: float, light_mm: np.ndarray,
                      pixels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The radiance of a Lambertian sphere of albedo 1 lit by a point light of intensity 1 at ``light_mm``,
    at ``pixels`` ``(..., 2)`` (default: every pixel of ``camera``): ``(radiance, the light's cosine, the
    view's cosine)``, each ``(...)`` float64 and 0 where the ray misses the sphere (and the radiance and
    the light's cosine where the light is behind the surface: a convex sphere shadows nothing else)."""
    origins, directions = camera.pixel_rays(pixels)
    centre = np.asarray(centre_mm, dtype=np.float64)
    offset = origins - centre
    b = np.einsum("...c,...c->...", directions, offset)
    disc = b**2 - (np.einsum("...c,...c->...", offset, offset) - radius_mm**2)
    hit = disc > 0
    t = -b - np.sqrt(np.where(hit, disc, 0.0))
    points = origins + t[..., None] * directions
    normals = (points - centre) / radius_mm
    to_light = np.asarray(light_mm, dtype=np.float64) - points
    distance2 = np.einsum("...c,...c->...", to_light, to_light)
    cosine = np.einsum("...c,...c->...", normals, to_light) / np.sqrt(distance2)
    lit = np.where(hit & (cosine > 0), cosine, 0.0)
    view = np.where(hit, -np.einsum("...c,...c->...", normals, directions), 0.0)
    return lit / (np.pi * distance2), lit, view


def channel_products(observed: np.ndarray, predicted: np.ndarray,
                     valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The least-squares ratios ``sum(o p) / sum(p^2)`` of an observed ``(H, W, C)`` image to the
    ``(H, W)`` prediction for intensity and gain 1, over the ``(H, W)`` bool ``valid`` pixels, per
    colour: ``(products (C,), relative RMS residuals (C,))``.

    Raises:
        ValueError: no valid pixel.
    """
    if not valid.any():
        raise ValueError("no pixel of the sphere is lit and seen well enough")
    prediction = predicted[valid]
    values = observed[valid]
    products = (values * prediction[:, None]).sum(axis=0) / float((prediction**2).sum())
    residual = values - products[None] * prediction[:, None]
    rms = np.sqrt(np.mean(residual**2, axis=0)) / np.maximum(np.mean(np.abs(values), axis=0), 1e-30)
    return products, rms


def split_products(products: np.ndarray, nominal_intensity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gains ``(C,)`` and intensities ``(K, C)`` from the ``(K, C)`` products of ``K`` modules in ``C``
    channels, with each channel's mean intensity over the modules at ``nominal_intensity`` ``(C,)``
    (module docstring)."""
    products = np.asarray(products, dtype=np.float64)
    gains = products.mean(axis=0) / np.asarray(nominal_intensity, dtype=np.float64)
    return gains, products / gains[None]
