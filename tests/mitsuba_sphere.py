"""Spheres rendered by Mitsuba 3 for ``polarface ior`` (docs/ior.md, "Experiments").

The sphere is Mitsuba's analytic ``sphere`` shape (hit points, normals and LED shadows from
``scene.ray_intersect`` / ``scene.ray_test``) with the ``pplastic`` BSDF (GGX specular with the full
Fresnel Mueller matrix plus the local Fresnel-transmission diffuse lobe), lit by the scene's LEDs
(unpolarized light through a linear polarizer along the camera x axis, radiant intensity 1e6) and seen
by the scene's pinhole camera; the machinery (pixel rays, BSDF evaluation, Stokes frames) is the one of
:mod:`mitsuba_capture` (docs/mitsuba_captures.md). The output is the camera-frame linear Stokes image,
so any analyzer model (:class:`polarface.optics.analyzer.AnalyzerModel`) and the 12-bit sensor of
:mod:`polarface.capture.sensor` can be applied afterwards (:func:`sensor_images`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from mitsuba_capture import _cast, _lobe_stokes, _mitsuba, _pplastic
from polarface.capture.sensor import SensorNoise, simulate_raw
from polarface.geometry.camera import PinholeCamera
from polarface.inverse.ior_scene import SphereScene
from polarface.optics.analyzer import AnalyzerModel

__all__ = ["LIGHT_INTENSITY", "perturb_scene", "render_mitsuba_sphere", "sensor_images"]

#: Radiant intensity of each LED (as :func:`polarface.inverse.ior_validation.render_sphere`).
LIGHT_INTENSITY = 1.0e6


def render_mitsuba_sphere(
    scene: SphereScene,
    eta: float,
    *,
    rho_sss_bar: float = 0.5,
    rho_s: float = 0.3,
    alpha_s: float = 0.2,
) -> np.ndarray:
    """Noise-free camera-frame linear Stokes ``(H, W, 3)`` float64 (s0, s1, s2) of the scene's sphere,
    zero off the sphere (the scene's camera, lights, centre and radius are the *true* geometry)."""
    mi = _mitsuba()
    pinhole = PinholeCamera(scene.K, scene.world_to_camera, scene.width, scene.height)
    mi_scene = mi.load_dict(
        {
            "type": "scene",
            "ball": {"type": "sphere", "center": [float(v) for v in scene.centre], "radius": scene.radius},
        }
    )
    lights = np.asarray(scene.lights, dtype=np.float64)
    hits = _cast(mi, mi_scene, pinhole, lights)
    bsdfs = (_pplastic(mi, eta, alpha_s, 1.0, 0.0), _pplastic(mi, eta, alpha_s, 0.0, 1.0))
    light_stokes = np.tile([1.0, 1.0, 0.0, 0.0], (len(lights), 1))  # polarized along camera x
    lobes = _lobe_stokes(mi, hits, hits.geometric_normal, pinhole, lights, bsdfs, light_stokes)
    distance2 = ((lights[None] - hits.position[:, None]) ** 2).sum(-1)
    weight = LIGHT_INTENSITY / distance2  # (N, K)
    stokes = rho_sss_bar * np.einsum("nk,nks->ns", weight, lobes[:, :, 0])
    stokes += rho_s * np.einsum("nk,nks->ns", weight, lobes[:, :, 1])
    image = np.zeros((scene.height * scene.width, 3))
    image[hits.pixel] = stokes[:, :3]
    return image.reshape(scene.height, scene.width, 3)


def sensor_images(
    stokes: np.ndarray, analyzer: AnalyzerModel | None = None, *, noise: bool = True, seed: int = 0
) -> dict[str, np.ndarray]:
    """``{"I0", "I45", "I90", "I135"}`` ``(H, W)`` float32 behind ``analyzer`` (ideal by default) of a
    Stokes image ``(H, W, 3)``: with ``noise``, the sensor's shot/read noise and 12-bit quantisation at
    an exposure putting the brightest analyzer pixel at 80 % of full well (as ``render_sphere``)."""
    analyzer = analyzer or AnalyzerModel()
    measured = np.clip(analyzer.measure(stokes), 0.0, None)  # (H, W, 4)
    exposure = 0.8 / max(float(measured.max()), 1e-12)
    sensor = SensorNoise(exposure=exposure)
    rng = np.random.default_rng(seed)
    out = {}
    for index, name in enumerate(("I0", "I45", "I90", "I135")):
        image = measured[..., index]
        if noise:
            raw = simulate_raw(image, sensor, seed=rng).astype(np.float64)
            image = raw / sensor.saturation_count / exposure
        out[name] = image.astype(np.float32)
    return out


def perturb_scene(
    scene: SphereScene,
    seed: int,
    *,
    light_mm: float = 2.0,
    focal_fraction: float = 0.002,
    principal_px: float = 1.0,
    sphere_mm: float = 0.5,
) -> SphereScene:
    """``scene`` as a real rig's calibration would give it: each light moved by ``light_mm`` and the
    sphere centre by ``sphere_mm`` in random directions, the focal lengths scaled by ``1 +
    focal_fraction`` and the principal point moved by ``principal_px`` in a random direction."""
    rng = np.random.default_rng(seed)

    def unit(count: int, dims: int) -> np.ndarray:
        vectors = rng.normal(size=(count, dims))
        return vectors / np.linalg.norm(vectors, axis=1, keepdims=True)

    K = scene.K.copy()
    K[0, 0] *= 1.0 + focal_fraction
    K[1, 1] *= 1.0 + focal_fraction
    K[:2, 2] += principal_px * unit(1, 2)[0]
    return dataclasses.replace(
        scene,
        K=K,
        lights=scene.lights + light_mm * unit(len(scene.lights), 3),
        centre=scene.centre + sphere_mm * unit(1, 3)[0],
    )
