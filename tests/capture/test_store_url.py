"""The capture store at an fsspec URL (memory://, file://): the same content as a local store, resume,
stale temporaries removed, clear errors for bad URLs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from polarface.capture.rig import paper_rig
from polarface.capture.sensor import mosaic, simulate_raw
from polarface.capture.store import CaptureStore
from polarface.capture.synthetic import stokes_pattern
from polarface.io import UrlPath, storage_path
from polarface.optics.stokes import intensities_from_stokes
from polarface.results.fingerprint import capture_identity
from storage_fixtures import memory_keys

WIDTH, HEIGHT = 48, 32


def _raws(seed: int) -> dict[str, np.ndarray]:
    stokes = stokes_pattern("face", HEIGHT, WIDTH, colour=True)
    intensities = np.moveaxis(intensities_from_stokes(stokes), -1, 0)
    return {
        cam: simulate_raw(mosaic(*intensities, sensor="color-polarization"), seed=seed + offset)
        for cam, offset in (("pol_upper", 0), ("pol_lower", 100))
    }


def _write(root) -> CaptureStore:
    store = CaptureStore.create(root, paper_rig(width=WIDTH, height=HEIGHT), sequence="dynamic")
    store.add_frame(0, 0.0, _raws(0))
    store.add_frame(2, 0.1, _raws(1))
    store.finalize()
    return store


@pytest.fixture(scope="module")
def local_store(tmp_path_factory):
    return CaptureStore.open(_write(tmp_path_factory.mktemp("capture") / "cap").root)


@pytest.mark.parametrize("scheme", ["memory", "file"])
def test_a_store_at_a_url_round_trips(scheme, memory_url, tmp_path, local_store):
    url = f"{memory_url}/cap" if scheme == "memory" else f"file://{tmp_path}/cap"
    _write(url)
    opened = CaptureStore.open(url)
    assert isinstance(opened.root, UrlPath) == (scheme == "memory")
    assert str(opened.root) == (url if scheme == "memory" else f"{tmp_path}/cap")
    opened.validate(deep=True)
    local = local_store
    assert opened.rig == local.rig and opened.manifest == local.manifest
    for frame in local.frames:
        assert opened.has_frame(frame.index)
        for cam in frame.raw:
            np.testing.assert_array_equal(opened.read_raw(frame.index, cam), local.read_raw(frame.index, cam))
            np.testing.assert_array_equal(opened.stack(frame.index, cam), local.stack(frame.index, cam))
            np.testing.assert_array_equal(opened.mask(frame.index, cam), local.mask(frame.index, cam))
        np.testing.assert_array_equal(opened.spectral_stack(frame.index), local.spectral_stack(frame.index))
        np.testing.assert_array_equal(opened.spectral_valid(frame.index), local.spectral_valid(frame.index))
    region = (slice(4, 12), slice(0, 8))
    np.testing.assert_array_equal(opened.observation("dop", 2, "pol_lower", region),
                                  local.observation("dop", 2, "pol_lower", region))
    assert capture_identity(url)["sha256"] == capture_identity(local.root)["sha256"]


def test_resume_and_stale_temporaries_at_a_url(memory_url):
    url = f"{memory_url}/cap"
    _write(url)
    stale = storage_path(url) / "raw" / "pol_upper" / ".tmp-000004-abc.png"
    stale.write_bytes(b"half a png")
    store = CaptureStore.create(url, paper_rig(width=WIDTH, height=HEIGHT), sequence="dynamic")
    assert not stale.exists()
    assert not store.add_frame(2, 0.1, _raws(1))  # unchanged frame: skipped
    assert store.add_frame(2, 0.1, _raws(5))  # changed: rewritten whole
    np.testing.assert_array_equal(store.read_raw(2, "pol_upper"), _raws(5)["pol_upper"])
    assert not [key for key in memory_keys(url) if ".tmp-" in key]


def test_bad_urls_are_refused_naming_the_url(memory_url):
    with pytest.raises(ValueError, match="storage URL 'nosuchfs://b/cap'"):
        CaptureStore.open("nosuchfs://b/cap")
    with pytest.raises(FileNotFoundError, match="not a capture store"):
        CaptureStore.open(f"{memory_url}/nothing")


def test_ingest_and_info_commands_take_urls_but_not_process_private_ones(tmp_path, memory_url, capsys):
    """The CLI takes a URL that a later process can read (``file://`` here; ``s3://`` on a cluster) and
    refuses ``memory://`` (issue 47: exit 0 and nothing persisted); the library still writes a store at any
    URL, the same store as a local one."""
    from polarface.capture.ingest import ingest_directory
    from polarface.cli import main
    from polarface.io import write_png

    paper_rig(width=WIDTH, height=HEIGHT).save(tmp_path / "rig.json")
    for frame in range(2):
        for cam, raw in _raws(frame).items():
            write_png(tmp_path / "raw" / cam / f"{frame}.png", raw, bit_depth=16)
    ingest = ["ingest", str(tmp_path / "raw"), "--rig", str(tmp_path / "rig.json"), "--no-progress", "--out"]
    url = f"{memory_url}/cap"
    with pytest.raises(SystemExit) as info:
        main([*ingest, url])
    assert info.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error.startswith("polarface ingest: error: argument --out:") and url in error
    assert not memory_keys(memory_url)  # nothing written
    local = f"file://{tmp_path}/cap"
    assert main([*ingest, local]) == 0 and main([*ingest, local]) == 0  # its own store: resumed
    capsys.readouterr()
    remote = ingest_directory(tmp_path / "raw", paper_rig(width=WIDTH, height=HEIGHT), url, progress=False)
    stored = CaptureStore.open(tmp_path / "cap")
    assert remote.manifest == stored.manifest
    np.testing.assert_array_equal(remote.spectral_stack(1), stored.spectral_stack(1))
    assert main(["info", local, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["kind"] == "capture"
    with pytest.raises(SystemExit):
        main(["info", "nosuchfs://bucket/cap"])
    assert "argument PATH: storage URL 'nosuchfs://bucket/cap': unknown protocol" in capsys.readouterr().err
