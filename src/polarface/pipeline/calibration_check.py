"""Why calibration matters, measured (issue 52; docs/calibration.md): a simulated rig that differs from
its nominal rig.json is calibrated from its calibration session, and its capture is reconstructed three
times, with the nominal, the calibrated and the true rig.

``check_calibration(OUT, CalibrationCheckConfig(...))`` writes::

    OUT/sim/                  the simulation (static sequence, ``--perturb-rig SEED``; resumed when present)
    OUT/calibrated.json       the rig calibrate-rig makes from OUT/sim/calibration
    OUT/<rig>/capture/        the raw frames ingested with that rig (nominal, calibrated, true)
    OUT/<rig>/result/         its reconstruction
    OUT/calibration_check.json  the rigs' errors against the true rig and each reconstruction's, with its
                              maps' median differences from the true rig's reconstruction

Every reconstruction uses the same geometry (``known``: the simulator's surface, so that the rigs alone
differ; ``stereo``: the nominal rig's stereo surface for all), so the differences are the rigs'.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from polarface.capture.ingest import ingest_directory
from polarface.capture.rig import Rig
from polarface.evaluate import evaluate
from polarface.io import write_json_atomic
from polarface.pipeline.calibrate_rig import calibrate_from_session, response_peaks_nm
from polarface.pipeline.inputs import resolve_reconstruct_inputs
from polarface.pipeline.reconstruct import reconstruct
from polarface.results import ResultFolder
from polarface.simulate import RigPerturbation, SimulationConfig, get_preset, simulate
from polarface.simulate.layout import GROUND_TRUTH

__all__ = ["RIG_NAMES", "CalibrationCheckConfig", "check_calibration", "format_calibration_check"]

#: The rigs the capture is reconstructed with, in the order they run.
RIG_NAMES = ("true", "calibrated", "nominal")
#: The maps compared with the true rig's reconstruction (median absolute difference over both masks;
#: ``rho_sss_bar`` relative).
COMPARED_MAPS = ("eta", "rho_sss_bar", "c_m", "c_h_out")


@dataclasses.dataclass(frozen=True)
class CalibrationCheckConfig:
    """What :func:`check_calibration` runs.

    Attributes:
        preset: the simulation preset (``tiny`` for tests, ``demo`` for the numbers).
        seed: the rig perturbation's seed (:class:`polarface.simulate.RigPerturbation`).
        geometry: ``known`` (the simulator's surface) or ``stereo`` (the nominal rig's stereo surface).
        fit_options: further fit options for every reconstruction (e.g. fewer ``iterations`` in tests).
    """

    preset: str = "demo"
    seed: int = 1
    geometry: str = "known"
    fit_options: dict[str, Any] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        get_preset(self.preset)
        RigPerturbation(seed=self.seed)
        if self.geometry not in ("known", "stereo"):
            raise ValueError(f"argument 'geometry' must be 'known' or 'stereo'; got {self.geometry!r}")


def _rig_errors(rig: Rig, true: Rig) -> dict[str, float]:
    """A rig's errors against the true one: LED positions (max, mm), intensities and gains (max relative,
    each in the calibration's gauge: per channel, the modules' mean intensity divided out), the channel
    responses' peaks (max, nm) and shapes (max RMS, each channel scaled to its maximum)."""
    def products(r: Rig) -> np.ndarray:
        gains = np.ones(6)
        for camera in r.cameras:
            for colour, channel in camera.colour_channels.items():
                gains[channel] = camera.channel_gains["RGB".index(colour)]
        intensity = np.array([np.broadcast_to(light.radiant_intensity, (6,)) for light in r.lights])
        return intensity, gains

    (i_rig, g_rig), (i_true, g_true) = products(rig), products(true)
    grid = np.asarray(true.spectral.wavelengths_nm)
    responses = [np.asarray(r.spectral.channel_responses) for r in (rig, true)]
    shapes = [r / r.max(axis=1, keepdims=True) for r in responses]
    positions = [np.array([light.position_mm for light in r.lights]) for r in (rig, true)]
    peaks = [response_peaks_nm(r, grid) for r in responses]
    return {
        "light_position_mm": float(np.linalg.norm(positions[0] - positions[1], axis=1).max()),
        "intensity": float(np.abs((i_rig / i_rig.mean(0)) / (i_true / i_true.mean(0)) - 1).max()),
        "gain": float(np.abs((g_rig * i_rig.mean(0)) / (g_true * i_true.mean(0)) - 1).max()),
        "response_peak_nm": float(np.abs(peaks[0] - peaks[1]).max()),
        "response_shape": float(np.sqrt(np.mean((shapes[0] - shapes[1]) ** 2, axis=1)).max()),
    }


def _map_differences(result: Path, reference: Path) -> dict[str, float]:
    """Median absolute differences of :data:`COMPARED_MAPS` between two RESULTs over both masks
    (``rho_sss_bar``: relative, over its six channels)."""
    folders = [ResultFolder(result), ResultFolder(reference)]
    mask = folders[0].read_mask() & folders[1].read_mask()
    out = {}
    for name in COMPARED_MAPS:
        if name == "rho_sss_bar":
            a, b = (folder.read_maps()[name][mask] for folder in folders)
            out[name] = float(np.median(np.abs(a - b) / np.maximum(b, 1e-6)))
        else:
            a, b = (folder.read_scalar_map(name)[mask] for folder in folders)
            out[name] = float(np.median(np.abs(a - b)))
    return out


def check_calibration(out: str | Path, config: CalibrationCheckConfig = CalibrationCheckConfig(),
                      progress: bool = True) -> dict[str, Any]:
    """Simulate, calibrate, reconstruct with each rig of :data:`RIG_NAMES` and compare (module docstring);
    returns the summary also written to ``OUT/calibration_check.json``. Reruns resume."""
    out = Path(out).absolute()
    sim = out / "sim"
    simulate(sim, SimulationConfig(preset=config.preset, sequences=("static",),
                                   rig_perturbation=RigPerturbation(seed=config.seed)), progress=progress)
    calibrated_path = out / "calibrated.json"
    started = time.perf_counter()
    report = calibrate_from_session(sim / "calibration", sim / "static" / "rig.json", calibrated_path,
                                    force=True)
    calibration_s = time.perf_counter() - started
    rigs = {"true": Rig.load(sim / GROUND_TRUTH / "rig.json"), "calibrated": Rig.load(calibrated_path),
            "nominal": Rig.load(sim / "static" / "rig.json")}
    geometry = sim / GROUND_TRUTH if config.geometry == "known" else None
    resolution = get_preset(config.preset).texture_resolution
    rows: dict[str, dict[str, Any]] = {}
    for name in ("nominal", "calibrated", "true") if geometry is None else RIG_NAMES:
        capture = ingest_directory(sim / "static" / "raw", rigs[name], out / name / "capture",
                                   progress=progress)
        result = out / name / "result"
        started = time.perf_counter()
        if not ResultFolder(result).stage_complete("biophysical"):
            inputs = resolve_reconstruct_inputs(capture.root, geometry=geometry,
                                                texture_resolution=resolution)
            reconstruct(inputs, result, fit_options=dict(config.fit_options), progress=progress,
                        resume=result.exists())
        if geometry is None:  # the others fit on the nominal rig's stereo surface
            geometry = result / "geometry"
        metrics = evaluate(result, sim, ["polarimetric", "biophysical"])
        rows[name] = {"rig_errors": _rig_errors(rigs[name], rigs["true"]), "metrics": _summary(metrics),
                      "seconds": time.perf_counter() - started}
    for name in ("calibrated", "nominal"):
        rows[name]["differences_from_true_rig"] = _map_differences(out / name / "result",
                                                                   out / "true" / "result")
    summary = {"format": "polarface-calibration-check", "config": dataclasses.asdict(config),
               "calibration": report, "calibration_s": calibration_s, "rigs": rows}
    write_json_atomic(out / "calibration_check.json", summary)
    return summary


def _summary(metrics: dict[str, Any]) -> dict[str, float]:
    """The evaluation's headline errors against the ground truth."""
    polarimetric, biophysical = metrics["polarimetric"], metrics["biophysical"]
    out = {"eta": polarimetric["eta"]["median_abs_error"],
           "rho_sss_bar": polarimetric["rho_sss_bar"]["median_relative_error"]}
    for name in ("c_m", "c_h_out"):
        out[name] = biophysical[name]["median_abs_error"]
    return out


def format_calibration_check(summary: dict[str, Any]) -> str:
    """The check as text: per rig its errors against the true rig, its reconstruction's errors against the
    ground truth and its maps' differences from the true rig's reconstruction."""
    lines = [f"{'rig':12s} {'LED mm':>7s} {'gain':>7s} {'intens.':>7s} {'peak nm':>7s} {'shape':>7s} | "
             f"{'eta':>7s} {'rho_sss':>7s} {'C_m':>7s} {'C_h_out':>7s} | diff from true rig: eta, rho_sss, "
             "C_m, C_h_out"]
    for name, row in summary["rigs"].items():
        rig, fit = row["rig_errors"], row["metrics"]
        diff = row.get("differences_from_true_rig")
        text = ", ".join(f"{diff[k]:.4f}" for k in COMPARED_MAPS) if diff else "-"
        lines.append(f"{name:12s} {rig['light_position_mm']:7.2f} {rig['gain']:7.4f} {rig['intensity']:7.4f} "
                     f"{rig['response_peak_nm']:7.2f} {rig['response_shape']:7.4f} | {fit['eta']:7.4f} "
                     f"{fit['rho_sss_bar']:7.4f} {fit['c_m']:7.4f} {fit['c_h_out']:7.4f} | {text}")
    return "\n".join(lines)
