"""A simulated rig that differs from its description: the true rig behind a nominal ``rig.json``.

A real rig is built from drawings and datasheets and then measured; what it really is differs from
what it was designed to be by a few millimetres, per cent and nanometres. :class:`RigPerturbation`
draws such a true rig from the nominal one (``polarface simulate --perturb-rig SEED``): the simulator
renders every frame with the true rig, the capture folders carry the nominal ``rig.json`` (the one a
user writes from the design), and ``SIM/ground_truth/rig.json`` keeps the true one, which
``polarface calibrate-rig`` must recover from calibration frames (docs/calibration.md).

What differs, each drawn from ``numpy.random.default_rng((seed, 52))`` in this order:

* every LED module's position, by ``N(0, light_position_mm^2)`` per axis;
* every LED module's radiant intensity, by a factor ``1 + N(0, light_intensity^2)`` (the LEDs keep the
  rig's spectrum, so one factor per module);
* the polarization cameras' R, G, B sensitivity, shifted by ``N(0, camera_shift_nm^2)`` nm per colour
  (one sensor model: both cameras alike);
* the two Dolby filters' pass bands, shifted by ``N(0, filter_shift_nm^2)`` nm per filter;
* every polarization camera's R, G, B gain, by a factor ``1 + N(0, camera_gain^2)``;
* every stereo camera's colour: its native R, G, B are ``(I + E) rgb`` of the reference colours, with
  ``E`` of ``N(0, stereo_colour^2)`` entries (:meth:`RigPerturbation.stereo_mixing`).

The channel responses of the true rig are those of the shifted parts
(:func:`polarface.skin.spectral.rig_spectral_parts`), so the perturbation needs the simulator's rig
(:func:`polarface.capture.rig.paper_rig`, whose spectral calibration is the default one).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from polarface.capture.rig import Rig, SpectralModel

__all__ = ["RigPerturbation"]

#: The magnitudes' names, in the order of the draws (module docstring).
MAGNITUDES = ("light_position_mm", "light_intensity", "camera_shift_nm", "filter_shift_nm", "camera_gain",
              "stereo_colour")


@dataclasses.dataclass(frozen=True)
class RigPerturbation:
    """How the simulated rig differs from its nominal description (module docstring).

    Attributes:
        seed: seed of the draws; None: the rig is the nominal one (nothing perturbed).
        light_position_mm: sigma of each LED module's position error per axis (mm).
        light_intensity: relative sigma of each LED module's radiant intensity.
        camera_shift_nm: sigma of the shift of each colour's sensitivity (nm).
        filter_shift_nm: sigma of the shift of each Dolby filter (nm).
        camera_gain: relative sigma of each polarization camera's R, G, B gain.
        stereo_colour: sigma of the entries of each stereo camera's colour mixing error.
    """

    seed: int | None = None
    light_position_mm: float = 3.0
    light_intensity: float = 0.03
    camera_shift_nm: float = 3.0
    filter_shift_nm: float = 2.0
    camera_gain: float = 0.03
    stereo_colour: float = 0.05

    def __post_init__(self) -> None:
        seed = self.seed
        integer = isinstance(seed, int | np.integer) and not isinstance(seed, bool)
        if seed is not None and (not integer or seed < 0):
            raise ValueError(f"argument 'seed' of the rig perturbation must be an integer >= 0 or None; "
                             f"got {self.seed!r}")
        for name in MAGNITUDES:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not (
                    math.isfinite(value) and 0.0 <= value <= _LIMITS[name]):
                raise ValueError(f"argument '{name}' of the rig perturbation must lie in "
                                 f"[0, {_LIMITS[name]}]; got {value!r}")

    @property
    def is_nominal(self) -> bool:
        """True when nothing is perturbed (no seed)."""
        return self.seed is None

    def draws(self, rig: Rig) -> dict[str, Any]:
        """The random errors for ``rig`` (module docstring), as plain lists: ``light_offsets_mm`` (per
        module, xyz), ``light_factors`` (per module), ``camera_shift_nm`` (R, G, B), ``filter_shift_nm``
        (upper, lower), ``camera_gains`` (polarization camera id -> R, G, B factors), ``stereo_mixing``
        (stereo camera id -> 3x3); empty for the nominal rig."""
        if self.is_nominal:
            return {}
        rng = np.random.default_rng((int(self.seed), 52))
        lights = len(rig.lights)
        polarization = [camera.id for camera in rig.cameras if camera.sensor != "rgb"]
        stereo = [camera.id for camera in rig.cameras if camera.sensor == "rgb"]
        offsets = rng.normal(0.0, self.light_position_mm, (lights, 3))
        factors = 1.0 + rng.normal(0.0, self.light_intensity, lights)
        camera_shift = rng.normal(0.0, self.camera_shift_nm, 3)
        filter_shift = rng.normal(0.0, self.filter_shift_nm, 2)
        gains = 1.0 + rng.normal(0.0, self.camera_gain, (len(polarization), 3))
        mixing = np.eye(3) + rng.normal(0.0, self.stereo_colour, (len(stereo), 3, 3))
        return {
            "light_offsets_mm": offsets.tolist(),
            "light_factors": factors.tolist(),
            "camera_shift_nm": camera_shift.tolist(),
            "filter_shift_nm": filter_shift.tolist(),
            "camera_gains": {camera_id: g.tolist() for camera_id, g in zip(polarization, gains, strict=True)},
            "stereo_mixing": {camera_id: m.tolist() for camera_id, m in zip(stereo, mixing, strict=True)},
        }

    def true_rig(self, rig: Rig) -> Rig:
        """The true rig behind the nominal ``rig`` (``rig`` itself when nothing is perturbed): the LED
        modules moved and scaled, the channel responses of the shifted sensor and filters, the
        polarization cameras' gains; exposures and geometry unchanged.

        Raises:
            ValueError: a rig without the default spectral calibration (the parts to shift are the
                default rig's).
        """
        if self.is_nominal:
            return rig
        from polarface.skin.spectral import (
            FINE_WAVELENGTHS_NM,
            SpectralCalibration,
            channel_responses,
            default_spectral_calibration,
            rig_spectral_parts,
        )

        if rig.spectral is None or rig.spectral.model_dump() != SpectralModel.from_calibration(
                default_spectral_calibration(rig.spectral.wavelengths_nm)).model_dump():
            raise ValueError("a perturbed rig needs the default spectral calibration (the simulator's rig); "
                             "this rig has another")
        draws = self.draws(rig)
        data = rig.model_dump(mode="json")
        for light, offset, factor in zip(data["lights"], draws["light_offsets_mm"], draws["light_factors"],
                                         strict=True):
            light["position_mm"] = [p + o for p, o in zip(light["position_mm"], offset, strict=True)]
            intensity = light["radiant_intensity"]
            light["radiant_intensity"] = ([v * factor for v in intensity] if isinstance(intensity, list)
                                          else intensity * factor)
        for camera in data["cameras"]:
            gains = draws["camera_gains"].get(camera["id"])
            if gains is not None:
                camera["channel_gains"] = [g * f for g, f in zip(camera["channel_gains"], gains, strict=True)]
        camera_parts, filters = rig_spectral_parts(draws["camera_shift_nm"], draws["filter_shift_nm"])
        grid = np.asarray(rig.spectral.wavelengths_nm)
        responses = channel_responses(camera_parts, filters, FINE_WAVELENGTHS_NM, grid)
        nominal = rig.spectral.to_calibration()
        true = SpectralCalibration(nominal.wavelengths_nm, nominal.channel_names,
                                   _as_tensor(responses), nominal.led_spd)
        data["spectral"] = SpectralModel.from_calibration(true).model_dump(mode="json")
        return Rig.model_validate(data)

    def spectral_parts(self, rig: Rig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The true rig's spectral parts on :data:`polarface.skin.spectral.FINE_WAVELENGTHS_NM` (1 nm): the
        camera's R, G, B sensitivity ``(3, F)``, the Dolby filters ``(2, F)`` (each shifted by its draw,
        :func:`polarface.skin.spectral.rig_spectral_parts`) and the LED spectrum ``(F,)`` (CIE LED-B5, the
        default calibration's: its table interpolated as the calibration's bins interpolate it)."""
        from polarface.skin.spectral import FINE_WAVELENGTHS_NM, load_spectral_table, rig_spectral_parts

        draws = self.draws(rig)
        camera, filters = rig_spectral_parts(draws.get("camera_shift_nm", (0.0, 0.0, 0.0)),
                                             draws.get("filter_shift_nm", (0.0, 0.0)))
        table_nm, table = load_spectral_table("cie_2018_led_illuminants_relative_spd.csv")
        led = np.interp(FINE_WAVELENGTHS_NM, table_nm, table["LED-B5"], left=0.0, right=0.0)
        return camera, filters, led / led.max()

    def stereo_mixing(self, rig: Rig, camera_id: str) -> np.ndarray:
        """``(3, 3)`` float64 matrix from the reference colours of a stereo camera's render
        (:func:`polarface.simulate.render.stereo_rgb`) to its native R, G, B (identity when nothing is
        perturbed)."""
        if self.is_nominal:
            return np.eye(3)
        return np.asarray(self.draws(rig)["stereo_mixing"][camera_id], dtype=np.float64)

    def to_dict(self) -> dict[str, Any]:
        """The configuration as ``simulation.json`` records it."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, payload: dict[str, Any] | None) -> RigPerturbation:
        """Inverse of :meth:`to_dict` (None: the nominal rig)."""
        return cls() if payload is None else cls(**payload)


#: Largest magnitude accepted per name (beyond it the perturbed rig is no longer "a few" off).
_LIMITS = {"light_position_mm": 50.0, "light_intensity": 0.5, "camera_shift_nm": 20.0,
           "filter_shift_nm": 20.0, "camera_gain": 0.5, "stereo_colour": 0.3}


def _as_tensor(values: np.ndarray) -> Any:
    import torch

    return torch.from_numpy(np.ascontiguousarray(values, dtype=np.float64))
