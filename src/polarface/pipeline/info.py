"""What a folder holds (``polarface info PATH``): a capture store, a simulation folder, a RESULT folder or
an imported authors' session.

:func:`folder_info` reads only the small files (``manifest.json``, ``rig.json``, ``simulation.json``,
``result.json``, ``imported.json``, frame markers, directory listings) and never decodes images or zarr
arrays, so it is fast on any size of folder. :func:`format_info` renders its dict for people. Layouts:
``docs/capture_store.md`` (capture store), ``docs/simulate.md`` (simulation folder),
``docs/result_folder.md`` (RESULT folder) and ``docs/authors_dataset.md`` (imported session: its unwrap
stores are compared with the chunk inventory the import recorded, a listing).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from polarface.capture.manifest import DERIVED_ZARR, MANIFEST_JSON, read_manifest
from polarface.io import read_json_object
from polarface.pipeline.inputs import IMPORTED_JSON, imported_stores_problem, read_input_folder
from polarface.results import ResultFolder
from polarface.simulate.layout import GROUND_TRUTH, SEQUENCE_NAMES, SIMULATION_JSON

__all__ = ["folder_info", "format_info"]



def _fingerprint(*records: dict[str, Any]) -> Any:
    """The first ``fingerprint`` found at the top level or under ``config`` of ``records`` (else None)."""
    for record in records:
        for holder in (record, record.get("config") if isinstance(record.get("config"), dict) else {}):
            if "fingerprint" in holder:
                return holder["fingerprint"]
    return None


def _cameras(rig_path: Path) -> list[dict[str, Any]]:
    """``id``, ``role``, ``sensor`` and ``resolution`` ``[width, height]`` (px) of each rig camera."""
    if not rig_path.is_file():
        return []
    rig = read_json_object(rig_path)
    return [
        {"id": c.get("id"), "role": c.get("role"), "sensor": c.get("sensor"),
         "resolution": [c.get("width"), c.get("height")]}
        for c in rig.get("cameras", []) if isinstance(c, dict)
    ]


def capture_info(root: Path) -> dict[str, Any]:
    """Frames (listed, with a completion marker), cameras and resolutions of a capture store."""
    manifest = read_manifest(root / MANIFEST_JSON)
    frames = manifest["frames"]
    stamps = [float(f["timestamp"]) for f in frames]
    markers = sum((root / "frames" / f"{int(f['index']):06d}.json").is_file() for f in frames)
    return {
        "kind": "capture",
        "path": str(root),
        "sequence": manifest.get("sequence"),
        "complete": bool(manifest.get("complete", False)),
        "frames": len(frames),
        "frames_with_marker": int(markers),
        "frames_derived": sum(bool(f.get("derived")) for f in frames),
        "duration_s": (max(stamps) - min(stamps)) if stamps else 0.0,
        "demosaicing": sorted({str(f.get("method")) for f in frames if f.get("method")}),
        "cameras": _cameras(root / "rig.json"),
        "derived_store": (root / str(manifest.get("derived_store", DERIVED_ZARR))).is_dir(),
        "fingerprint": _fingerprint(manifest),
    }


def imported_info(root: Path) -> dict[str, Any]:
    """Kind, frames, views, texture, cameras and state of an imported authors' session (``stores``: None
    when the import recorded no inventory or is unfinished, else ``"intact"`` or what differs)."""
    record = read_json_object(root / IMPORTED_JSON)
    complete = record.get("complete") is True
    stores = None
    if complete and isinstance(record.get("stores"), dict):
        stores = imported_stores_problem(root, record) or "intact"
    return {
        "kind": "imported",
        "path": str(root),
        "sequence": record.get("kind"),
        "complete": complete,
        "session": record.get("session"),
        "frames": len(record.get("frames") or []),
        "views": record.get("views"),
        "texture_resolution": record.get("texture_resolution"),
        "cameras": _cameras(root / "rig.json"),
        "stores": stores,
        "seconds": record.get("seconds"),
    }


def _map_files(maps_dir: Path) -> list[str]:
    return sorted(p.name for p in maps_dir.iterdir() if p.is_file()) if maps_dir.is_dir() else []


def simulation_info(root: Path) -> dict[str, Any]:
    """Configuration, timings, sequences (as :func:`capture_info`) and ground-truth maps of a simulation."""
    summary = read_json_object(root / SIMULATION_JSON) if (root / SIMULATION_JSON).is_file() else {}
    timings = summary.get("timings", {})
    return {
        "kind": "simulation",
        "path": str(root),
        "complete": bool(summary),
        "configuration": summary.get("config", {}),
        "channel_names": summary.get("channel_names", []),
        "seconds": timings.get("total_s") if isinstance(timings, dict) else None,
        "timings_s": timings,
        "peak_rss_mb": summary.get("peak_rss_mb"),
        "sequences": {
            name: capture_info(root / name)
            for name in SEQUENCE_NAMES
            if (root / name / MANIFEST_JSON).is_file()
        },
        "ground_truth_maps": _map_files(root / GROUND_TRUTH / "maps"),
        "fingerprint": _fingerprint(summary),
    }


def _stage_seconds(record: dict[str, Any]) -> float | None:
    """A stage's wall time (s): ``total_s`` or ``stage_s`` of its timings, or their only entry."""
    timings = record.get("timings") or record.get("timings_s") or {}
    if not isinstance(timings, dict):
        return None
    for key in ("total_s", "stage_s"):
        if isinstance(timings.get(key), int | float):
            return float(timings[key])
    numbers = [v for v in timings.values() if isinstance(v, int | float)]
    return float(numbers[0]) if len(numbers) == 1 else None


def _dynamic_frames(record: Any, frame_folders: list[str]) -> dict[str, Any] | None:
    """The dynamic frames of a RESULT: ``frames`` (count), ``done`` (count with maps), ``failed``
    ``{index: reason}``, from ``stages.dynamic`` (None when it has no such record nor frame folder)."""
    if not isinstance(record, dict) or not record:
        return {"frames": len(frame_folders), "done": None, "failed": {}} if frame_folders else None
    failed = record.get("failed_frames") if isinstance(record.get("failed_frames"), dict) else {}
    frames, completed = record.get("frames"), record.get("completed")
    return {
        "frames": len(frames) if isinstance(frames, list) else len(frame_folders),
        "done": len(completed) if isinstance(completed, list) else None,
        "failed": {str(k): str(v) for k, v in failed.items()},
    }


def result_info(root: Path) -> dict[str, Any]:
    """Header, stages done (with their times), maps, previews, report and configuration of a RESULT."""
    folder = ResultFolder(root)
    result = folder.read_result()
    stages = result.get("stages", {}) if isinstance(result.get("stages"), dict) else {}
    frames_dir = root / "frames"
    frames = sorted(p.name for p in frames_dir.iterdir() if p.is_dir()) if frames_dir.is_dir() else []
    previews = sorted(folder.previews_dir.glob("*.png")) if folder.previews_dir.is_dir() else []
    return {
        "kind": "result",
        "path": str(root),
        "format": result.get("format"),
        "version": result.get("version"),
        "channel_names": result.get("channel_names", []),
        "texture_resolution": result.get("texture_resolution"),
        "texel_size_mm": result.get("texel_size_mm"),
        "stages": {
            name: {"complete": bool(rec.get("complete", False)), "seconds": _stage_seconds(rec)}
            | ({"skipped": rec["skipped"]} if rec.get("skipped") else {})
            for name, rec in stages.items() if isinstance(rec, dict)
        },
        "texels": stages.get("polarimetric", {}).get("texels"),
        "maps": _map_files(folder.maps_dir),
        "previews": len(previews),
        "report": folder.report_path.name if folder.report_path.is_file() else None,
        "frames": frames,
        "dynamic": _dynamic_frames(stages.get("dynamic"), frames),
        "configuration": {
            name: rec["config"] for name, rec in stages.items() if isinstance(rec, dict) and "config" in rec
        },
        "fingerprint": _fingerprint(result, *[r for r in stages.values() if isinstance(r, dict)]),
    }


#: Folder kind (:data:`polarface.pipeline.inputs.INPUT_KINDS`) -> its description, in the order tried.
_DESCRIBERS = {
    "result": result_info,
    "capture": capture_info,
    "imported": imported_info,
    "simulation": simulation_info,
}


def folder_info(path: str | Path) -> dict[str, Any]:
    """What ``path`` holds, as a JSON-ready dict with ``kind`` = ``capture``, ``simulation``, ``result`` or
    ``imported``.

    The kind is :func:`polarface.pipeline.inputs.read_input_folder`'s (a RESULT has ``result.json``, a
    capture store ``manifest.json``, an imported authors' session ``imported.json``, a simulation folder
    ``simulation.json`` or a ``static/``/``dynamic/`` capture store beside ``ground_truth/``).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: ``path`` is none of the four, or one of its JSON files is malformed (named).
    """
    folder = read_input_folder(path, tuple(_DESCRIBERS))
    return _DESCRIBERS[folder.kind](folder.root)


def _number(value: Any, unit: str = "") -> str:
    if isinstance(value, float):
        return f"{value:.3g}{unit}"
    return "?" if value is None else f"{value}{unit}"


def _flat(config: Any, prefix: str = "") -> list[str]:
    """``key=value`` strings of a nested configuration dict (lists shown compactly)."""
    if not isinstance(config, dict):
        return [f"{prefix}={config}"] if prefix else [str(config)]
    out: list[str] = []
    for key, value in config.items():
        name = f"{prefix}.{key}" if prefix else str(key)
        out += _flat(value, name) if isinstance(value, dict) else [f"{name}={json.dumps(value)}"]
    return out


def _wrapped(head: str, items: list[str], indent: str = "  ") -> list[str]:
    """``head`` followed by comma-separated ``items``, wrapped at 100 columns."""
    import textwrap

    text = f"{indent}{head}: {', '.join(items) or 'none'}"
    return textwrap.wrap(text, 100, subsequent_indent=indent + "    ", break_on_hyphens=False,
                         break_long_words=False) or [text]


def _capture_lines(info: dict[str, Any], indent: str = "  ") -> list[str]:
    state = "complete" if info["complete"] else "INCOMPLETE"
    lines = [
        f"{indent}sequence {info['sequence']} ({state}): {info['frames']} frames "
        f"({info['frames_with_marker']} with a completion marker, {info['frames_derived']} demosaiced"
        f"{', ' + '/'.join(info['demosaicing']) if info['demosaicing'] else ''}), "
        f"{_number(info['duration_s'], ' s')} long",
    ]
    return lines + _camera_lines(info["cameras"], indent)


def _camera_lines(cameras: list[dict[str, Any]], indent: str) -> list[str]:
    """``cameras (N):`` and one line per camera: id, role, sensor, resolution."""
    lines = [f"{indent}cameras ({len(cameras)}):"]
    for cam in cameras:
        width, height = cam["resolution"]
        lines.append(f"{indent}  {cam['id']:<12} {cam['role'] or '?':<14} {cam['sensor'] or '?':<20} "
                     f"{width} x {height} px")
    return lines


def _result_lines(info: dict[str, Any]) -> list[str]:
    resolution = info["texture_resolution"] or ["?", "?"]
    lines = [
        f"  {info['format']} v{info['version']}: texture {resolution[0]} x {resolution[1]} texels, texel "
        f"{_number(info['texel_size_mm'], ' mm')}, {_number(info['texels'])} texels fitted",
        f"  channels: {', '.join(info['channel_names']) or '?'}",
        "  stages:" if info["stages"] else "  stages: none done",
    ]
    for name, stage in info["stages"].items():
        state = "done" if stage["complete"] else "not complete"
        detail = f"skipped: {stage['skipped']}" if stage.get("skipped") else _number(stage["seconds"], " s")
        lines.append(f"    {name:<14} {state:<13} {detail}")
    lines += _wrapped(f"maps ({len(info['maps'])})", info["maps"])
    lines.append(f"  previews: {info['previews']} PNG; report: {info['report'] or 'not written'}")
    if info["frames"]:
        lines.append(f"  frames: {len(info['frames'])} ({info['frames'][0]} .. {info['frames'][-1]})")
    dynamic = info.get("dynamic")
    if dynamic:
        failed = [f"{t} ({reason})" for t, reason in dynamic["failed"].items()]
        lines += _wrapped(f"dynamic frames: {dynamic['frames']}, done {_number(dynamic['done'])}, "
                          f"failed {len(failed)}", failed)
    for name, config in info["configuration"].items():
        lines += _wrapped(f"configuration of {name}", _flat(config))
    return lines


def _imported_lines(info: dict[str, Any]) -> list[str]:
    state = "complete" if info["complete"] else "INTERRUPTED (rerun 'polarface import-authors' to finish)"
    resolution = info["texture_resolution"] or ["?", "?"]
    stores = {None: "not checked (no inventory recorded)", "intact": "as the import wrote them"}.get(
        info["stores"], f"CHANGED: {info['stores']}")
    lines = [
        f"  {info['sequence']} session ({state}) from {info['session']}",
        f"  {info['frames']} frames, {info['views'] if info['views'] is not None else '?'} views, texture "
        f"{resolution[0]} x {resolution[1]} texels",
        f"  unwrap stores: {stores}",
    ]
    return lines + _camera_lines(info["cameras"], "  ")


def format_info(info: dict[str, Any]) -> str:
    """The human-readable text of a :func:`folder_info` dict (several lines, no trailing newline)."""
    kind = info["kind"]
    titles = {"capture": "capture store", "simulation": "simulation folder", "imported": "imported session"}
    lines = [f"{titles.get(kind, 'RESULT folder')} {info['path']}"]
    if kind == "capture":
        lines += _capture_lines(info)
    elif kind == "imported":
        lines += _imported_lines(info)
    elif kind == "simulation":
        seconds, memory = _number(info["seconds"], " s"), _number(info["peak_rss_mb"], " MB")
        lines.append(
            f"  simulated in {seconds}, peak memory {memory}"
            if info["complete"]
            else "  no simulation.json (not written by polarface simulate, or interrupted)"
        )
        lines.append(f"  channels: {', '.join(info['channel_names']) or '?'}")
        for name, sequence in info["sequences"].items():
            lines.append(f"  {name}/:")
            lines += _capture_lines(sequence, "    ")
        maps = info["ground_truth_maps"]
        lines += _wrapped(f"ground truth maps ({len(maps)})", maps)
        if info["configuration"]:
            lines += _wrapped("configuration", _flat(info["configuration"]))
    else:
        lines += _result_lines(info)
    if info.get("fingerprint") is not None:
        lines.append(f"  fingerprint: {info['fingerprint']}")
    return "\n".join(lines)
