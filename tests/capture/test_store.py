"""polarface.capture.store and ingest: layout, resume, validation errors, nothing half-written."""

from __future__ import annotations

import json

import numpy as np
import pytest

from polarface.capture.ingest import ingest_directory, scan_raw_directory
from polarface.capture.rig import paper_rig
from polarface.capture.sensor import mosaic, simulate_raw
from polarface.capture.store import CaptureStore
from polarface.capture.synthetic import stokes_pattern
from polarface.io import write_png
from polarface.optics.stokes import intensities_from_stokes

WIDTH, HEIGHT = 48, 32


def _rig():
    return paper_rig(width=WIDTH, height=HEIGHT)


def _raw(seed=0, scale=1.0):
    stokes = stokes_pattern("face", HEIGHT, WIDTH, colour=True) * scale
    return simulate_raw(
        mosaic(*np.moveaxis(intensities_from_stokes(stokes), -1, 0), sensor="color-polarization"), seed=seed
    )


def _raws(seed=0):
    return {"pol_upper": _raw(seed), "pol_lower": _raw(seed + 100)}


def test_write_read_roundtrip(tmp_path):
    store = CaptureStore.create(tmp_path / "cap", _rig(), sequence="dynamic")
    assert store.add_frame(0, 0.0, _raws(0))
    assert store.add_frame(2, 0.1, _raws(1))
    manifest = store.finalize()
    assert manifest["frame_count"] == 2 and manifest["complete"] and manifest["sequence"] == "dynamic"
    opened = CaptureStore.open(tmp_path / "cap")
    assert [f.index for f in opened.frames] == [0, 2]
    assert opened.frames[1].raw["pol_upper"] == "raw/pol_upper/000002.png"
    np.testing.assert_array_equal(opened.read_raw(2, "pol_upper"), _raws(1)["pol_upper"])
    stack = opened.stack(2, "pol_upper")
    assert stack.shape == (4, HEIGHT, WIDTH, 3) and stack.dtype == np.float32
    region = opened.observation("i_sss", 2, "pol_lower", region=(slice(4, 12), slice(0, 8)))
    np.testing.assert_allclose(region, 2 * opened.stack(2, "pol_lower")[2, 4:12, :8], rtol=1e-6)
    assert opened.mask(0, "pol_upper").dtype == np.uint8
    assert opened.observation("aolp", 0, "pol_upper").max() < np.pi
    opened.validate(deep=True)
    assert not list((tmp_path / "cap").rglob(".tmp-*"))
    # six spectral channels on the reference (pol_upper) grid
    assert opened.spectral_reference == "pol_upper"
    six = opened.spectral_stack(2)
    assert six.shape == (4, HEIGHT, WIDTH, 6)
    np.testing.assert_array_equal(six[..., 0], stack[..., 0])  # pol_upper R -> channel 0
    valid = opened.spectral_valid(2)
    assert valid.mean() > 0.6
    lower_r = six[..., 3][:, valid]  # pol_lower R registered by the plane fallback
    assert np.isfinite(lower_r).all() and lower_r.mean() > 0
    dop6 = opened.spectral_observation("dop", 2)
    assert dop6.shape == (HEIGHT, WIDTH, 6)


def test_resume_skips_completed_frames(tmp_path):
    rig = _rig()
    store = CaptureStore.create(tmp_path / "cap", rig)
    assert store.add_frame(0, 0.0, _raws(0))
    again = CaptureStore.create(tmp_path / "cap", rig)
    assert not again.add_frame(0, 0.0, _raws(0))  # same content: skipped
    assert again.add_frame(0, 0.0, _raws(5))  # new content: rewritten
    np.testing.assert_array_equal(again.read_raw(0, "pol_upper"), _raws(5)["pol_upper"])
    assert [f.index for f in again.frames] == [0] and not again.manifest["complete"]
    with pytest.raises(ValueError, match="different rig"):
        CaptureStore.create(tmp_path / "cap", paper_rig(width=64, height=32))


def test_crash_leaves_no_trusted_frame(tmp_path, monkeypatch):
    store = CaptureStore.create(tmp_path / "cap", _rig())
    store.add_frame(0, 0.0, _raws(0))

    def boom(*args, **kwargs):
        raise RuntimeError("simulated crash")

    monkeypatch.setattr(CaptureStore, "_write_derived", boom)
    with pytest.raises(RuntimeError):
        store.add_frame(0, 0.0, _raws(7))  # rewriting frame 0 crashes half-way
    with pytest.raises(RuntimeError):
        store.add_frame(1, 0.05, _raws(8))
    monkeypatch.undo()
    assert not (tmp_path / "cap" / "frames" / "000000.json").exists()
    assert not (tmp_path / "cap" / "frames" / "000001.json").exists()
    with pytest.raises(ValueError, match="not in the manifest"):
        store.finalize()  # the raw PNGs of the crashed frames exist but no frame trusts them
    resumed = CaptureStore.create(tmp_path / "cap", _rig())
    resumed.add_frame(0, 0.0, _raws(7))
    resumed.add_frame(1, 0.05, _raws(8))
    resumed.finalize()
    assert [f.index for f in CaptureStore.open(tmp_path / "cap").frames] == [0, 1]


@pytest.mark.parametrize(
    ("raws", "message"),
    [
        ({"pol_upper": _raw()}, "missing for polarimetric camera"),
        ({**_raws(), "ghost": _raw()}, "'ghost' is not in the rig"),
        ({**_raws(), "pol_upper": _raw()[:, :40]}, "shape"),
        ({**_raws(), "pol_upper": _raw().astype(np.uint8)}, "8-bit"),
        ({**_raws(), "pol_upper": _raw().astype(np.float32)}, "integer"),
        ({**_raws(), "pol_upper": _raw() + np.uint16(5000)}, "bit_depth"),
    ],
)
def test_add_frame_rejects_bad_raw(tmp_path, raws, message):
    store = CaptureStore.create(tmp_path / "cap", _rig())
    with pytest.raises(ValueError, match=message):
        store.add_frame(0, 0.0, raws)
    assert not list((tmp_path / "cap" / "frames").iterdir())
    assert not (tmp_path / "cap" / "raw").exists()


def test_add_frame_argument_errors(tmp_path):
    store = CaptureStore.create(tmp_path / "cap", _rig())
    with pytest.raises(ValueError, match="frame_index"):
        store.add_frame(-1, 0.0, _raws())
    with pytest.raises(ValueError, match="timestamp"):
        store.add_frame(0, float("nan"), _raws())
    with pytest.raises(ValueError, match="sequence"):
        CaptureStore.create(tmp_path / "other", _rig(), sequence="looped")
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "file.txt").write_text("x")
    with pytest.raises(ValueError, match="not a capture store"):
        CaptureStore.create(tmp_path / "junk", _rig())


def _finished(tmp_path):
    store = CaptureStore.create(tmp_path / "cap", _rig())
    store.add_frame(0, 0.0, _raws(0))
    store.add_frame(1, 0.05, _raws(1))
    store.finalize()
    return tmp_path / "cap"


def test_validation_errors(tmp_path):
    root = _finished(tmp_path)
    (root / "raw" / "pol_lower" / "000001.png").unlink()
    with pytest.raises(ValueError, match=r"000001\.png' of camera 'pol_lower' is missing"):
        CaptureStore.open(root)
    write_png(root / "raw" / "pol_lower" / "000001.png", (_raws(1)["pol_lower"] // 16).astype(np.uint8))
    with pytest.raises(ValueError, match="8-bit"):
        CaptureStore.open(root)
    write_png(root / "raw" / "pol_lower" / "000001.png", _raw()[:, :40], bit_depth=16)
    with pytest.raises(ValueError, match="40x32"):
        CaptureStore.open(root)
    write_png(root / "raw" / "pol_lower" / "000001.png", _raws(1)["pol_lower"], bit_depth=16)
    CaptureStore.open(root)
    write_png(root / "raw" / "pol_lower" / "000009.png", _raws(1)["pol_lower"], bit_depth=16)
    with pytest.raises(ValueError, match=r"000009\.png' is not in the manifest"):
        CaptureStore.open(root)


def test_manifest_errors(tmp_path):
    root = _finished(tmp_path)
    manifest = json.loads((root / "manifest.json").read_text())
    manifest["frames"][0]["raw"]["ghost"] = "raw/ghost/000000.png"
    (root / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match="'ghost' is not in the rig"):
        CaptureStore.open(root)
    (root / "manifest.json").write_text("{")
    with pytest.raises(ValueError, match="not valid JSON"):
        CaptureStore.open(root)
    (root / "manifest.json").unlink()
    with pytest.raises(FileNotFoundError, match="manifest"):
        CaptureStore.open(root)


def test_truncated_raw_png_detected(tmp_path):
    root = _finished(tmp_path)
    path = root / "raw" / "pol_upper" / "000000.png"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    store = CaptureStore.open(root)  # header still readable
    with pytest.raises(ValueError, match="truncated"):
        store.validate(deep=True)


def test_derived_requires_completed_frame(tmp_path):
    store = CaptureStore.create(tmp_path / "cap", _rig())
    store.add_frame(0, 0.0, _raws(0), process=False)
    store.finalize()
    with pytest.raises(ValueError, match="no completed derived"):
        store.stack(0, "pol_upper")
    with pytest.raises(ValueError, match="not in the manifest"):
        store.stack(3, "pol_upper")
    with pytest.raises(ValueError, match="name"):
        store.observation("i_xyz", 0, "pol_upper")


def test_saturated_frame_is_masked_in_store(tmp_path):
    store = CaptureStore.create(tmp_path / "cap", _rig())
    raws = {cam: np.full((HEIGHT, WIDTH), 4095, np.uint16) for cam in ("pol_upper", "pol_lower")}
    store.add_frame(0, 0.0, raws)
    assert (store.mask(0, "pol_upper") & 1).all()


# -------------------------------------------------------------------------------------- ingest
def _raw_dir(tmp_path, frames=(0, 1, 2)):
    raw_dir = tmp_path / "raw_in"
    for number in frames:
        for cam, raw in _raws(number).items():
            write_png(raw_dir / cam / f"{number:04d}.png", raw, bit_depth=16)
    return raw_dir


def test_ingest_directory(tmp_path):
    raw_dir = _raw_dir(tmp_path)
    (raw_dir / "timestamps.csv").write_text("frame,timestamp_s\n0,0.0\n1,0.04\n2,0.09\n")
    store = ingest_directory(raw_dir, _rig(), tmp_path / "cap", progress=False, sequence="dynamic")
    assert [f.timestamp for f in store.frames] == [0.0, 0.04, 0.09]
    again = ingest_directory(raw_dir, _rig(), tmp_path / "cap", progress=False, sequence="dynamic")
    assert len(again.frames) == 3


def test_ingest_errors(tmp_path):
    raw_dir = _raw_dir(tmp_path)
    (raw_dir / "pol_lower" / "0002.png").unlink()
    with pytest.raises(ValueError, match=r"frame 2 is missing for camera\(s\) \['pol_lower'\]"):
        scan_raw_directory(raw_dir, _rig())
    write_png(raw_dir / "ghost" / "0000.png", _raw(), bit_depth=16)
    with pytest.raises(ValueError, match="'ghost' is not in the rig"):
        scan_raw_directory(raw_dir, _rig())
    with pytest.raises(FileNotFoundError):
        scan_raw_directory(tmp_path / "nothing", _rig())


def test_ingest_rejects_8_bit_and_leaves_no_frame(tmp_path):
    raw_dir = _raw_dir(tmp_path, frames=(0,))
    write_png(raw_dir / "pol_upper" / "0000.png", (_raw() // 16).astype(np.uint8))
    with pytest.raises(ValueError, match="8-bit"):
        ingest_directory(raw_dir, _rig(), tmp_path / "cap", progress=False)
    assert not (tmp_path / "cap").exists()
