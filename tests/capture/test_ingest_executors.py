"""``ingest`` with its frames as executor units: on Ray (2 workers of a local Ray instance) the store is
the local executor's byte for byte, the store's shared metadata is written by the submitting process
only, and a frame failing in its unit is named while the others complete."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

import polarface.capture.ingest as ingest_module
from polarface.capture.ingest import INGEST_JSON, IngestUnit, ingest_directory, run_ingest_unit
from polarface.capture.rig import paper_rig
from polarface.capture.sensor import mosaic, simulate_raw
from polarface.capture.store import CaptureStore
from polarface.capture.synthetic import stokes_pattern
from polarface.executors import LocalExecutor, RayExecutor
from polarface.io import write_png
from polarface.optics.stokes import intensities_from_stokes
from ray_fixtures import RAY_CPUS, ray_instance  # noqa: F401 (fixture)

WIDTH, HEIGHT = 48, 32
FRAMES = 6


def _rig():
    return paper_rig(width=WIDTH, height=HEIGHT)


@pytest.fixture(scope="module")
def raw_dir(tmp_path_factory) -> Path:
    """A RAW_DIR of :data:`FRAMES` frames of the two polarimetric cameras (noisy face pattern)."""
    root = tmp_path_factory.mktemp("ingest_executors") / "raw"
    stokes = stokes_pattern("face", HEIGHT, WIDTH, colour=True)
    signal = mosaic(*np.moveaxis(intensities_from_stokes(stokes), -1, 0), sensor="color-polarization")
    for number in range(FRAMES):
        for offset, camera in enumerate(("pol_upper", "pol_lower")):
            write_png(root / camera / f"{number:04d}.png", simulate_raw(signal, seed=number + 100 * offset),
                      bit_depth=16)
    return root


def _tree(root: Path) -> dict[str, str]:
    """Digests of every file of a store but its run record ``ingest.json`` (seconds and pids differ)."""
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and p.name != INGEST_JSON}


def test_ray_ingest_is_the_local_store_byte_for_byte(raw_dir, ray_instance, tmp_path):  # noqa: F811
    ingest_directory(raw_dir, _rig(), tmp_path / "local", progress=False)
    store = ingest_directory(raw_dir, _rig(), tmp_path / "ray", progress=False,
                             executor=RayExecutor(workers=RAY_CPUS))
    assert [f.index for f in store.frames] == list(range(FRAMES))
    assert _tree(tmp_path / "ray") == _tree(tmp_path / "local")
    CaptureStore.open(tmp_path / "ray").validate(deep=True)
    record = json.loads((tmp_path / "ray" / INGEST_JSON).read_text())
    units = record["executor"]["units"]
    assert record["executor"]["name"] == "ray" and sorted(units, key=int) == [str(f) for f in range(FRAMES)]
    assert all(unit["node_id"] and unit["written"] for unit in units.values())
    local = json.loads((tmp_path / "local" / INGEST_JSON).read_text())["executor"]
    assert local["name"] == "local" and local["units"]["0"]["node_id"] is None
    # resumed on Ray: every frame is found complete and skipped, nothing changes
    ingest_directory(raw_dir, _rig(), tmp_path / "ray", progress=False,
                     executor=RayExecutor(workers=RAY_CPUS))
    assert _tree(tmp_path / "ray") == _tree(tmp_path / "local")
    units = json.loads((tmp_path / "ray" / INGEST_JSON).read_text())["executor"]["units"]
    assert not any(unit["written"] for unit in units.values())


def test_a_unit_writes_its_frame_only(raw_dir, tmp_path):
    """A unit writes its raw files, chunks and marker; the arrays' metadata and the manifest are the
    submitting process's (sized before, rebuilt after)."""
    store = CaptureStore.create(tmp_path / "cap", _rig())
    store.reserve_frames(FRAMES)
    metadata = {p: p.read_bytes() for p in [*sorted((tmp_path / "cap").rglob("zarr.json")),
                                             tmp_path / "cap" / "manifest.json"]}
    files = tuple((camera, raw_dir / camera / "0003.png") for camera in ("pol_lower", "pol_upper"))
    assert run_ingest_unit(IngestUnit(tmp_path / "cap", 3, 0.15, files)) == {"written": True}
    assert {p: p.read_bytes() for p in metadata} == metadata  # nothing shared was rewritten
    assert store.has_frame(3) and CaptureStore.open_writer(tmp_path / "cap").sequence == "static"
    assert json.loads((tmp_path / "cap" / "manifest.json").read_text())["frames"] == []
    store.write_manifest()
    assert [f.index for f in store.frames] == [3] and np.isfinite(store.stack(3, "pol_upper")).all()


def test_a_frame_failing_in_its_unit_is_named_and_the_others_complete(raw_dir, tmp_path, monkeypatch):
    spoiled = tmp_path / "raw"
    for camera in ("pol_lower", "pol_upper"):
        for number in range(3):
            (spoiled / camera).mkdir(parents=True, exist_ok=True)
            (spoiled / camera / f"{number:04d}.png").write_bytes((raw_dir / camera / f"{number:04d}.png")
                                                                 .read_bytes())
    (spoiled / "pol_lower" / "0001.png").write_bytes(b"not a png")
    monkeypatch.setattr(ingest_module, "check_raw_files", lambda *args, **kwargs: None)  # let it reach a unit
    out = tmp_path / "cap"
    CaptureStore.create(out, _rig())  # a store being resumed: a failed run keeps its complete frames
    with pytest.raises(ValueError, match=r"1 frame\(s\) failed: frame 1: ") as info:
        ingest_directory(spoiled, _rig(), out, progress=False, executor=LocalExecutor())
    assert "\n" not in str(info.value)
    assert [f.index for f in CaptureStore.open(out, validate=False).frames] == [0, 2]
