"""The dynamic stage on an imported authors' dynamic session (``polarface import-authors 6_Dynamic_1``).

The authors' dynamic module carries each frame's tracked geometry as UV-space maps in the rig world
(``docs/authors_dataset.md``), so the stereo, alignment and tracking steps of
:mod:`polarface.pipeline.dynamic.stage` are skipped: per selected frame the imported unwrap store
(``DIR/frames/NNNN/unwrap.zarr``) is copied into ``RESULT/frames/NNNN`` and step 4 of that module runs
unchanged (dynamic fit with eta and the roughnesses of the static RESULT, chromophores, render), with the
frame's texel-grid mesh in the world frame and the identity as alignment. Frames run in this process, in
order; each resumes as in the capture path. Timestamps assume the rig's 20 fps (paper Sec. 4).
"""

from __future__ import annotations

import resource
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from polarface.device import resolve_device
from polarface.executors import check_thread_count
from polarface.geometry.mesh import load_mesh
from polarface.io import record_path
from polarface.pipeline.dynamic.config import DynamicStageConfig
from polarface.pipeline.dynamic.frames import frame_done, load_static_inputs, process_frame
from polarface.pipeline.inputs import (
    check_static_result,
    copy_unwrap_store,
    parse_frame_selection,
    read_imported,
)
from polarface.results import ResultFolder

__all__ = ["FRAME_RATE_HZ", "reconstruct_dynamic_imported"]

#: Frame rate of the rig (paper Sec. 4), for the frames' timestamps.
FRAME_RATE_HZ = 20.0


def reconstruct_dynamic_imported(
    result_dir: str | Path,
    imported: Path,
    config: DynamicStageConfig | None = None,
    *,
    frames: str | Sequence[int] | None = None,
    device: str = "auto",
    threads: int | None = 1,
    progress: bool = True,
) -> dict[str, Any]:
    """Fit the frames of an imported dynamic session into the static RESULT ``result_dir`` (module
    docstring); returns ``result.json``'s ``stages.dynamic`` record (keys of
    :func:`polarface.pipeline.dynamic.stage.reconstruct_dynamic`).

    Raises:
        ValueError: ``threads`` < 1, no static result, not a finished dynamic import, a texture size other
            than the static maps', or a bad selection (``parse_frame_selection``).
    """
    started = time.perf_counter()
    config = config or DynamicStageConfig()
    check_thread_count(threads)
    folder = ResultFolder(result_dir)
    check_static_result(folder)
    record = read_imported(imported, "dynamic")
    all_frames = list(range(len(record["frames"])))
    selected = parse_frame_selection(frames, all_frames)
    static = load_static_inputs(folder)
    if list(static.mask.shape) != list(record["texture_resolution"]):
        raise ValueError(f"'{imported}' has texture {record['texture_resolution']} but the static maps of "
                         f"'{folder.root}' are {list(static.mask.shape)}: import the sessions of one subject")
    resolved = resolve_device(device)
    identity = np.eye(4)
    previous = folder.stage_record("dynamic").get("timings", {}).get("frames", {})
    per_frame: dict[str, dict[str, float]] = {}
    failed: dict[str, str] = {}
    for frame in tqdm(selected, desc="dynamic: frames", unit="frame", disable=not progress):
        frame_folder = folder.frame(frame)
        if frame_done(frame_folder, config):
            if str(frame) in previous:
                per_frame[str(frame)] = previous[str(frame)]
            continue
        begun = time.perf_counter()
        source = Path(imported) / "frames" / f"{frame:04d}"
        try:
            frame_folder.root.mkdir(parents=True, exist_ok=True)
            if not Path(frame_folder.unwrap_path).is_dir():
                copy_unwrap_store(source / "unwrap.zarr", Path(frame_folder.unwrap_path))
            mesh = load_mesh(source / "mesh.obj")
            timings = process_frame(None, folder, frame, all_frames, mesh, identity, static, config,
                                     resolved, threads)
        except (ValueError, FileNotFoundError, RuntimeError) as exc:
            failed[str(frame)] = str(exc)
            continue
        frame_folder.update_result({"frame": frame, "timestamp_s": frame / FRAME_RATE_HZ})
        per_frame[str(frame)] = {**timings, "total_s": time.perf_counter() - begun}
    completed = [f for f in selected if str(f) not in failed and frame_done(folder.frame(f), config)]
    totals = [v["total_s"] for v in per_frame.values()]
    summary = {
        "capture": record_path(folder.root, imported),
        "imported": record["session"],
        "frames": all_frames,
        "selected": selected,
        "completed": completed,
        "failed_frames": failed,
        "anchors": [],
        "timestamps_s": {str(f): f / FRAME_RATE_HZ for f in all_frames},
        "alignment": identity.tolist(),
        "timings": {"geometry_s": 0.0, "tracking_s": 0.0, "frames": per_frame,
                    "stage_s": time.perf_counter() - started},
        "seconds_per_frame": float(np.mean(totals)) if totals else 0.0,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "config": config.to_json(),
        "executor": {"name": "local", "units": {}},
    }
    folder.record_stage("dynamic", summary)
    return folder.stage_record("dynamic")
