"""polarface ingest refuses inputs it would store wrongly (issue 47's bad-input campaign): frames sharing a
timestamp, a rerun into its own store from another raw sequence (the same one resumes), and a truncated
raw frame reported in one line."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from polarface.capture.ingest import ingest_directory
from polarface.capture.rig import paper_rig
from polarface.capture.sensor import mosaic, simulate_raw
from polarface.capture.store import CaptureStore
from polarface.capture.synthetic import stokes_pattern
from polarface.cli import main
from polarface.io import write_png
from polarface.optics.stokes import intensities_from_stokes

WIDTH, HEIGHT = 48, 32
CAMERAS = ("pol_upper", "pol_lower")


def _rig():
    return paper_rig(width=WIDTH, height=HEIGHT)


def _raw_dir(root: Path, seed: int = 0, frames=range(3)) -> Path:
    stokes = stokes_pattern("smooth", HEIGHT, WIDTH, colour=True)
    images = mosaic(*np.moveaxis(intensities_from_stokes(stokes), -1, 0), sensor="color-polarization")
    for number in frames:
        for offset, camera in enumerate(CAMERAS):
            raw = simulate_raw(images, seed=seed + number + 100 * offset)
            write_png(root / camera / f"{number:04d}.png", raw, bit_depth=16)
    return root


def _tree(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and p.name != "ingest.json"}


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    """``(raw_a, raw_b, store)``: two raw sequences of the same frame numbers, ``raw_a`` ingested."""
    root = tmp_path_factory.mktemp("ingest_inputs")
    raw_a, raw_b = _raw_dir(root / "raw_a", seed=0), _raw_dir(root / "raw_b", seed=50)
    _rig().save(root / "rig.json")
    ingest_directory(raw_a, _rig(), root / "store", progress=False)
    return raw_a, raw_b, root / "store"


def _cli(raw_dir: Path, out: Path, *extra: str) -> int:
    return main(["ingest", str(raw_dir), "--rig", str(raw_dir.parent / "rig.json"), "--out", str(out),
                 "--no-progress", *extra])


@pytest.mark.parametrize(
    ("timestamps", "message"),
    [
        ("frame,timestamp_s\n0,0.0\n1,0.0\n2,0.1\n",
         r"timestamps\.csv' line 3: frame 1 has the timestamp of frame 0"),
        ("frame,timestamp_s\n0,0.0\n1,0.05\n1,0.06\n2,0.1\n",
         r"timestamps\.csv' line 4: frame 1 is listed again"),
    ],
    ids=["shared-timestamp", "frame-twice"],
)
def test_duplicate_timestamps_are_refused_naming_the_frames(tmp_path, capsys, timestamps, message):
    raw_dir = _raw_dir(tmp_path / "raw")
    _rig().save(tmp_path / "rig.json")
    (raw_dir / "timestamps.csv").write_text(timestamps)
    with pytest.raises(ValueError, match=message):
        ingest_directory(raw_dir, _rig(), tmp_path / "store", progress=False)
    assert _cli(raw_dir, tmp_path / "store") == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "timestamps.csv" in error[0]
    assert not (tmp_path / "store").exists()


def test_a_frame_file_twice_names_both_files(tmp_path):
    raw_dir = _raw_dir(tmp_path / "raw", frames=range(1))
    (raw_dir / "pol_upper" / "0000.png").rename(raw_dir / "pol_upper" / "0.png")
    _raw_dir(tmp_path / "raw", frames=range(1))
    with pytest.raises(ValueError, match=r"frame 0 appears twice .*0\.png.*0000\.png"):
        ingest_directory(raw_dir, _rig(), tmp_path / "store", progress=False)


def test_rerun_with_another_raw_sequence_is_refused_and_the_same_resumes(stored, tmp_path, capsys):
    raw_a, raw_b, original = stored
    store = tmp_path / "store"
    import shutil

    shutil.copytree(original, store)
    before = _tree(store)
    with pytest.raises(ValueError, match=r"ingested from other inputs: frame 0 of camera 'pol_lower' holds "
                                         r"other raw data than '.*raw_b/pol_lower/0000\.png'.*--force"):
        ingest_directory(raw_b, _rig(), store, progress=False)
    assert _cli(raw_b, store) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "raw_b" in error[0] and "--force" in error[0]
    for options, message in (({"fps": 10.0}, "frame 1 has timestamp 0.05 s, not 0.1 s"),
                             ({"method": "bilinear"}, "demosaiced with 'residual', not 'bilinear'"),
                             ({"sequence": "dynamic"}, "holds a static sequence, not a dynamic one")):
        with pytest.raises(ValueError, match=message):
            ingest_directory(raw_a, _rig(), store, progress=False, **options)
    with pytest.raises(ValueError, match=r"holds frame\(s\) \[2\], which RAW_DIR lacks"):
        ingest_directory(_raw_dir(tmp_path / "raw_two", frames=range(2)), _rig(), store, progress=False)
    assert _tree(store) == before  # nothing of it was touched
    # the same raw sequence resumes (every frame skipped), and --force replaces the store
    assert len(ingest_directory(raw_a, _rig(), store, progress=False).frames) == 3
    assert _tree(store) == before
    assert _cli(raw_b, store, "--force") == 0
    capsys.readouterr()
    assert _tree(store) != before and len(CaptureStore.open(store).frames) == 3


def _truncate_to(size: int):
    def spoil(path: Path) -> None:
        data = path.read_bytes()
        path.write_bytes(data[: size if size >= 0 else len(data) + size])

    return spoil


@pytest.mark.parametrize(
    "spoil",
    [
        _truncate_to(200),
        _truncate_to(20),  # OpenCV's logger printed a line of its own (now silenced by polarface.io.images)
        _truncate_to(-10),  # libpng printed 'libpng error: Read Error' itself (now held by io.images)
    ],
    ids=["middle", "header", "tail"],
)
@pytest.mark.parametrize("force", [False, True], ids=["new", "force"])
def test_truncated_raw_frame_is_one_error_line(stored, tmp_path, capfd, spoil, force):
    raw_a, _, original = stored
    raw_dir = tmp_path / "raw"
    import shutil

    shutil.copytree(raw_a, raw_dir)
    shutil.copy(raw_a.parent / "rig.json", tmp_path / "rig.json")
    bad = raw_dir / "pol_lower" / "0002.png"
    spoil(bad)
    out = tmp_path / "store"
    if force:
        shutil.copytree(original, out)
    capfd.readouterr()
    assert _cli(raw_dir, out, *(["--force"] if force else [])) == 2
    captured = capfd.readouterr()
    lines = [line for line in (captured.err + captured.out).splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("polarface ingest: error:") and str(bad) in lines[0], lines
    assert lines[0].count(str(bad)) == 1
    assert out.exists() == force
