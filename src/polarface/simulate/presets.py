"""Simulator presets and skin-type presets.

Presets fix the image size, the texture resolution and the number of frames:

=======  ==================  ==============  ===========  ============
preset   polarimetric image  texture         static       dynamic
=======  ==================  ==============  ===========  ============
tiny     256 x 212           256 x 256       4 views      2 frames
demo     612 x 512           512 x 512       24 views     10 frames
full     2448 x 2048         2048 x 2048     200 views    50 frames
=======  ==================  ==============  ===========  ============

612 x 512 is the effective (per-superpixel) resolution of the paper's 2448 x 2048
colour-polarization camera (supplement, "Spatial resolution").

The RGB stereo cameras (geometry) render at ``stereo_width`` x ``stereo_height``: 2448 x 2048 in the
``full`` preset (a 5 MP machine-vision camera of the IMX250 class, the sensor family of the rig's
polarization cameras), 612 x 512 in ``demo`` (a quarter of that per side, like the polarimetric images:
rendering eight stereo views at 1224 x 1024 would add ~14 s per frame, ~8 min to the demo, for a
measured 0.4 -> 0.33 mm median error of a frame's mesh) and 320 x 256 in ``tiny`` (tests only).
The static sequence sweeps the yaw by +-60 deg (paper: the revolving chair), except ``tiny``: +-12 deg,
so that its four frames (8 deg apart) register from stereo; 40 deg steps overlap too little.

Skin types follow the paper's supplement Table "Estimated biophysical parameters" (forehead and
cheek means of subjects with skin types I-IV); types V and VI extrapolate the melanin trend
(documented, not measured by the paper).
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["PRESETS", "SKIN_TYPES", "SimulationPreset", "SkinTypePreset", "get_preset", "get_skin_type"]


@dataclass(frozen=True)
class SimulationPreset:
    """Sizes and sequence lengths of one simulator preset.

    Attributes:
        name: preset name.
        width, height: polarimetric camera image size in pixels (the demosaiced resolution).
        stereo_width, stereo_height: RGB stereo camera image size in pixels.
        texture_resolution: side of the square UV atlas in texels.
        static_frames: number of views of the static (revolving chair) sequence.
        dynamic_frames: number of frames of the dynamic (expression) sequence.
        dynamic_frame_step: the dynamic sequence keeps every k-th frame of a 20 fps recording, so that
            ``dynamic_frames`` frames span the blood-flow recovery (~2 s, paper Fig. "blood flow").
        yaw_range_deg: static sequence yaw sweep (+-) of the head on the chair, degrees.
        pitch_range_deg: static sequence pitch oscillation amplitude, degrees.
        frame_chunk: frames rendered per chunk (bounds memory for the full preset).
        validation_views: viewpoints of the validation camera outside the rig
            (:mod:`polarface.simulate.validation`; the paper averages 200 novel poses).
    """

    name: str
    width: int
    height: int
    stereo_width: int
    stereo_height: int
    texture_resolution: int
    static_frames: int
    dynamic_frames: int
    dynamic_frame_step: int
    yaw_range_deg: float = 60.0
    pitch_range_deg: float = 10.0
    frame_chunk: int = 1
    validation_views: int = 24


PRESETS: dict[str, SimulationPreset] = {
    # tiny: +-12 deg (8 deg steps) so that its 4 frames register from stereo (40 deg steps do not)
    "tiny": SimulationPreset(
        "tiny", 256, 212, 320, 256, 256, 4, 2, 20, yaw_range_deg=12.0, pitch_range_deg=4.0, validation_views=4
    ),
    "demo": SimulationPreset("demo", 612, 512, 612, 512, 512, 24, 10, 4),
    "full": SimulationPreset("full", 2448, 2048, 2448, 2048, 2048, 200, 50, 1),
}


@dataclass(frozen=True)
class SkinTypePreset:
    """Mean biophysical parameters of a skin type (volume fractions, dimensionless).

    Attributes:
        name: Fitzpatrick type I..VI.
        c_m: melanin fraction of the outer layer.
        beta_m: eumelanin fraction of the melanin.
        c_h_in: haemoglobin fraction of the inner layer.
        c_h_out: haemoglobin fraction of the outer layer.
        cheek: the same four values on the cheek (c_m, beta_m, c_h_in, c_h_out).
        source: where the numbers come from.
    """

    name: str
    c_m: float
    beta_m: float
    c_h_in: float
    c_h_out: float
    cheek: tuple[float, float, float, float] = field(default=(0.0, 0.0, 0.0, 0.0))
    source: str = "Ha et al. 2024, supplement Table tb:res_params (forehead / cheek means)"


SKIN_TYPES: dict[str, SkinTypePreset] = {
    "I": SkinTypePreset("I", 0.03243, 0.09607, 0.03691, 0.01701, (0.02891, 0.07224, 0.02672, 0.04337)),
    "II": SkinTypePreset("II", 0.05036, 0.04759, 0.02072, 0.08323, (0.04335, 0.03684, 0.01722, 0.05639)),
    "III": SkinTypePreset("III", 0.06155, 0.05304, 0.03622, 0.07337, (0.03993, 0.02355, 0.05753, 0.09753)),
    "IV": SkinTypePreset("IV", 0.08909, 0.05291, 0.02654, 0.10450, (0.07982, 0.05559, 0.02135, 0.09513)),
    # Extrapolated: melanin continues the I->IV trend (about +0.06 and +0.12 over IV, within the
    # Donner & Jensen 2006 range for darkly pigmented skin); haemoglobin as type IV.
    "V": SkinTypePreset(
        "V", 0.15, 0.06, 0.026, 0.10, (0.13, 0.06, 0.021, 0.095), source="extrapolated from types I-IV"
    ),
    "VI": SkinTypePreset(
        "VI", 0.25, 0.07, 0.026, 0.10, (0.22, 0.07, 0.021, 0.095), source="extrapolated from types I-IV"
    ),
}


def get_preset(name: str) -> SimulationPreset:
    """The preset called ``name`` (``tiny``, ``demo`` or ``full``); ValueError naming the choices."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(
            f"argument 'preset': unknown preset {name!r}; choose one of {sorted(PRESETS)}"
        ) from None


def get_skin_type(name: str) -> SkinTypePreset:
    """The skin-type preset ``I``..``VI`` (case-insensitive); ValueError naming the choices."""
    key = str(name).strip().upper()
    if key not in SKIN_TYPES:
        raise ValueError(
            f"argument 'skin_type': unknown skin type {name!r}; choose one of {list(SKIN_TYPES)}"
        )
    return SKIN_TYPES[key]
