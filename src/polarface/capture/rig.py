"""The rig description ``rig.json``: cameras, polarized light modules and spectral calibration.

Validated with pydantic v2: a bad file raises ``ValueError`` whose message names the file and the
field. Units: positions in mm, angles in radians, wavelengths in nm. Camera poses are 4x4
``world_to_camera`` matrices in the OpenCV convention (camera x right, y down, z forward).

Six spectral channels (paper Sec. 4.1): each polarimetric camera sits behind one eye of Dolby 3D
glasses that splits its R, G, B into an upper and a lower half band. Channel order (shared with
``polarface.skin.spectral.CHANNEL_NAMES``): camera 1 (upper halves) R, G, B, then camera 2 (lower
halves) R, G, B, i.e. ``("red_upper", "green_upper", "blue_upper", "red_lower", "green_lower",
"blue_lower")``: camera 1 maps R, G, B to channels 0, 1, 2 and camera 2 to 3, 4, 5.

This module holds the rig itself (:class:`Rig`: reading and writing ``rig.json``, stereo pairs, what
differs between two rigs) and :func:`paper_rig`; its parts are in :mod:`polarface.capture.rig_components`
(cameras, light modules) and :mod:`polarface.capture.rig_spectral` (spectral calibration), and are
importable from here too.
"""

from __future__ import annotations

import json
import math
from typing import Literal

import numpy as np
from pydantic import Field, ValidationError, model_validator

from polarface.capture.rig_components import (
    AnalyzerCalibration,
    Camera,
    LightModule,
    StrictModel,
    one_line_errors,
)
from polarface.capture.rig_spectral import SIX_CHANNEL_NAMES, SpectralModel
from polarface.geometry.camera import look_at
from polarface.io.atomic import write_json_atomic
from polarface.io.storage import PathOrUrl, StoragePath, storage_path

__all__ = [
    "SIX_CHANNEL_NAMES",
    "AnalyzerCalibration",
    "Camera",
    "LightModule",
    "Rig",
    "SpectralModel",
    "paper_rig",
]


class Rig(StrictModel):
    """The whole rig: ``rig.json``.

    Attributes:
        name: free text.
        units: always ``"mm"``.
        cameras: cameras with unique ids.
        lights: polarized light modules.
        spectral: six-channel spectral calibration, or None.
        stereo_pairs: the stereo modules as ``[camera_id, camera_id]`` pairs; empty: cameras of role
            ``stereo`` named ``<module>_a`` / ``<module>_b`` are paired by name.
    """

    name: str = "rig"
    units: Literal["mm"] = "mm"
    cameras: list[Camera]
    lights: list[LightModule] = Field(default_factory=list)
    spectral: SpectralModel | None = None
    stereo_pairs: list[tuple[str, str]] = Field(default_factory=list)

    @model_validator(mode="after")
    def _unique(self) -> Rig:
        for kind, items in (("camera", self.cameras), ("light", self.lights)):
            ids = [item.id for item in items]
            duplicates = sorted({i for i in ids if ids.count(i) > 1})
            if duplicates:
                raise ValueError(f"{kind} ids must be unique; duplicated: {duplicates}")
        ids = {camera.id for camera in self.cameras}
        for first, second in self.stereo_pairs:
            unknown = sorted({first, second} - ids)
            if unknown or first == second:
                raise ValueError(
                    f"stereo_pairs: pair [{first!r}, {second!r}] must name two different cameras of the rig"
                    + (f" (unknown: {unknown})" if unknown else "")
                )
        return self

    def stereo_camera_pairs(self) -> list[tuple[Camera, Camera]]:
        """The stereo modules' camera pairs (``stereo_pairs``, else ``<module>_a`` / ``_b`` by name).

        Raises:
            ValueError: the rig has no stereo pair (the message points to known-geometry mode), or a
                stereo camera has no partner.
        """
        if self.stereo_pairs:
            return [(self.camera(a), self.camera(b)) for a, b in self.stereo_pairs]
        stereo = {c.id: c for c in self.cameras if c.role == "stereo"}
        pairs = [
            (camera, stereo[camera_id[:-2] + "_b"])
            for camera_id, camera in stereo.items()
            if camera_id.endswith("_a") and camera_id[:-2] + "_b" in stereo
        ]
        paired = {c.id for pair in pairs for c in pair}
        if stereo.keys() - paired:
            raise ValueError(
                f"rig: stereo camera(s) {sorted(stereo.keys() - paired)} have no partner; name them "
                "<module>_a / <module>_b or list the rig's 'stereo_pairs'"
            )
        if not pairs:
            raise ValueError(
                "rig: no stereo camera pair, so geometry cannot be reconstructed from the capture; give "
                "a mesh and poses instead ('--mesh MESH --poses POSES')"
            )
        return pairs

    def camera(self, camera_id: str) -> Camera:
        """The camera named ``camera_id``; ``ValueError`` listing the rig's cameras otherwise."""
        for camera in self.cameras:
            if camera.id == camera_id:
                return camera
        raise ValueError(f"camera '{camera_id}' is not in the rig (cameras: {[c.id for c in self.cameras]})")

    def polarimetric_cameras(self) -> list[Camera]:
        """Cameras with role ``polarimetric``, in file order."""
        return [c for c in self.cameras if c.role == "polarimetric"]

    def geometry_differences(self, other: Rig, atol: float = 1e-6) -> list[str]:
        """What differs between this rig and ``other`` in what the reconstruction relies on: the cameras
        (ids, roles, sensors, sizes, ``K``, distortion, ``world_to_camera``, channel gains), the lights
        (positions, polarizers, Stokes vectors, radiant intensities) and the spectral calibration;
        exposure and black/white levels may differ between captures. One entry per difference, naming the
        field (e.g. ``cameras[pol_upper].K``); empty when the rigs agree within ``atol``."""

        def close(a, b) -> bool:
            a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
            return a.shape == b.shape and bool(np.allclose(a, b, rtol=0.0, atol=atol))

        differences = []
        mine, theirs = {c.id: c for c in self.cameras}, {c.id: c for c in other.cameras}
        if mine.keys() != theirs.keys():
            differences.append(f"cameras: {sorted(mine)} vs {sorted(theirs)}")
        for camera_id in sorted(mine.keys() & theirs.keys()):
            a, b = mine[camera_id], theirs[camera_id]
            for field in ("role", "sensor", "width", "height", "colour_channels", "channel_gains"):
                if getattr(a, field) != getattr(b, field):
                    differences.append(f"cameras[{camera_id}].{field}")
            for field in ("K", "distortion", "world_to_camera"):
                if not close(getattr(a, field), getattr(b, field)):
                    differences.append(f"cameras[{camera_id}].{field}")
        if len(self.lights) != len(other.lights):
            differences.append(f"lights: {len(self.lights)} vs {len(other.lights)} modules")
        for a, b in zip(self.lights, other.lights, strict=False):
            for field in ("position_mm", "polarizer_angle", "stokes", "radiant_intensity"):
                if not close(getattr(a, field), getattr(b, field)):
                    differences.append(f"lights[{a.id}].{field}")
        if (self.spectral is None) != (other.spectral is None) or (
            self.spectral is not None and self.spectral.model_dump() != other.spectral.model_dump()
        ):
            differences.append("spectral")
        return differences

    @classmethod
    def load(cls, path: PathOrUrl) -> Rig:
        """Read and validate a ``rig.json`` (a local path or a URL).

        Raises:
            FileNotFoundError: if the file does not exist.
            ValueError: on invalid JSON or schema errors (message names the file and the fields).
        """
        path = storage_path(path)
        if not path.is_file():
            raise FileNotFoundError(f"rig file '{path}' does not exist")
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"rig file '{path}' is not valid JSON: {exc}") from exc
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise ValueError(f"rig file '{path}' is invalid: {one_line_errors(exc)}") from exc

    def save(self, path: PathOrUrl) -> StoragePath:
        """Write ``rig.json`` atomically; returns the path."""
        return write_json_atomic(path, self.model_dump(mode="json"))


def _default_spectral() -> SpectralModel | None:
    try:
        from polarface.skin.spectral import default_spectral_calibration
    except ImportError:
        return None
    return SpectralModel.from_calibration(default_spectral_calibration())


def paper_rig(scale: float = 1.0, width: int = 2448, height: int = 2048) -> Rig:
    """The rig of Ha et al. 2024 (Sec. 4.1), in a world frame centred on the polarimetric module.

    World frame: origin between the two polarimetric cameras, x right, y down, z towards the face,
    which is centred at ``(0, 0, 1000 * scale)`` mm. Components:

    * ``pol_upper`` / ``pol_lower``: IMX250MYR colour-polarization cameras 60 mm apart, verged on
      the face centre; focal length framing a 250 mm wide field at 1 m (``f = 4 * width`` px);
      12-bit, black level 0. ``pol_upper`` (the paper's left camera, upper half bands) maps R, G, B to
      channels 0, 1, 2, ``pol_lower`` to 3, 4, 5 (see the module docstring).
    * 8 LED modules of 5 LEDs, each one point light, on a 100 mm radius circle around the lens axis
      (5.72 deg at 1 m), polarizer axis along image x: incident Stokes [1, 1, 0, 0]; radiant intensity
      1e6 per channel, so the irradiance at the face is about 1 (``I_L / Gamma^2``).
    * Four RGB stereo pairs (``stereo{k}_a`` / ``_b``, 100 mm baseline) at (+-250, +-200) mm.

    Args:
        scale: multiplies every distance (face distance, baselines, light radius).
        width, height: image size; K is scaled with ``width`` (``cx, cy`` at the centre). Smaller
            sizes give test/demo presets; both must be multiples of 4.

    Returns:
        The :class:`Rig`; ``spectral`` is the default calibration of
        :mod:`polarface.skin.spectral` when that module is available, else None.
    """
    if not (scale > 0 and math.isfinite(scale)):
        raise ValueError(f"argument 'scale' must be > 0; got {scale}")
    if width % 4 or height % 4 or width <= 0 or height <= 0:
        raise ValueError(
            f"arguments 'width' and 'height' must be positive multiples of 4; got {width}x{height}"
        )
    distance = 1000.0 * scale
    focal = 4.0 * width
    K = [[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]]
    target = np.array([0.0, 0.0, distance])
    world_up = (0.0, -1.0, 0.0)  # the rig world has y down
    cameras = []
    for cam_id, x_mm, channels in (
        ("pol_upper", -30.0, {"R": 0, "G": 1, "B": 2}),
        ("pol_lower", 30.0, {"R": 3, "G": 4, "B": 5}),
    ):
        cameras.append(
            Camera(
                id=cam_id,
                role="polarimetric",
                sensor="color-polarization",
                width=width,
                height=height,
                K=K,
                world_to_camera=look_at(np.array([x_mm * scale, 0.0, 0.0]), target, up=world_up).tolist(),
                bit_depth=12,
                colour_channels=channels,
            )
        )
    for k, (sx, sy) in enumerate(((-1, -1), (1, -1), (-1, 1), (1, 1))):
        for suffix, dx in (("a", -50.0), ("b", 50.0)):
            centre = np.array([(250.0 * sx + dx) * scale, 200.0 * sy * scale, 0.0])
            cameras.append(
                Camera(
                    id=f"stereo{k}_{suffix}",
                    role="stereo",
                    sensor="rgb",
                    width=width,
                    height=height,
                    K=K,
                    world_to_camera=look_at(centre, target, up=world_up).tolist(),
                    bit_depth=12,
                )
            )
    lights = []
    for k in range(8):
        angle = 2.0 * math.pi * k / 8
        position = (100.0 * scale * math.cos(angle), 100.0 * scale * math.sin(angle), 0.0)
        lights.append(
            LightModule(
                id=f"led{k}",
                position_mm=position,
                polarizer_angle=0.0,
                stokes=(1.0, 1.0, 0.0, 0.0),
                radiant_intensity=1.0e6 * scale**2,
            )
        )
    pairs = [(f"stereo{k}_a", f"stereo{k}_b") for k in range(4)]
    return Rig(
        name="ha2024-paper-rig", cameras=cameras, lights=lights, spectral=_default_spectral(),
        stereo_pairs=pairs,
    )
