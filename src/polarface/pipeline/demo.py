"""The README's demo jobs: the whole pipeline on the embedded head, and the optics-only sphere.

:func:`run_demo_pipeline` (``polarface demo --out DIR [--preset demo|tiny]``) runs, resumably:

  1. simulation: a synthetic capture of the bundled head with the paper's rig -> DIR/sim
  2. reconstruction from the raw frames only: geometry from the stereo pairs (mesh with a cylindrical
     atlas, poses), texture-space polarimetric inverse rendering, then the biophysical stage; then the
     dynamic sequence frame by frame (tracking, per-frame maps and chromophores)
     -> DIR/result (geometry/, tracking/, frames/, maps as EXR, previews, report.html); the simulator's
     geometry is used only by the evaluation
  3. evaluation: errors against the simulator's ground truth -> DIR/metrics.json, figures (the
     geometry error heat map) -> DIR/figures/; beside it (on the workers, when there are two cores or
     more), every export format (``polarface export``) -> DIR/result/exports (the Mitsuba scene, the
     glTF and its offline 3D viewer page, USD, kernels), then the reconstruction's report (it links
     the viewer), and the landing page's comparison figures
  4. DIR/index.html: a landing page linking the report, the metrics and the simulated frames, with the
     metrics as a table of value, target and pass, and per parameter the ground truth, the
     reconstruction and the error side by side (DIR/comparison/*.png; frame previews in DIR/frames/).

:func:`run_sphere_demo` (``polarface demo --sphere --out DIR``) renders a skin-like sphere under the 8
polarized LED modules (:func:`polarface.render.demo.render_demo`), written as:
  exr/I0.exr, I45, I90, I135      analyzer images, channels R, G, B (linear float32 radiance)
  exr/I_sss.exr, I_zeta, I_s      observations 2 I90, I135 - I45, I0 - I90
  exr/DoP.exr, AoLP.exr           linear DoP and AoLP in [0, pi) radians, per channel
  exr/mask.exr                    1 on the sphere, 0 on the background
  png/*.png                       previews (sRGB tone-mapped or colour-mapped, channel G for maps)
  parameters.json                 the scene and material parameters used
  index.html                      a page showing every image with a caption
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import numpy as np

from polarface.results import layout
from polarface.simulate.layout import ground_truth_folder

__all__ = ["run_demo_pipeline", "run_sphere_demo"]

_CAPTIONS = {
    "I0": "I0: analyzer at 0 deg, co-polarized with the LEDs: specular + subsurface.",
    "I45": "I45: analyzer at 45 deg.",
    "I90": "I90: analyzer at 90 deg, cross-polarized: specular removed, subsurface only.",
    "I135": "I135: analyzer at 135 deg.",
    "I_sss": "I_sss = 2 I90: unpolarized subsurface observation.",
    "I_zeta": "I_zeta = I135 - I45: polarized subsurface observation (signed, channel G; blue < 0 < red).",
    "I_s": "I_s = I0 - I90: specular-dominant observation (signed, channel G): specular highlight > 0, "
    "subsurface polarization term -T- T+ xi (negative where the normal tilts up/down).",
    "DoP": "Degree of linear polarization (channel G).",
    "AoLP": "Angle of linear polarization in [0, pi) (channel G, cyclic colour map).",
}


# ---- the pipeline demo ---------------------------------------------------------------------------
#: What the demo's last steps write under DIR (beside ``index.html`` and ``demo.json``): when they all exist
#: and ``demo.json`` records the ``result.json`` they were made from, a rerun does not redo them.
_TAIL_OUTPUTS = ("metrics.json", "result/report.html", "result/exports/export.json", "comparison")


def _result_digest(out: Path) -> str:
    """SHA-256 of ``DIR/result/result.json``: it changes whenever a stage of the RESULT reruns."""
    return hashlib.sha256((out / "result" / layout.RESULT_JSON).read_bytes()).hexdigest()


def _tail_up_to_date(out: Path) -> bool:
    """Whether the evaluation, export, report and landing page of ``out`` were made from the RESULT as it
    is now (``demo.json``'s ``result_sha256``) and are all present."""
    from polarface.io import read_json_object

    try:
        record = read_json_object(out / "demo.json")
        current = _result_digest(out)
    except (OSError, ValueError):
        return False
    present = all((out / name).exists() for name in (*_TAIL_OUTPUTS, "index.html"))
    return present and record.get("complete") is True and record.get("result_sha256") == current


def _demo_steps(out: Path, preset: str, skin_type: str, say: Callable[[str], None]
                ) -> tuple[dict[str, Any], list | None]:
    """Simulate, reconstruct, evaluate and export; each step announced as the equivalent command line.
    Returns the metrics and the landing page's comparison figures (None: the landing page and everything
    after the reconstruction are up to date, :func:`_tail_up_to_date`, and were not redone)."""
    from polarface.executors import LocalExecutor, ProcessExecutor
    from polarface.io import read_json_object
    from polarface.pipeline.inputs import resolve_reconstruct_inputs
    from polarface.pipeline.reconstruct import reconstruct
    from polarface.results import ResultFolder
    from polarface.simulate.pipeline import SimulationConfig, simulate

    sim, result = out / "sim", out / "result"
    # The simulator's frames, the stereo frames, the patches and the dynamic frames are independent units;
    # on a machine with more than one core they run in worker processes (docs/performance.md).
    workers = os.cpu_count() or 1
    executor = ProcessExecutor(workers) if workers > 1 else LocalExecutor()
    on_workers = f" --executor processes --workers {workers}" if workers > 1 else ""
    say(f"polarface demo: polarface simulate --preset {preset} --skin-type {skin_type} --out {sim}"
        + on_workers)
    config = SimulationConfig(
        preset=preset, seed=0, skin_type=skin_type, noise=True, subsurface_blur=True,
        sequences=("static", "dynamic"),
    )
    with executor:
        summary = simulate(str(sim), config, executor=executor)
        say(json.dumps({"out": str(sim), "timings": summary["timings"],
                        "peak_rss_mb": summary["peak_rss_mb"]}, indent=2))
        resume = result.exists()
        say(f"polarface demo: polarface reconstruct {sim} --dynamic {sim} --out {result}"
            f"{' --resume' if resume else ''}{on_workers}")
        reconstruct(resolve_reconstruct_inputs(sim), result, resume=resume, dynamic=sim, executor=executor,
                    report=False)
        if _tail_up_to_date(out):
            say(f"polarface demo: {out}/index.html is up to date with {result} (nothing to redo)")
            return read_json_object(out / "metrics.json"), None
        # the export, the evaluation, the report and the landing page's comparison figures read the
        # finished RESULT and write apart: units on the workers (each mostly one core's work), the report
        # after the export, whose viewer it links (in this process: one after the other, on one core)
        say(f"polarface demo: polarface evaluate {result} --gt {sim} --out {out / 'metrics.json'} "
            f"--figures {out / 'figures'}")
        say(f"polarface demo: polarface export {result} --out {result / 'exports'} --force")
        steps: tuple[_TailStep, ...] = ("export", "evaluate", "report", "comparisons")
        outcomes = executor.map_dependent(_run_demo_tail, len(steps), lambda k: _DemoTail(steps[k], out),
                                          after=[[], [], [steps.index("export")], []], failures=())
        exported, metrics, report, comparisons = (outcome.value for outcome in outcomes)
    folder = ResultFolder(result)
    folder.record_stage("report", report)
    say(reconstruct_summary_line(result, folder.read_result()))
    say(json.dumps(metrics, indent=2))
    say(json.dumps(exported))
    return metrics, comparisons


_TailStep = Literal["export", "evaluate", "report", "comparisons"]


@dataclasses.dataclass(frozen=True)
class _DemoTail:
    """One step after the reconstruction of the demo folder ``out``, as an executor unit."""

    step: _TailStep
    out: Path


def _run_demo_tail(unit: _DemoTail) -> Any:
    """Of the demo folder ``unit.out``: ``polarface evaluate`` (returns the metrics, written to
    ``out/metrics.json``), ``polarface export`` (returns its seconds per format), the reconstruction's
    ``report.html`` (returns the report stage's record) or the landing page's comparison figures (returns
    their :class:`polarface.report.html.ImageItem` list)."""
    sim, result = unit.out / "sim", unit.out / "result"  # each step imports only what it runs
    if unit.step == "evaluate":
        from polarface.evaluate import evaluate
        from polarface.io import write_json_atomic
        from polarface.io.output_folder import output_folder

        # as `polarface evaluate --figures` writes it: the printed command line reruns on this folder
        with output_folder(unit.out / "figures", "evaluate", force=True, staged=True) as figures:
            metrics = evaluate(result, sim, figures_dir=figures)
        write_json_atomic(unit.out / "metrics.json", metrics)
        return metrics
    if unit.step == "report":
        from polarface.pipeline.reconstruct import write_result_report
        from polarface.results import ResultFolder

        return write_result_report(ResultFolder(result))
    if unit.step == "comparisons":
        from polarface.report.demo_index import write_comparisons

        return write_comparisons(unit.out, result, ground_truth_folder(sim))
    from polarface.io.output_folder import output_folder
    from polarface.pipeline.export import export_result

    exports = result / "exports"
    with output_folder(exports, "export", force=True) as folder:
        record = export_result(result, Path(folder))
    return {"out": str(exports), "seconds": record["seconds"],
            "formats": {name: entry["seconds"] for name, entry in record["formats"].items()}}


def reconstruct_summary_line(out: str | Path, result: dict[str, Any]) -> str:
    """The one-line summary ``polarface reconstruct`` prints after a run; it ends with the report's path.

    Args:
        out: the RESULT folder.
        result: its ``result.json`` content (``stages.polarimetric`` gives texels and throughput).
    """
    from polarface.results import ResultFolder

    stage = result.get("stages", {}).get("polarimetric", {})
    return (
        f"polarface reconstruct: wrote {out} ({stage.get('texels', 0)} texels, "
        f"{stage.get('throughput_texel_view_iterations_per_s', 0):.3g} texel-view it/s); "
        f"report: {ResultFolder(out).report_path}"
    )


def _demo_page(out: Path, preset: str, skin_type: str, elapsed: float, metrics: dict[str, Any],
               comparisons: list):
    """The landing page (:func:`polarface.report.demo_index.demo_index_page`): links, metrics table with
    targets, ground truth / reconstruction / error per parameter (``comparisons``, written), simulated
    frames."""
    from polarface.report.demo_index import demo_index_page

    subtitle = f"preset {preset}, skin type {skin_type}, {elapsed / 60:.1f} min on this machine"
    return demo_index_page(out, subtitle, metrics, comparisons=comparisons)


def _print_now(line: str) -> None:
    print(line, flush=True)


def run_demo_pipeline(
    out: str | Path, preset: str = "demo", skin_type: str = "II", say: Callable[[str], None] = _print_now
) -> Path:
    """Simulate -> reconstruct -> evaluate into ``out`` and write ``out/index.html`` (module docstring).

    Args:
        out: output folder (``sim/``, ``result/``, ``metrics.json``, ``demo.json``, ``index.html``); a
            finished one is checked and left as it is in seconds (nothing redone).
        preset: simulator preset (``demo`` or ``tiny``).
        skin_type: Fitzpatrick skin type I..VI of the simulated subject.
        say: receives the progress lines (default: printed and flushed).

    Returns:
        The path of ``index.html``.
    """
    from polarface.io import write_json_atomic

    out = Path(out)
    started = time.perf_counter()
    metrics, comparisons = _demo_steps(out, preset, skin_type, say)
    if comparisons is None:  # nothing was redone
        return out / "index.html"
    elapsed = time.perf_counter() - started
    path = _demo_page(out, preset, skin_type, elapsed, metrics, comparisons).write(out / "index.html")
    write_json_atomic(out / "demo.json", {"preset": preset, "skin_type": skin_type, "seconds": elapsed,
                                          "complete": True, "result_sha256": _result_digest(out)})
    say(f"polarface demo: wrote {out}/index.html ({elapsed / 60:.1f} min)")
    return path


# ---- the sphere demo -----------------------------------------------------------------------------
def _sphere_parameters(size: int, eta: float | None):
    from polarface.render.demo import DemoParameters

    if size < 8 or size > 4096:
        raise ValueError(f"argument '--size' must be in [8, 4096]; got {size}")
    overrides: dict[str, Any] = {"width": size, "height": size, "focal_px": 1400.0 * size / 256}
    if eta is not None:
        if not eta > 1.0:
            raise ValueError(f"argument '--eta' must be > 1; got {eta}")
        overrides["eta"] = eta
    return dataclasses.replace(DemoParameters(), **overrides)


def _render_sphere(params) -> tuple[dict[str, np.ndarray], np.ndarray, float]:
    """Render on one torch thread; returns the named ``(H, W, C)`` float32 images, the mask and seconds."""
    import torch

    from polarface.render.demo import render_demo

    # A 256x256 render is ~40k pixels per elementwise op: intra-op threading costs more than it gains,
    # and on a busy machine OpenMP workers spinning against other processes slow it down a lot.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        start = time.perf_counter()
        result = render_demo(params)
        render_seconds = time.perf_counter() - start
    finally:
        torch.set_num_threads(threads)
    images = result.images
    maps = {
        "I0": images.i0, "I45": images.i45, "I90": images.i90, "I135": images.i135,
        "I_sss": images.i_sss, "I_zeta": images.i_zeta, "I_s": images.i_s,
        "DoP": images.dop(), "AoLP": images.aolp(),
    }
    maps = {name: value.numpy().astype(np.float32) for name, value in maps.items()}
    return maps, result.geometry.mask.numpy(), render_seconds


def _write_sphere_preview(path: Path, name: str, value: np.ndarray, mask: np.ndarray, exposure: float,
                          green: int) -> None:
    from polarface.io import colormap_png, write_png
    from polarface.render.colour import encode_srgb

    if name in ("I0", "I45", "I90", "I135", "I_sss"):
        preview = value[..., :3] if value.shape[-1] >= 3 else np.repeat(value[..., :1], 3, -1)
        scale = 2.0 * exposure if name == "I_sss" else exposure
        write_png(path, encode_srgb(preview / scale).astype(np.float64))
    elif name in ("I_zeta", "I_s"):
        channel = value[..., green]
        limit = float(np.percentile(np.abs(channel[mask]), 99.5)) if mask.any() else 1.0
        colormap_png(path, channel, vmin=-limit, vmax=limit or 1.0, cmap="coolwarm", mask=mask,
                     label=f"{name} (linear radiance)")
    elif name == "DoP":
        colormap_png(path, value[..., green], vmin=0.0, mask=mask, label="DoP (1)")
    else:
        colormap_png(path, value[..., green], vmin=0.0, vmax=np.pi, cmap="twilight", mask=mask,
                     label="AoLP (rad)")


def _sphere_page(params, render_seconds: float, parameters: dict[str, Any]):
    from polarface.report.html import HtmlPage, ImageItem

    page = HtmlPage(
        "polarface demo: polarimetric images of a skin-like sphere",
        subtitle=f"{params.width}x{params.height} px, {params.light_count} polarized LED "
        f"modules {params.off_axis_deg:.2f} deg off axis, rendered in "
        f"{render_seconds:.2f} s on CPU",
    )
    page.section(
        "Analyzer images",
        "Linear radiance seen behind the four polarizer angles of a polarization camera "
        "(sRGB previews, common exposure; EXR files hold the linear values).",
    ).image_grid([ImageItem(f"png/{n}.png", _CAPTIONS[n]) for n in ("I0", "I45", "I90", "I135")])
    page.section(
        "Observations (paper, Sec. 4.2)",
        "The separations the inverse stage fits: subsurface, its polarized part, and the specular.",
    ).image_grid([ImageItem(f"png/{n}.png", _CAPTIONS[n]) for n in ("I_sss", "I_zeta", "I_s")], columns=3)
    page.section("Polarization", "Per-pixel degree and angle of linear polarization.").image_grid(
        [ImageItem(f"png/{n}.png", _CAPTIONS[n]) for n in ("DoP", "AoLP")], columns=2
    )
    page.section("Parameters").table(parameters)
    return page


#: The command name the sphere demo's folder marker and lock record.
SPHERE_COMMAND = "demo --sphere"


def run_sphere_demo(
    out: str | Path, size: int = 256, eta: float | None = None, *, force: bool = False
) -> float:
    """Render the optics-only sphere demo into ``out`` (module docstring); every file is written atomically.

    ``out`` must be absent, empty or an earlier sphere demo (:func:`polarface.io.output_folder.output_folder`:
    marker file, lock); nothing else in it is renamed or deleted.

    Args:
        out: output folder.
        size: image width and height in pixels, in [8, 4096].
        eta: refractive index (> 1; default the demo's).
        force: replace a non-empty ``out`` not written by the sphere demo (swapped in after success).

    Returns:
        The render time in seconds.

    Raises:
        ValueError: ``size`` or ``eta`` out of range (nothing is written); ``out`` is a file, busy, or holds
            other data (:class:`polarface.io.output_folder.OutputFolderError`).
    """
    from polarface.io.output_folder import output_folder

    params = _sphere_parameters(size, eta)
    with output_folder(out, SPHERE_COMMAND, force=force) as folder:
        maps, mask, render_seconds = _render_sphere(params)
        _write_sphere(folder, params, maps, mask, render_seconds)
    return render_seconds


def _write_sphere(folder: Path, params, maps: dict[str, np.ndarray], mask, seconds: float) -> None:
    """Write the images, previews, parameters.json and index.html of the sphere demo into ``folder``."""
    from tqdm import tqdm

    from polarface.io import write_exr, write_json_atomic

    names = list(params.channel_names)
    exposure = float(np.percentile(maps["I0"][mask], 99.5)) if mask.any() else 1.0
    exposure = exposure if exposure > 0 else 1.0
    green = names.index("G") if "G" in names else 0
    for name, value in tqdm(maps.items(), desc="writing images", unit="image", leave=False):
        write_exr(folder / "exr" / f"{name}.exr", value, names)
        _write_sphere_preview(folder / "png" / f"{name}.png", name, value, mask, exposure, green)
    write_exr(folder / "exr" / "mask.exr", mask.astype(np.float32))
    parameters = {
        k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(params).items()
    }
    parameters["off_axis_deg"] = params.off_axis_deg
    write_json_atomic(folder / "parameters.json", parameters)
    _sphere_page(params, seconds, parameters).write(folder / "index.html")
