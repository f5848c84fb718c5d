"""Reading a capture store from a local path, a ``file://`` URL and fsspec's in-memory file system
(``memory://``): what the URL code path costs over the local one.

Usage:
    python benchmarks/bench_storage.py [--capture SIM/static] [--work DIR] [--repeats 5] [--json OUT.json]

Without ``--capture`` it simulates the tiny preset's static capture into ``--work`` (or reuses it). The
store is copied into ``memory://`` key by key; then, per location, the best of ``--repeats`` runs
(interleaved over the locations) of two jobs is taken:

* ``open``: :meth:`CaptureStore.open` with its validation (rig, manifest, every frame marker and raw
  file's header);
* ``read``: every frame's raw frames, I0/I45/I90/I135 stacks and masks of every polarimetric camera,
  and the merged six-channel stack (the unwrap stage's reads).

Prints seconds per job, megabytes read and the overhead of each URL over the local path (the arrays
read are checked equal to the local ones), and the file system calls each job makes on ``memory://``:
on object storage each is one request, whose latency (milliseconds) is what a URL adds there.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def _capture(work: Path) -> Path:
    from polarface.simulate.pipeline import SimulationConfig, simulate

    sim = work / "sim"
    if not (sim / "static" / "manifest.json").is_file():
        simulate(sim, SimulationConfig(preset="tiny", sequences=("static",)), progress=False)
    return sim / "static"


def _upload(local: Path, url: str) -> int:
    """Copy every file of ``local`` under ``url``; returns the bytes copied."""
    from polarface.io.storage import remove_tree, storage_path

    remove_tree(url)
    target, total = storage_path(url), 0
    for path in sorted(local.rglob("*")):
        if path.is_file():
            data = path.read_bytes()
            (target / path.relative_to(local).as_posix()).write_bytes(data)
            total += len(data)
    return total


def _read_all(location: str) -> list[np.ndarray]:
    from polarface.capture.store import CaptureStore

    store = CaptureStore.open(location)
    cameras = [c.id for c in store.rig.polarimetric_cameras()]
    arrays = []
    for frame in store.frames:
        for cam in frame.raw:
            arrays.append(store.read_raw(frame.index, cam))
        for cam in cameras:
            arrays += [store.stack(frame.index, cam), store.mask(frame.index, cam)]
        if store.spectral_reference is not None:
            arrays.append(store.spectral_stack(frame.index))
    return arrays


def _count_requests(job) -> dict[str, int]:
    """Calls of the in-memory file system's operations during ``job()`` (outermost calls only, per
    thread): on object storage each is one request (``cat_file``: GET, ``info``/``exists``/``isfile``/
    ``isdir``: HEAD, ``ls``/``glob``/``find``: LIST)."""
    import threading

    from fsspec.implementations.memory import MemoryFileSystem

    names = ("cat_file", "info", "exists", "isfile", "isdir", "ls", "glob", "find")
    counts, depth = dict.fromkeys(names, 0), threading.local()
    originals = {name: getattr(MemoryFileSystem, name) for name in names}

    def counting(name):
        def call(self, *args, **kwargs):
            level = getattr(depth, "level", 0)
            counts[name] += level == 0
            depth.level = level + 1
            try:
                return originals[name](self, *args, **kwargs)
            finally:
                depth.level = level
        return call

    for name in names:
        setattr(MemoryFileSystem, name, counting(name))
    try:
        job()
    finally:
        for name, original in originals.items():
            setattr(MemoryFileSystem, name, original)
    return {name: count for name, count in counts.items() if count}


def _timed(job) -> tuple[float, object]:
    started = time.perf_counter()
    value = job()
    return time.perf_counter() - started, value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--capture", type=Path, default=None, help="a capture store (default: tiny preset)")
    parser.add_argument("--work", type=Path, default=Path("bench_storage_work"))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    from polarface.capture.store import CaptureStore

    local = args.capture or _capture(args.work)
    size = _upload(local, "memory://bench-storage/capture")
    locations = {"local path": str(local), "file:// URL": f"file://{local.resolve()}",
                 "memory:// URL": "memory://bench-storage/capture"}
    reference = _read_all(str(local))  # also warms the page cache and the imports
    rows = {name: {"open_s": float("inf"), "read_s": float("inf"), "identical": True} for name in locations}
    for _ in range(args.repeats):  # interleaved, best of the repeats: the least disturbed run of each
        for name, location in locations.items():
            open_s, _ = _timed(lambda location=location: CaptureStore.open(location))
            read_s, arrays = _timed(lambda location=location: _read_all(location))
            row = rows[name]
            row["open_s"], row["read_s"] = min(row["open_s"], open_s), min(row["read_s"], read_s)
            row["identical"] &= all(np.array_equal(a, b) for a, b in zip(arrays, reference, strict=True))
            row["megabytes_read"] = sum(a.nbytes for a in arrays) / 1e6
    memory = locations["memory:// URL"]
    requests = {"open": _count_requests(lambda: CaptureStore.open(memory)),
                "read": _count_requests(lambda: _read_all(memory))}
    base = rows["local path"]
    print(f"capture '{local}': {size / 1e6:.1f} MB stored, {base['megabytes_read']:.1f} MB of arrays read")
    print(f"{'location':<15} {'open (s)':>9} {'read (s)':>9} {'read overhead':>14} {'identical':>10}")
    for name, row in rows.items():
        overhead = row["read_s"] / base["read_s"] - 1
        row["read_overhead"] = overhead
        print(f"{name:<15} {row['open_s']:>9.3f} {row['read_s']:>9.3f} {overhead:>13.0%} "
              f"{'yes' if row['identical'] else 'NO':>10}")
    for job, counts in requests.items():
        print(f"file system calls of '{job}' on memory:// (a request each on object storage): "
              f"{sum(counts.values())} {counts}")
    if args.json:
        payload = {"capture": str(local), "stored_bytes": size, "rows": rows, "requests": requests}
        args.json.write_text(json.dumps(payload, indent=1))


if __name__ == "__main__":
    main()
