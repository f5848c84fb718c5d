"""Simulated frames of a polarimetric calibration target (for the tests and
benchmarks/bench_calibrate_polarization.py).

The ground truth is independent of the estimator under test: each frame is the forward model of
:class:`polarface.optics.analyzer.AnalyzerModel` (fully polarized light at the polarizer angle) times
per-analyzer gains, sampled by :func:`polarface.capture.sensor.mosaic` and digitised with shot, read and
quantisation noise by :func:`polarface.capture.sensor.simulate_raw`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from polarface.capture.rig import Camera
from polarface.capture.sensor import SensorNoise, mosaic, simulate_raw
from polarface.optics.analyzer import AnalyzerModel

K_SMALL = [[200.0, 0.0, 64.0], [0.0, 200.0, 64.0], [0.0, 0.0, 1.0]]


def target_camera(sensor: str = "mono-polarization", size: int = 128, **fields) -> Camera:
    """A polarization camera of ``size x size`` pixels (extra ``fields`` as in rig.json)."""
    return Camera(id="cam", role="polarimetric", sensor=sensor, width=size, height=size, K=K_SMALL, **fields)


def target_frames(
    camera: Camera,
    models: Sequence[AnalyzerModel],
    polarizer_deg: Sequence[float],
    *,
    gains: Sequence[Sequence[float]] | None = None,
    radiance: float = 0.8,
    frame_scales: Sequence[float] | None = None,
    noise: SensorNoise | None = None,
    seed: int = 0,
    noiseless: bool = False,
    shading: np.ndarray | None = None,
) -> list[np.ndarray]:
    """Raw uint16 frames of ``camera`` seeing a uniform fully polarized target at each polarizer angle.

    Args:
        camera: its sensor, size and pattern phase are used (black/white levels come from ``noise``).
        models: one model (mono) or three (R, G, B).
        polarizer_deg: polarizer angles, degrees from image +x.
        gains: per model, four analyzer gains (default 1).
        radiance: signal of the target before the analyzers, 1 = full well.
        frame_scales: per-frame source intensity factors (default 1).
        noise: the sensor model (default :class:`SensorNoise()`: 12 bit, black 0).
        seed: noise seed.
        noiseless: quantisation only.
        shading: optional ``(H, W)`` illumination factor (vignetting), multiplies every analyzer.
    """
    rng = np.random.default_rng(seed)
    gains = gains or [np.ones(4)] * len(models)
    scales = frame_scales or [1.0] * len(polarizer_deg)
    size = (camera.height, camera.width)
    field = np.ones(size) if shading is None else shading
    frames = []
    for angle, scale in zip(polarizer_deg, scales, strict=True):
        two = np.deg2rad(2.0 * angle)
        stokes = radiance * scale * np.array([1.0, np.cos(two), np.sin(two)])
        per_model = [
            np.maximum(m.measure(stokes) * np.asarray(g), 0.0) for m, g in zip(models, gains, strict=True)
        ]
        if camera.sensor == "mono-polarization":
            images = [field * per_model[0][k] for k in range(4)]
        else:
            images = [np.stack([field * per_model[c][k] for c in range(3)], -1) for k in range(4)]
        signal = mosaic(*images, sensor=camera.sensor, phase=camera.pattern_phase)
        frames.append(simulate_raw(signal, noise, seed=rng, noiseless=noiseless))
    return frames
