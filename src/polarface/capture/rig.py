"""The rig description ``rig.json``: cameras, polarized light modules and spectral calibration.

Validated with pydantic v2: a bad file raises ``ValueError`` whose message names the file and the
field. Units: positions in mm, angles in radians, wavelengths in nm. Camera poses are 4x4
``world_to_camera`` matrices in the OpenCV convention (camera x right, y down, z forward).

Six spectral channels (paper Sec. 4.1): each polarimetric camera sits behind one eye of Dolby 3D
glasses that splits its R, G, B into an upper and a lower half band. Channel order (shared with
``polarface.skin.spectral.CHANNEL_NAMES``): camera 1 (upper halves) R, G, B, then camera 2 (lower
halves) R, G, B, i.e. ``("red_upper", "green_upper", "blue_upper", "red_lower", "green_lower",
"blue_lower")``: camera 1 maps R, G, B to channels 0, 1, 2 and camera 2 to 3, 4, 5.
"""

from __future__ import annotations

import json
import math
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from polarface.geometry.camera import PinholeCamera, look_at
from polarface.io.atomic import write_json_atomic
from polarface.io.storage import PathOrUrl, StoragePath, storage_path
from polarface.optics.analyzer import IDEAL_ANALYZER_ANGLES_DEG, AnalyzerModel

__all__ = [
    "SIX_CHANNEL_NAMES",
    "AnalyzerCalibration",
    "Camera",
    "LightModule",
    "Rig",
    "SpectralModel",
    "paper_rig",
]

#: Default names of the six spectral channels, in channel order (as polarface.skin.spectral).
SIX_CHANNEL_NAMES = ("red_upper", "green_upper", "blue_upper", "red_lower", "green_lower", "blue_lower")


def _finite_matrix(value: Any, rows: int, cols: int, name: str) -> list[list[float]]:
    array = np.asarray(value, dtype=np.float64)
    if array.shape != (rows, cols):
        raise ValueError(f"{name} must be a {rows}x{cols} matrix; got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    return array.tolist()


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


def _field_path(loc: tuple[Any, ...]) -> str:
    """``("lights", 3, "position_mm", 0)`` -> ``lights[3].position_mm[0]``."""
    path = ""
    for part in loc:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else str(part))
    return path or "rig"


def _one_line(exc: ValidationError) -> str:
    """Every error of a pydantic ``ValidationError`` on one line: ``field.path: message; ...``."""
    parts = (f"{_field_path(tuple(e['loc']))}: {' '.join(str(e['msg']).split())}" for e in exc.errors())
    return "; ".join(parts)


class SpectralModel(_Model):
    """Spectral calibration: six camera channel responses and the LED spectrum on one grid.

    Attributes:
        wavelengths_nm: ``(L,)`` increasing wavelengths in nm.
        channel_names: the six channel names, in channel order.
        channel_responses: ``(6, L)`` relative response of each channel (camera x Dolby filter).
        led_spd: ``(L,)`` relative spectral power of the LEDs.
    """

    wavelengths_nm: list[float]
    channel_names: list[str] = Field(default_factory=lambda: list(SIX_CHANNEL_NAMES))
    channel_responses: list[list[float]]
    led_spd: list[float]

    @model_validator(mode="after")
    def _shapes(self) -> SpectralModel:
        wavelengths = np.asarray(self.wavelengths_nm, dtype=np.float64)
        if wavelengths.ndim != 1 or wavelengths.size < 2 or not np.all(np.diff(wavelengths) > 0):
            raise ValueError("wavelengths_nm must be at least two strictly increasing values (nm)")
        if len(self.channel_names) != 6 or len(set(self.channel_names)) != 6:
            raise ValueError(f"channel_names must be 6 distinct names; got {self.channel_names}")
        responses = np.asarray(self.channel_responses, dtype=np.float64)
        if responses.shape != (6, wavelengths.size):
            raise ValueError(f"channel_responses must be (6, {wavelengths.size}); got {responses.shape}")
        spd = np.asarray(self.led_spd, dtype=np.float64)
        if spd.shape != wavelengths.shape:
            raise ValueError(f"led_spd must have {wavelengths.size} values; got {spd.shape}")
        for name, array in (
            ("channel_responses", responses),
            ("led_spd", spd),
            ("wavelengths_nm", wavelengths),
        ):
            if not np.isfinite(array).all() or (array < 0).any():
                raise ValueError(f"{name} must be finite and non-negative")
        return self

    def to_calibration(self) -> Any:
        """``polarface.skin.spectral.SpectralCalibration`` built from these lists (lazy import)."""
        from polarface.skin.spectral import SpectralCalibration

        return SpectralCalibration.from_dict(self.model_dump())

    @classmethod
    def from_calibration(cls, calibration: Any) -> SpectralModel:
        """Build from a ``SpectralCalibration`` (its ``to_dict()`` keys of the same names)."""
        data = calibration.to_dict()
        return cls.model_validate({k: _plain(data[k]) for k in cls.model_fields if k in data})


def _plain(value: Any) -> Any:
    return np.asarray(value).tolist() if hasattr(value, "__array__") or hasattr(value, "tolist") else value


class AnalyzerCalibration(_Model):
    """The measured analyzers of a polarization camera (or of one colour channel of it).

    Absent from ``rig.json`` means ideal (infinite extinction ratio, 0/45/90/135 deg). Written by
    ``polarface calibrate-polarization`` with its one-sigma uncertainties.

    Attributes:
        extinction_ratio: ``k1 / k2`` of the micro-polarizers (> 1); None = infinite (ideal).
        analyzer_angles_deg: orientations of the analyzers polarface calls 0, 45, 90, 135 deg, degrees
            from image +x, counter-clockwise as seen by the camera (``docs/conventions.md``).
        extinction_ratio_std, analyzer_angles_std_deg: one-sigma uncertainties of the calibration.
    """

    extinction_ratio: float | None = Field(default=None, gt=1)
    analyzer_angles_deg: tuple[float, float, float, float] = IDEAL_ANALYZER_ANGLES_DEG
    extinction_ratio_std: float | None = Field(default=None, ge=0)
    analyzer_angles_std_deg: tuple[float, float, float, float] | None = None

    @model_validator(mode="after")
    def _check_model(self) -> AnalyzerCalibration:
        self.model()  # raises ValueError for angles out of order
        return self

    def model(self) -> AnalyzerModel:
        """This calibration as an :class:`polarface.optics.analyzer.AnalyzerModel`."""
        ratio = math.inf if self.extinction_ratio is None else self.extinction_ratio
        return AnalyzerModel(ratio, self.analyzer_angles_deg)


class Camera(_Model):
    """One camera of the rig.

    Attributes:
        id: unique name (used for raw folders and store arrays).
        role: ``polarimetric`` (appearance) or ``stereo`` (geometry).
        sensor: ``color-polarization`` (IMX250MYR), ``mono-polarization`` (IMX250MZR) or ``rgb``.
        width, height: image size in pixels.
        K: 3x3 intrinsic matrix (pixels).
        distortion: OpenCV distortion coefficients (k1, k2, p1, p2[, k3, ...]); empty = none.
        world_to_camera: 4x4 rigid transform, OpenCV camera convention, translation in mm.
        black_level, white_level: raw counts of black and of saturation.
        bit_depth: ADC bits (raw values lie in [0, 2**bit_depth - 1]).
        exposure: relative exposure (time x gain) divided out by demosaicing.
        pattern_phase: (row, col) phase of the mosaic (cropped/flipped readouts).
        colour_channels: for colour cameras, the spectral channel index (0..5) of R, G, B, e.g.
            ``{"R": 0, "G": 1, "B": 2}``; empty for mono cameras or when unused.
        analyzer: the measured micro-polarizers (polarization sensors only): one
            :class:`AnalyzerCalibration` for every colour, or one per colour ``{"R": ..., "G": ...,
            "B": ...}`` (colour cameras; a colour left out is ideal); None = ideal analyzers.
    """

    id: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")
    role: Literal["polarimetric", "stereo"]
    sensor: Literal["color-polarization", "mono-polarization", "rgb"]
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    K: list[list[float]]
    distortion: list[float] = Field(default_factory=list, max_length=14)
    world_to_camera: list[list[float]] = Field(default_factory=lambda: np.eye(4).tolist())
    black_level: float = Field(default=0.0, ge=0)
    white_level: float | None = None
    bit_depth: int = Field(default=12, ge=1, le=16)
    exposure: float = Field(default=1.0, gt=0)
    pattern_phase: tuple[int, int] = (0, 0)
    colour_channels: dict[Literal["R", "G", "B"], int] = Field(default_factory=dict)
    analyzer: AnalyzerCalibration | dict[Literal["R", "G", "B"], AnalyzerCalibration] | None = None

    @field_validator("K")
    @classmethod
    def _check_k(cls, value: Any) -> list[list[float]]:
        matrix = _finite_matrix(value, 3, 3, "K")
        if matrix[0][0] <= 0 or matrix[1][1] <= 0 or matrix[2] != [0.0, 0.0, 1.0]:
            raise ValueError("K must have positive focal lengths and last row [0, 0, 1]")
        return matrix

    @field_validator("world_to_camera")
    @classmethod
    def _check_pose(cls, value: Any) -> list[list[float]]:
        matrix = np.asarray(_finite_matrix(value, 4, 4, "world_to_camera"))
        rotation = matrix[:3, :3]
        if not np.allclose(matrix[3], [0, 0, 0, 1]) or not np.allclose(
            rotation @ rotation.T, np.eye(3), atol=1e-6
        ):
            raise ValueError("world_to_camera must be rigid: orthonormal rotation, last row [0, 0, 0, 1]")
        if np.linalg.det(rotation) < 0:
            raise ValueError("world_to_camera rotation must be proper (det +1)")
        return matrix.tolist()

    @field_validator("distortion")
    @classmethod
    def _check_distortion(cls, value: list[float]) -> list[float]:
        if len(value) not in (0, 4, 5, 8, 12, 14) or not all(math.isfinite(v) for v in value):
            raise ValueError("distortion must hold 0, 4, 5, 8, 12 or 14 finite OpenCV coefficients")
        return value

    @field_validator("analyzer", mode="before")
    @classmethod
    def _check_analyzer(cls, value: Any) -> Any:
        """One calibration, or one per colour when every key is R, G or B (clear one-line errors)."""
        if value is None or isinstance(value, AnalyzerCalibration):
            return value
        if not isinstance(value, dict):
            raise ValueError("must be an object {extinction_ratio, analyzer_angles_deg} or {R, G, B: ...}")
        if value and set(value) <= {"R", "G", "B"}:
            per_colour = {}
            for colour, entry in value.items():
                try:
                    per_colour[colour] = AnalyzerCalibration.model_validate(entry)
                except ValidationError as exc:
                    raise ValueError(f"{colour}: {_one_line(exc)}") from None
            return per_colour
        try:
            return AnalyzerCalibration.model_validate(value)
        except ValidationError as exc:
            raise ValueError(_one_line(exc)) from None

    @field_validator("colour_channels")
    @classmethod
    def _check_channels(cls, value: dict[str, int]) -> dict[str, int]:
        if any(not 0 <= v < 6 for v in value.values()):
            raise ValueError(f"colour_channels indices must lie in 0..5; got {value}")
        return value

    @model_validator(mode="after")
    def _check_levels(self) -> Camera:
        white = self.saturation_level
        if not self.black_level < white <= 2**self.bit_depth - 1:
            raise ValueError(
                f"levels must satisfy black_level ({self.black_level}) < white_level ({white}) <= "
                f"2**bit_depth - 1 ({2**self.bit_depth - 1})"
            )
        if self.sensor == "mono-polarization" and self.colour_channels:
            raise ValueError("colour_channels must be empty for a mono-polarization camera")
        if self.analyzer is not None and self.sensor == "rgb":
            raise ValueError("analyzer is only allowed for a polarization sensor; this camera is 'rgb'")
        if isinstance(self.analyzer, dict) and self.sensor != "color-polarization":
            raise ValueError("a per-colour analyzer {R, G, B} needs a color-polarization sensor")
        period = {"mono-polarization": 2, "color-polarization": 4}.get(self.sensor)
        if period is not None and not all(0 <= p < period for p in self.pattern_phase):
            raise ValueError(
                f"pattern_phase must lie in 0..{period - 1} for a {self.sensor} camera; "
                f"got {self.pattern_phase}"
            )
        return self

    @property
    def saturation_level(self) -> float:
        """White level in counts (``2**bit_depth - 1`` when not given)."""
        return float(self.white_level if self.white_level is not None else 2**self.bit_depth - 1)

    @property
    def intrinsics(self) -> np.ndarray:
        """K as a float64 ``(3, 3)`` array."""
        return np.asarray(self.K, dtype=np.float64)

    @property
    def pose(self) -> np.ndarray:
        """world_to_camera as a float64 ``(4, 4)`` array."""
        return np.asarray(self.world_to_camera, dtype=np.float64)

    @property
    def centre_mm(self) -> np.ndarray:
        """Camera centre in world coordinates, mm, ``(3,)``."""
        pose = self.pose
        return -pose[:3, :3].T @ pose[:3, 3]

    def analyzer_model(self, colour: str | None = None) -> AnalyzerModel:
        """The analyzers of colour ``colour`` (``"R"``, ``"G"``, ``"B"``; None for a mono sensor or a
        camera-wide calibration) as an :class:`polarface.optics.analyzer.AnalyzerModel`; ideal when
        ``rig.json`` gives none."""
        if self.analyzer is None:
            return AnalyzerModel()
        if isinstance(self.analyzer, AnalyzerCalibration):
            return self.analyzer.model()
        if colour not in ("R", "G", "B"):
            raise ValueError(
                f"camera {self.id!r} has per-colour analyzers; colour must be R, G or B; got {colour!r}"
            )
        calibration = self.analyzer.get(colour)
        return AnalyzerModel() if calibration is None else calibration.model()

    def pinhole(self) -> PinholeCamera:
        """This camera as a :class:`polarface.geometry.camera.PinholeCamera` (K, pose, size, distortion)."""
        return PinholeCamera.from_dict(self.model_dump())


class LightModule(_Model):
    """One polarized LED module, treated as a point light.

    Attributes:
        id: unique name.
        position_mm: ``[x, y, z]`` in world coordinates, mm.
        polarizer_angle: transmission axis of the linear polarizer, radians, measured in the
            reference camera's image plane from image +x (so 0 gives Stokes [1, 1, 0, 0]).
        stokes: normalised incident Stokes vector ``[1, s1, s2, s3]`` in the camera frame.
        radiant_intensity: radiant intensity ``I_L`` per spectral channel (6 values) or one value
            for all, arbitrary radiometric unit per steradian.
    """

    id: str = Field(min_length=1)
    position_mm: tuple[float, float, float]
    polarizer_angle: float = 0.0
    stokes: tuple[float, float, float, float] = (1.0, 1.0, 0.0, 0.0)
    radiant_intensity: float | list[float] = 1.0e6

    @field_validator("stokes")
    @classmethod
    def _check_stokes(cls, value: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
        if value[0] <= 0 or math.hypot(value[1], value[2], value[3]) > value[0] * (1 + 1e-9):
            raise ValueError(f"stokes must be physical (s0 > 0, |s1,s2,s3| <= s0); got {value}")
        return value

    @field_validator("radiant_intensity")
    @classmethod
    def _check_intensity(cls, value: float | list[float]) -> float | list[float]:
        values = [value] if isinstance(value, float | int) else value
        if (not isinstance(value, float | int) and len(values) != 6) or any(
            not math.isfinite(v) or v < 0 for v in values
        ):
            raise ValueError("radiant_intensity must be one or six finite non-negative values")
        return value


class Rig(_Model):
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
        (ids, roles, sensors, sizes, ``K``, distortion, ``world_to_camera``), the lights (positions,
        polarizers, Stokes vectors, radiant intensities) and the spectral calibration; exposure and
        black/white levels may differ between captures. One entry per difference, naming the field
        (e.g. ``cameras[pol_upper].K``); empty when the rigs agree within ``atol``."""

        def close(a, b) -> bool:
            a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
            return a.shape == b.shape and bool(np.allclose(a, b, rtol=0.0, atol=atol))

        differences = []
        mine, theirs = {c.id: c for c in self.cameras}, {c.id: c for c in other.cameras}
        if mine.keys() != theirs.keys():
            differences.append(f"cameras: {sorted(mine)} vs {sorted(theirs)}")
        for camera_id in sorted(mine.keys() & theirs.keys()):
            a, b = mine[camera_id], theirs[camera_id]
            for field in ("role", "sensor", "width", "height", "colour_channels"):
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
            raise ValueError(f"rig file '{path}' is invalid: {_one_line(exc)}") from exc

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
