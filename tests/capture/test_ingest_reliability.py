"""polarface ingest leaves nothing half-written: raw files checked first, failed runs cleaned, resume
after SIGKILL gives the same bytes as an uninterrupted run."""

from __future__ import annotations

import errno
import hashlib
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from polarface.capture.ingest import ingest_directory
from polarface.capture.rig import paper_rig
from polarface.capture.sensor import mosaic, simulate_raw
from polarface.capture.store import CaptureStore
from polarface.capture.synthetic import stokes_pattern
from polarface.io import write_png
from polarface.optics.stokes import intensities_from_stokes

WIDTH, HEIGHT = 48, 32
SRC = Path(__file__).resolve().parents[2] / "src"


def _rig():
    return paper_rig(width=WIDTH, height=HEIGHT)


def _raw(seed=0):
    stokes = stokes_pattern("face", HEIGHT, WIDTH, colour=True)
    return simulate_raw(
        mosaic(*np.moveaxis(intensities_from_stokes(stokes), -1, 0), sensor="color-polarization"), seed=seed
    )


def _raw_dir(tmp_path, frames=range(4), name="raw_in"):
    raw_dir = tmp_path / name
    for number in frames:
        for offset, cam in enumerate(("pol_upper", "pol_lower")):
            write_png(raw_dir / cam / f"{number:04d}.png", _raw(number + 100 * offset), bit_depth=16)
    return raw_dir


def _tree(root: Path) -> dict[str, str]:
    """Digest of every file of a store but ``ingest.json``, the run's record (seconds, pids differ)."""
    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != "ingest.json"
    }


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:200])


def _over_range(path: Path) -> None:
    write_png(path, np.full((HEIGHT, WIDTH), 65535, np.uint16), bit_depth=16)


@pytest.mark.parametrize(
    ("spoil", "message"),
    [
        (lambda p: write_png(p, _raw()[:, :40], bit_depth=16), "shape"),
        (lambda p: write_png(p, (_raw() // 16).astype(np.uint8)), "8-bit"),
        (_truncate, r"0003\.png"),
        (_over_range, "beyond bit_depth"),
    ],
    ids=["size", "8-bit", "truncated", "over-range"],
)
def test_bad_last_frame_names_the_file_and_writes_nothing(tmp_path, spoil, message):
    raw_dir = _raw_dir(tmp_path)
    bad = raw_dir / "pol_lower" / "0003.png"
    spoil(bad)
    with pytest.raises(ValueError, match=message) as info:
        ingest_directory(raw_dir, _rig(), tmp_path / "cap", progress=False)
    assert str(bad) in str(info.value) and "\n" not in str(info.value)
    assert not (tmp_path / "cap").exists()
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match=r"0003\.png"):
        ingest_directory(raw_dir, _rig(), empty, progress=False)
    assert empty.is_dir() and not list(empty.iterdir())


def test_write_error_removes_the_store_this_run_created(tmp_path, monkeypatch):
    raw_dir = _raw_dir(tmp_path, frames=range(3))
    original = CaptureStore.add_frame

    def full_disk(self, index, *args, **kwargs):
        if index == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return original(self, index, *args, **kwargs)

    monkeypatch.setattr(CaptureStore, "add_frame", full_disk)
    with pytest.raises(OSError, match="No space"):
        ingest_directory(raw_dir, _rig(), tmp_path / "cap", progress=False)
    assert not (tmp_path / "cap").exists()
    # resuming an existing store keeps its completed frames on a later error
    monkeypatch.undo()
    ingest_directory(_raw_dir(tmp_path, range(2), "two"), _rig(), tmp_path / "cap", progress=False)
    monkeypatch.setattr(CaptureStore, "add_frame", full_disk)
    with pytest.raises(OSError):
        ingest_directory(raw_dir, _rig(), tmp_path / "cap", progress=False)
    assert [f.index for f in CaptureStore.open(tmp_path / "cap").frames] == [0, 1]


def test_stale_temporaries_are_removed_on_resume(tmp_path):
    raw_dir = _raw_dir(tmp_path, frames=range(2))
    ingest_directory(raw_dir, _rig(), tmp_path / "cap", progress=False)
    stale = [
        tmp_path / "cap" / "raw" / "pol_upper" / ".tmp-000001-abc.png",
        tmp_path / "cap" / "frames" / ".tmp-000001-abc.json",
        tmp_path / "cap" / ".tmp-manifest-abc.json",
    ]
    for path in stale:
        path.write_bytes(b"half")
    ingest_directory(raw_dir, _rig(), tmp_path / "cap", progress=False)
    assert not any(p.exists() for p in stale)
    CaptureStore.open(tmp_path / "cap").validate(deep=True)
    # a folder a killed run left with only a temporary rig.json counts as empty
    killed = tmp_path / "killed"
    killed.mkdir()
    (killed / ".tmp-rig-abc.json").write_text("{")
    assert len(ingest_directory(raw_dir, _rig(), killed, progress=False).frames) == 2


_SCRIPT = """
import sys
from polarface.capture.ingest import ingest_directory
from polarface.capture.rig import paper_rig
ingest_directory(sys.argv[1], paper_rig(width=48, height=32), sys.argv[2], progress=False)
"""


def _run(raw_dir: Path, out: Path, kill_after: float | None = None) -> None:
    env = {**os.environ, "PYTHONPATH": f"{SRC}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    process = subprocess.Popen([sys.executable, "-c", _SCRIPT, str(raw_dir), str(out)], env=env)
    if kill_after is None:
        assert process.wait(timeout=300) == 0
        return
    deadline = time.monotonic() + 120
    while not (out / "frames" / "000001.json").exists() and process.poll() is None:
        assert time.monotonic() < deadline
        time.sleep(0.005)
    time.sleep(kill_after)
    process.send_signal(signal.SIGKILL)
    process.wait(timeout=60)


@pytest.mark.slow
def test_sigkill_then_resume_gives_the_same_store(tmp_path):
    raw_dir = _raw_dir(tmp_path, frames=range(8))
    _run(raw_dir, tmp_path / "straight")
    killed = tmp_path / "killed"
    _run(raw_dir, killed, kill_after=random.Random(os.getpid()).uniform(0.0, 0.3))
    _run(raw_dir, killed)
    assert _tree(killed) == _tree(tmp_path / "straight")


def test_resume_removes_a_chunk_left_half_written_by_zarr(tmp_path):
    """zarr writes a chunk as ``<key>.<uuid>.partial`` and renames it: a process killed in between
    leaves the ``.partial`` behind, which a resumed ingest removes."""
    raw_dir = _raw_dir(tmp_path, frames=range(2))
    _run(raw_dir, tmp_path / "straight")
    expected = _tree(tmp_path / "straight")
    chunk = next(p for p in sorted((tmp_path / "straight" / "derived.zarr").rglob("c/*")) if p.is_dir())
    stale = chunk / "0.1234abcd.partial"
    stale.write_bytes(b"half a chunk")
    _run(raw_dir, tmp_path / "straight")
    assert not stale.exists()
    assert _tree(tmp_path / "straight") == expected


@pytest.mark.parametrize(
    ("timestamps", "message"),
    [
        ("frame,timestamp_s\n0,0\n1,nan\n", r"timestamps\.csv' line 3"),
        ("frame,timestamp_s\n0,0\n1,inf\n", r"timestamps\.csv' line 3"),
        ("frame,timestamp_s\n0,1\n1,0.5\n", r"timestamps\.csv'.*decrease"),
    ],
)
def test_bad_timestamps_name_the_file_and_write_nothing(tmp_path, timestamps, message):
    raw_dir = _raw_dir(tmp_path, frames=range(2))
    (raw_dir / "timestamps.csv").write_text(timestamps)
    with pytest.raises(ValueError, match=message):
        ingest_directory(raw_dir, _rig(), tmp_path / "store", progress=False)
    assert not (tmp_path / "store").exists()


def test_infinite_fps_is_rejected(tmp_path):
    with pytest.raises(ValueError, match="fps"):
        ingest_directory(tmp_path, _rig(), tmp_path / "store", fps=float("inf"), progress=False)
