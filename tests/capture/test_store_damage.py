"""A damaged capture store is refused in one line naming the file (issue 47): a chunk overwritten with
garbage (was ``RuntimeError: error during blosc decompression``), a deleted chunk (was read as NaN), damaged
zarr metadata, a truncated frame marker, a store of another sequence kind."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from polarface.capture.derived_chunks import touched_chunks
from polarface.capture.ingest import ingest_directory
from polarface.capture.rig import paper_rig
from polarface.capture.sensor import mosaic, simulate_raw
from polarface.capture.store import CaptureStore
from polarface.capture.synthetic import stokes_pattern
from polarface.io import write_png
from polarface.optics.stokes import intensities_from_stokes

WIDTH, HEIGHT = 48, 32


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> tuple[Path, Path]:
    """``(RAW_DIR, store)``: two frames of the paper rig's polarimetric cameras, ingested (read-only)."""
    root = tmp_path_factory.mktemp("store_damage")
    images = mosaic(*np.moveaxis(intensities_from_stokes(stokes_pattern("face", HEIGHT, WIDTH, colour=True)),
                                 -1, 0), sensor="color-polarization")
    for number in range(2):
        for offset, camera in enumerate(("pol_upper", "pol_lower")):
            raw = simulate_raw(images, seed=number + 10 * offset)
            write_png(root / "raw" / camera / f"{number}.png", raw, bit_depth=16)
    ingest_directory(root / "raw", paper_rig(width=WIDTH, height=HEIGHT), root / "store", progress=False)
    return root / "raw", root / "store"


@pytest.fixture
def store(built, tmp_path) -> Path:
    copy = tmp_path / "store"
    shutil.copytree(built[1], copy)
    return copy


def _one_line(info) -> str:
    text = str(info.value)
    assert "\n" not in text
    return text


@pytest.mark.parametrize(
    ("chunk", "read"),
    [
        ("stacks/pol_lower/c/1/2/0/0/0", lambda s: s.observation("i_sss", 1, "pol_lower")),
        ("spectral/stacks/c/1/3/0/0/0", lambda s: s.spectral_stack(1, (slice(0, 4), slice(0, 4)))),
        ("masks/pol_upper/c/1/0/0", lambda s: s.mask(1, "pol_upper")),
    ],
    ids=["stack", "spectral", "mask"],
)
def test_garbage_chunk_names_the_chunk_array_and_frame(store, chunk, read):
    path = store / "derived.zarr" / chunk
    if not path.exists():  # a mask of zeros is not written: write garbage in its place
        path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(np.random.default_rng(1).bytes(3000))
    with pytest.raises(ValueError) as info:
        read(CaptureStore.open(store))
    text = _one_line(info)
    assert f"'derived.zarr/{chunk}'" in text and "(frame 1)" in text and "cannot be decoded" in text
    assert "frames/000001.json" in text  # how to have the frame rewritten
    # the other frame still reads
    CaptureStore.open(store).stack(0, "pol_lower")


def test_deleted_chunk_is_named_not_read_as_nan(store):
    (store / "derived.zarr" / "stacks" / "pol_upper" / "c" / "0" / "3" / "0" / "0" / "0").unlink()
    opened = CaptureStore.open(store)
    with pytest.raises(ValueError, match=r"chunk 'derived\.zarr/stacks/pol_upper/c/0/3/0/0/0' of derived "
                                         r"array 'stacks/pol_upper' \(frame 0\) is missing") as info:
        opened.stack(0, "pol_upper")
    _one_line(info)
    assert np.isfinite(opened.stack(1, "pol_upper")).all()  # the other frame, the other camera still read
    assert np.isfinite(opened.stack(0, "pol_lower")).all()


def test_damaged_zarr_metadata_names_the_file(store):
    (store / "derived.zarr" / "stacks" / "pol_lower" / "zarr.json").write_text('{"shape": [')
    with pytest.raises(ValueError, match=r"array 'stacks/pol_lower'.*stacks/pol_lower/zarr\.json") as info:
        CaptureStore.open(store).stack(0, "pol_lower")
    _one_line(info)
    (store / "derived.zarr" / "zarr.json").write_text("garbage")
    with pytest.raises(ValueError, match=r"derived\.zarr/zarr\.json"):
        CaptureStore.open(store).stack(0, "pol_upper")


def test_truncated_frame_marker_names_the_file(built, store):
    marker = store / "frames" / "000001.json"
    marker.write_text(marker.read_text()[:40])
    raw_dir = built[0]
    with pytest.raises(ValueError, match=r"frame marker '.*frames/000001\.json' is not valid JSON") as info:
        ingest_directory(raw_dir, paper_rig(width=WIDTH, height=HEIGHT), store, progress=False)
    _one_line(info)
    with pytest.raises(ValueError, match=r"000001\.json"):
        CaptureStore.open(store).write_manifest()
    marker.unlink()  # as the message says: the frame is rewritten by a rerun
    resumed = ingest_directory(raw_dir, paper_rig(width=WIDTH, height=HEIGHT), store, progress=False)
    assert len(resumed.frames) == 2


def test_create_refuses_a_store_of_the_other_sequence(store):
    with pytest.raises(ValueError, match="holds a static sequence, not a dynamic one"):
        CaptureStore.create(store, paper_rig(width=WIDTH, height=HEIGHT), sequence="dynamic")


def test_touched_chunks():
    assert touched_chunks((4, 4, 32, 48), (1, 1, 16, 16), (2, slice(None), slice(10, 20), slice(0, 16))) == [
        (2, a, r, 0) for a in range(4) for r in (0, 1)]
    assert touched_chunks((4, 32), (1, 16), (1, slice(5, 5))) == []
