"""Refractive index of a sphere from one capture folder: the ``polarface ior`` job.

The folder holds ``I0.exr, I45.exr, I90.exr, I135.exr`` (float32 linear; one channel ``Y`` or R, G, B)
and ``scene.json`` (camera, lights and sphere in mm, optional ``polarizer`` calibration; schema in
docs/ior.md and :meth:`polarface.inverse.ior_scene.SphereScene.from_dict`). The estimator is
:func:`polarface.inverse.ior.estimate_ior` (analyzer calibration applied, sphere refined from its
silhouette, jackknife uncertainty, shading check of the lights).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from polarface.inverse.ior import IorResult, estimate_ior
from polarface.inverse.ior_scene import SphereScene
from polarface.inverse.ior_validation import validate_paper_objects
from polarface.io import read_exr, read_json_object

__all__ = ["ANALYZER_IMAGE_NAMES", "estimate_ior_from_folder", "read_analyzer_image", "validate_ior"]

#: Analyzer images of an IOR capture folder (file stems of the EXRs).
ANALYZER_IMAGE_NAMES = ("I0", "I45", "I90", "I135")


def read_analyzer_image(path: str | os.PathLike[str]) -> np.ndarray:
    """One analyzer EXR as float64: ``(H, W)`` from a ``Y`` channel, else ``(H, W, C)`` (R, G, B, or
    every channel in name order)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image '{path}' does not exist")
    channels = read_exr(path)
    if "Y" in channels:
        return np.asarray(channels["Y"], dtype=np.float64)
    names = [n for n in ("R", "G", "B") if n in channels]
    if not names:
        names = sorted(channels)
    return np.stack([np.asarray(channels[n], dtype=np.float64) for n in names], axis=-1)


def estimate_ior_from_folder(
    folder: str | os.PathLike[str], eta_range: tuple[float, float] = (1.05, 3.0), refine: bool = True
) -> IorResult:
    """Read the capture folder (module docstring) and estimate the sphere's refractive index
    (``refine``: refit the sphere's centre to its silhouette).

    Raises:
        FileNotFoundError: the folder, ``scene.json`` or an analyzer image is missing.
        ValueError: invalid JSON or scene (:meth:`SphereScene.from_dict`), images the estimator rejects,
            or an estimate on a bound of ``eta_range`` (``IorResult.at_bound``: not a measurement, so it
            is an error rather than a number printed with exit status 0).
    """
    lo, hi = (float(v) for v in eta_range)
    if not 1.0 < lo < hi < float("inf"):
        raise ValueError(f"argument 'eta_range' must satisfy 1 < lo < hi (finite); got {tuple(eta_range)}")
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"folder '{folder}' does not exist")
    scene_path = folder / "scene.json"
    if not scene_path.is_file():
        raise FileNotFoundError(f"'{scene_path}' does not exist")
    payload = read_json_object(scene_path)
    try:
        scene = SphereScene.from_dict(payload)
    except ValueError as exc:
        raise ValueError(f"'{scene_path}': {exc}") from exc
    images = {name: read_analyzer_image(folder / f"{name}.exr") for name in ANALYZER_IMAGE_NAMES}
    result = estimate_ior(images, scene, eta_range=tuple(eta_range), refine=refine)
    if result.at_bound:
        raise ValueError(
            f"eta estimate {result.eta:.4f} lies on the bound of argument 'eta_range' "
            f"[{eta_range[0]}, {eta_range[1]}]: the best fit is at or beyond the bound, so it is not a "
            "measurement (widen the range, or check scene.json and the images)"
        )
    return result


def validate_ior(noise: bool = False) -> dict:
    """Render the paper's ten objects as spheres and estimate each one's eta.

    Returns:
        ``{"rows": [...], "mean_abs_error": float, "noise": bool}``, rows as returned by
        :func:`polarface.inverse.ior_validation.validate_paper_objects`.
    """
    rows = validate_paper_objects(noise=noise)
    return {
        "rows": rows,
        "mean_abs_error": float(np.mean([r["abs_error"] for r in rows])),
        "noise": noise,
    }
