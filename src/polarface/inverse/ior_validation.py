"""The paper's ten validation objects as rendered spheres (paper Table "Validation on refractive index
measurements", Sec. 6): the scene, polarface's own sphere renderer and the validation table of
``polarface ior --validate`` (docs/ior.md)."""

from __future__ import annotations

import numpy as np
import torch

from polarface.inverse.ior_scene import SphereScene, sphere_pixels

__all__ = ["PAPER_OBJECTS", "default_sphere_scene", "render_sphere", "validate_paper_objects"]


#: The ten objects of the paper's validation table: (name, measured eta_gt) (Ha et al. 2024, Sec. 6).
PAPER_OBJECTS: tuple[tuple[str, float], ...] = (
    ("red billiard", 1.485),
    ("green billiard", 1.469),
    ("blue billiard", 1.504),
    ("white billiard", 1.463),
    ("POM", 1.462),
    ("fake pearl", 2.295),
    ("yellow silicone", 1.303),
    ("pink silicone", 1.177),
    ("white silicone", 1.248),
    ("light green silicone", 1.343),
)


def default_sphere_scene(size: int = 256, radius: float = 40.0) -> SphereScene:
    """The paper rig's upper polarimetric camera and 8 LED modules looking at a sphere at 1 m."""
    from polarface.capture.rig import paper_rig

    rig = paper_rig(width=size, height=size)
    camera = rig.polarimetric_cameras()[0]
    return SphereScene(
        np.asarray(camera.K),
        np.asarray(camera.world_to_camera),
        size,
        size,
        np.array([0.0, 0.0, 1000.0]),
        radius,
        np.array([light.position_mm for light in rig.lights], dtype=np.float64),
    )


def render_sphere(
    scene: SphereScene,
    eta: float,
    *,
    rho_sss_bar: float = 0.5,
    rho_s: float = 0.3,
    alpha_s: float = 0.2,
    noise: bool = False,
    seed: int = 0,
) -> dict[str, np.ndarray]:
    """Analyzer images ``{"I0", "I45", "I90", "I135"}`` ``(H, W)`` float32 of a dielectric sphere under the
    scene's lights (radiant intensity 1e6, the rig's), with the full forward model
    (:func:`polarface.optics.render_polarimetric`); ``noise`` adds the rig's sensor shot/read noise
    and 12-bit quantisation at an exposure putting the brightest pixel at 80 % of full well."""
    from polarface.capture.sensor import SensorNoise, simulate_raw
    from polarface.optics.image_formation import render_polarimetric

    mask, position, normal, centre = sphere_pixels(scene)
    up = -scene.world_to_camera[1, :3]
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64))  # noqa: E731
    images = render_polarimetric(
        t(normal[mask]),
        t(position[mask]),
        t(centre),
        t(up),
        t(scene.lights),
        torch.full((len(scene.lights), 1), 1.0e6, dtype=torch.float64),
        eta,
        alpha_s,
        0.6,
        rho_s,
        0.1,
        rho_sss_bar,
    )
    out = {}
    for name, values in (("I0", images.i0), ("I45", images.i45), ("I90", images.i90), ("I135", images.i135)):
        image = np.zeros((scene.height, scene.width), np.float64)
        image[mask] = values[:, 0].numpy()
        out[name] = image
    if noise:
        exposure = 0.8 / max(float(out["I0"].max()), 1e-12)
        sensor = SensorNoise(exposure=exposure)
        rng = np.random.default_rng(seed)
        for name in out:
            raw = simulate_raw(out[name], sensor, seed=rng).astype(np.float64)
            white = (2**sensor.bit_depth - 1) if sensor.white_level is None else sensor.white_level
            out[name] = (raw - sensor.black_level) / (white - sensor.black_level) / exposure
    return {k: v.astype(np.float32) for k, v in out.items()}


def validate_paper_objects(
    noise: bool = False, size: int = 256, seed: int = 0
) -> list[dict[str, float | str]]:
    """Render a sphere for each of :data:`PAPER_OBJECTS` and estimate its eta: list of table rows
    (the scene is exact here, so the sphere is not refined from its silhouette)."""
    from polarface.inverse.ior import estimate_ior

    scene = default_sphere_scene(size)
    rows = []
    for index, (name, eta_gt) in enumerate(PAPER_OBJECTS):
        images = render_sphere(scene, eta_gt, noise=noise, seed=seed + index)
        result = estimate_ior(images, scene, refine=False)
        rows.append(
            {"object": name, "eta_gt": eta_gt, "eta": result.eta, "abs_error": abs(result.eta - eta_gt)}
        )
    return rows
