"""``polarface reconstruct CAPTURE --out RESULT``: static polarimetric inverse rendering (paper Sec. 5).

CAPTURE is a static capture store (``polarface ingest`` / ``SIM/static``) or a simulation folder
(then ``SIM/static`` is used and the geometry defaults to ``SIM/ground_truth``). Geometry is "known":
``--geometry DIR`` (``DIR/mesh_rest.obj`` + ``DIR/static/poses.json``, the simulator's ground-truth
layout) or ``--mesh MESH --poses POSES`` (OBJ/PLY with UVs in the model frame, mm; model -> rig-world
4x4 per capture frame).

The run is a sequence of stages over the RESULT folder (:data:`STAGES`); each reads and writes the
documented artifacts, records itself in ``result.json`` and is skipped by ``--resume`` when done:

* ``prepare``: ``rig.json``, ``mesh.obj``, ``result.json`` skeleton, ``unwrap.zarr`` (texture space);
* ``polarimetric``: ``maps/*.exr`` + ``maps/mask.png``, ``previews/*.png``, ``checkpoints/``;
* ``report``: ``report.html`` (maps, loss curve, residuals, DoP/AoLP of observation vs re-render).

Bad input (no poses, mismatched UV atlas, all-invisible texels, NaN observations) raises ValueError
before anything is written, or removes the RESULT folder this run created.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

NAME = "reconstruct"
HELP = "static polarimetric inverse rendering of a capture into texture maps (RESULT folder)"

LOGGER = logging.getLogger(__name__)
MAP_NAMES = ("eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss", "displacement_mm")


@dataclasses.dataclass
class ReconstructContext:
    """What the stages share: inputs, options and the RESULT folder."""

    capture: Path
    out: Path
    mesh_path: Path
    poses_path: Path
    texture_resolution: int
    device: str
    resume: bool
    progress: bool
    holdout_every: int
    fit_options: dict = dataclasses.field(default_factory=dict)
    stop_after_patches: int | None = None
    threads: int | None = 1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", type=Path, help="static capture store, or a simulation folder (SIM)")
    parser.add_argument("--out", type=Path, required=True, help="RESULT folder")
    parser.add_argument(
        "--geometry",
        type=Path,
        default=None,
        help="folder with mesh_rest.obj and static/poses.json (default SIM/ground_truth)",
    )
    parser.add_argument(
        "--mesh", type=Path, default=None, help="rest mesh with UVs (OBJ/PLY, model frame, mm)"
    )
    parser.add_argument(
        "--poses", type=Path, default=None, help="model -> rig-world 4x4 per frame (.json/.npy)"
    )
    parser.add_argument(
        "--texture-resolution",
        type=int,
        default=None,
        help="UV atlas side in texels (default: the simulation's, else 512)",
    )
    parser.add_argument(
        "--iterations", type=int, default=None, help="optimiser steps per patch (default 150)"
    )
    parser.add_argument("--lr", type=float, default=None, help="learning rate (default 0.03)")
    parser.add_argument("--optimizer", choices=("rmsprop", "adam"), default=None)
    parser.add_argument(
        "--refine-lobes",
        type=int,
        default=None,
        metavar="N",
        help="Levenberg-Marquardt iterations on the lobe maps after each patch (default 0; see docs)",
    )
    parser.add_argument(
        "--holdout-every",
        type=int,
        default=4,
        help="hold out every n-th frame for evaluation (0: none; default 4)",
    )
    parser.add_argument(
        "--device", default=None, help="cpu, cuda or auto (default: POLARFACE_DEVICE or auto)"
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch threads of the fit (default 1: fastest on a busy 2-core CPU; try 2+ on an idle one)",
    )
    parser.add_argument("--resume", action="store_true", help="continue an interrupted run in RESULT")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def _resolve_inputs(args: argparse.Namespace) -> tuple[Path, Path, Path, int]:
    capture = Path(args.capture)
    if not capture.exists():
        raise FileNotFoundError(f"capture '{capture}' does not exist")
    sim_root = None
    if (capture / "static" / "manifest.json").exists():
        sim_root, capture = capture, capture / "static"
    if not (capture / "manifest.json").exists():
        raise ValueError(f"'{capture}' is not a capture store (no manifest.json)")
    if args.mesh is not None or args.poses is not None:
        if args.mesh is None or args.poses is None:
            raise ValueError("arguments '--mesh' and '--poses' must be given together")
        mesh_path, poses_path = Path(args.mesh), Path(args.poses)
    else:
        geometry = args.geometry or (sim_root / "ground_truth" if sim_root is not None else None)
        if geometry is None:
            raise ValueError(
                "no geometry: pass '--geometry DIR' or '--mesh MESH --poses POSES' (known-geometry mode)"
            )
        mesh_path, poses_path = Path(geometry) / "mesh_rest.obj", Path(geometry) / "static" / "poses.json"
    if not mesh_path.is_file():
        raise FileNotFoundError(f"mesh '{mesh_path}' does not exist")
    if not poses_path.is_file():
        raise ValueError(f"the capture has no poses: '{poses_path}' does not exist (pass '--poses')")
    resolution = args.texture_resolution
    if resolution is None:
        resolution = 512
        summary = (sim_root / "simulation.json") if sim_root is not None else None
        if summary is not None and summary.exists():
            resolution = int(json.loads(summary.read_text())["preset"]["texture_resolution"])
    return capture, mesh_path, poses_path, int(resolution)


def _load_geometry(ctx: ReconstructContext):
    from polarface.capture.store import CaptureStore
    from polarface.geometry.mesh import load_mesh
    from polarface.geometry.poses import load_poses

    store = CaptureStore.open(ctx.capture)
    mesh = load_mesh(ctx.mesh_path)
    poses = load_poses(ctx.poses_path)
    frames = [r.index for r in store.frames]
    if len(poses) != len(frames):
        raise ValueError(
            f"'{ctx.poses_path}' holds {len(poses)} poses but the capture has {len(frames)} frames"
        )
    return store, mesh, poses


def _read_result(out: Path) -> dict:
    path = out / "result.json"
    return json.loads(path.read_text(encoding="utf-8")) if path.exists() else {}


def _update_result(out: Path, stage: str, payload: dict, **top) -> None:
    from polarface.io import write_json_atomic

    result = _read_result(out)
    result.update(top)
    result.setdefault("stages", {})[stage] = payload
    write_json_atomic(out / "result.json", result)


def stage_prepare(ctx: ReconstructContext) -> dict:
    """Copy rig and mesh, write the result.json skeleton and unwrap the capture into ``unwrap.zarr``."""
    from polarface.geometry.mesh import save_obj
    from polarface.io import write_json_atomic
    from polarface.texture import UnwrapConfig, unwrap_capture

    started = time.perf_counter()
    store, mesh, poses = _load_geometry(ctx)
    config = UnwrapConfig(texture_resolution=ctx.texture_resolution, holdout_every=ctx.holdout_every)
    unwrap = unwrap_capture(store, mesh, poses, ctx.out / "unwrap.zarr", config, progress=ctx.progress)
    store.rig.save(ctx.out / "rig.json")
    save_obj(ctx.out / "mesh.obj", mesh)
    geometry = unwrap.geometry()
    valid = geometry.mask
    texel_size = float(np.median(0.5 * (geometry.texel_size_u[valid] + geometry.texel_size_v[valid])))
    calibration = store.rig.spectral.to_calibration() if store.rig.spectral is not None else None
    names = list(calibration.channel_names) if calibration is not None else [f"channel{i}" for i in range(6)]
    result = _read_result(ctx.out)
    result.update(
        {
            "format": "polarface-result",
            "version": 1,
            "channel_names": names,
            "texture_resolution": list(unwrap.resolution),
            "texel_size_mm": texel_size,
        }
    )
    result.setdefault("stages", {})
    write_json_atomic(ctx.out / "result.json", result)
    views = unwrap.views
    return {
        "views": len(views),
        "held_out_views": [i for i, v in enumerate(views) if v.held_out],
        "capture": str(ctx.capture),
        "mesh": str(ctx.mesh_path),
        "poses": str(ctx.poses_path),
        "timings": {"prepare_s": time.perf_counter() - started},
    }


def stage_polarimetric(ctx: ReconstructContext) -> dict:
    """Fit the polarimetric maps and write ``maps/``, ``previews/`` (checkpoints in ``checkpoints/``)."""
    from polarface.device import resolve_device
    from polarface.inverse.polarimetric import PolarimetricConfig, fit_polarimetric
    from polarface.texture import UnwrapStore

    started = time.perf_counter()
    device = resolve_device(ctx.device)
    config = PolarimetricConfig(**ctx.fit_options)
    unwrap = UnwrapStore.open(ctx.out / "unwrap.zarr")
    fit = fit_polarimetric(
        unwrap,
        config,
        device=device,
        checkpoint=ctx.out / "checkpoints" / "polarimetric.npz",
        progress=ctx.progress,
        stop_after_patches=ctx.stop_after_patches,
        threads=ctx.threads,
    )
    if not fit.complete:
        raise InterruptedError("polarimetric stage interrupted (checkpoint written; rerun with --resume)")
    write_maps(ctx.out, fit.maps, fit.mask, fit.view_count)
    np.save(ctx.out / "checkpoints" / "loss_curve.npy", np.asarray(fit.loss_curve))
    masked = {k: float(np.median(v[fit.mask])) for k, v in fit.maps.items() if v.ndim == 2}
    return {
        "config": _jsonable(dataclasses.asdict(config)),
        "device": str(device),
        "patches": fit.patches,
        "samples": fit.sample_count,
        "texels": int(fit.mask.sum()),
        "texels_below_min_views": int(((fit.view_count > 0) & (fit.view_count < config.min_views)).sum()),
        "texels_in_boundary_margin": int(((fit.view_count >= config.min_views) & ~fit.mask).sum()),
        "throughput_texel_view_iterations_per_s": fit.throughput,
        "final_loss": fit.loss_curve[-1] if fit.loss_curve else None,
        "median": masked,
        "timings": {**fit.timings, "stage_s": time.perf_counter() - started},
    }


def _jsonable(value):
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    return value


def write_maps(
    out: Path, maps: dict[str, np.ndarray], mask: np.ndarray, view_count: np.ndarray | None = None
) -> None:
    """Write ``maps/<name>.exr`` (GT conventions), ``maps/mask.png``, ``previews/<name>.png`` and, when
    given, ``maps/view_count.exr`` (fitting views per texel; the mask needs ``min_views`` of them)."""
    from polarface.io import colormap_png, write_exr, write_png

    names = _read_result(out).get("channel_names") or [f"channel{i}" for i in range(6)]
    for name in MAP_NAMES:
        write_exr(out / "maps" / f"{name}.exr", {"Y": maps[name].astype(np.float32)})
        values = maps[name][mask]
        vmin, vmax = (
            (float(np.percentile(values, 1)), float(np.percentile(values, 99))) if values.size else (0, 1)
        )
        colormap_png(
            out / "previews" / f"{name}.png",
            np.where(mask, maps[name], np.nan),
            vmin=vmin,
            vmax=vmax if vmax > vmin else vmin + 1e-6,
            mask=mask,
            title=name,
            colorbar=True,
        )
    rho = maps["rho_sss_bar"].astype(np.float32)
    write_exr(out / "maps" / "rho_sss_bar.exr", {n: rho[..., i] for i, n in enumerate(names)})
    write_png(out / "maps" / "mask.png", mask.astype(np.uint8) * 255)
    if view_count is not None:
        write_exr(out / "maps" / "view_count.exr", {"Y": view_count.astype(np.float32)})
        seen = view_count > 0
        colormap_png(
            out / "previews" / "view_count.png",
            np.where(seen, view_count, np.nan).astype(np.float64),
            vmin=0.0,
            vmax=float(max(view_count.max(), 1)),
            mask=seen,
            title="fitting views per texel",
            colorbar=True,
        )
    upper = rho[..., :3] if rho.shape[-1] >= 3 else np.repeat(rho[..., :1], 3, -1)
    preview = np.clip(upper / max(float(np.percentile(upper[mask], 99.5)) if mask.any() else 1.0, 1e-6), 0, 1)
    write_png(
        out / "previews" / "rho_sss_bar_rgb.png", np.where(mask[..., None], preview, 0.0).astype(np.float64)
    )


def stage_biophysical(ctx: ReconstructContext) -> dict:
    """Chromophore maps and diffusion profiles from ``maps/rho_sss_bar.exr`` (paper Sec. 5.3)."""
    from polarface.inverse.biophysical_stage import run_biophysical_stage

    return run_biophysical_stage(ctx.out, device=ctx.device, progress=ctx.progress)


def stage_report(ctx: ReconstructContext) -> dict:
    """Write ``report.html`` (:mod:`polarface.inverse.polarimetric_report`, plus the biophysical section)."""
    from polarface.inverse.biophysical_stage import report_section
    from polarface.inverse.polarimetric_report import write_report

    started = time.perf_counter()
    extra = [lambda page: report_section(page, ctx.out)] if (ctx.out / "maps" / "c_m.exr").is_file() else []
    write_report(ctx.out, extra_sections=extra)
    return {"timings": {"report_s": time.perf_counter() - started}}


#: The stages in order: (name, function).
STAGES: list[tuple[str, Callable[[ReconstructContext], dict]]] = [
    ("prepare", stage_prepare),
    ("polarimetric", stage_polarimetric),
    ("biophysical", stage_biophysical),
    ("report", stage_report),
]


def run_stages(ctx: ReconstructContext, stages=None) -> dict:
    """Run ``stages`` (default :data:`STAGES`) in order, skipping completed ones when resuming."""
    stages = STAGES if stages is None else stages
    for name, function in stages:
        done = _read_result(ctx.out).get("stages", {}).get(name, {}).get("complete", False)
        if ctx.resume and done:
            LOGGER.info("stage %s already complete; skipped", name)
            continue
        LOGGER.info("stage %s", name)
        payload = function(ctx)
        payload["complete"] = True
        _update_result(ctx.out, name, payload)
    return _read_result(ctx.out)


def run(args: argparse.Namespace) -> int:
    capture, mesh_path, poses_path, resolution = _resolve_inputs(args)
    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not args.resume:
        raise ValueError(
            f"output folder '{out}' exists and is not empty; pass '--resume' or choose another --out"
        )
    if args.holdout_every < 0 or args.holdout_every == 1:
        raise ValueError(f"argument '--holdout-every' must be 0 or >= 2; got {args.holdout_every}")
    options = {
        k: v
        for k, v in (
            ("iterations", args.iterations),
            ("lr", args.lr),
            ("optimizer", args.optimizer),
            ("refine_lobes_iterations", args.refine_lobes),
        )
        if v is not None
    }
    ctx = ReconstructContext(
        capture,
        out,
        mesh_path,
        poses_path,
        resolution,
        args.device or "auto",
        args.resume,
        not args.quiet,
        args.holdout_every,
        options,
        threads=args.threads,
    )
    created = not out.exists()
    try:
        # validate the inputs before anything is written
        from polarface.inverse.polarimetric import PolarimetricConfig

        PolarimetricConfig(**options)
        _load_geometry(ctx)
        out.mkdir(parents=True, exist_ok=True)
        result = run_stages(ctx)
    except (ValueError, FileNotFoundError):
        if created and out.exists():
            shutil.rmtree(out, ignore_errors=True)
        raise
    stage = result.get("stages", {}).get("polarimetric", {})
    print(
        f"polarface reconstruct: wrote {out} ({stage.get('texels', 0)} texels, "
        f"{stage.get('throughput_texel_view_iterations_per_s', 0):.3g} texel-view it/s)"
    )
    return 0
