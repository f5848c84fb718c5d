"""The dynamic stage's input checks (pipeline/dynamic_inputs.py), each before anything is written: a dynamic
capture that is the static one, ``--frames`` out of order, ``threads`` < 1, a truncated raw image; and what
a failure found late leaves in ``RESULT/tracking`` (issue 47's bad-input campaign).

The inputs are the shared tiny simulation (tests/conftest.py) and a fake static RESULT (its files, not a
reconstruction: every check here runs before any work); stores are "copied" by their records, with the
image folders linked, so that a copy has the same content identity at another path.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

import polarface.pipeline.dynamic.stage as dynamic_module
from dynamic_fixtures import fake_static_result, snapshot
from polarface.capture import check_raw_images_whole
from polarface.capture.store import CaptureStore
from polarface.executors import check_thread_count
from polarface.pipeline.dynamic import reconstruct_dynamic
from polarface.pipeline.dynamic.tracking import _tracking_images
from polarface.pipeline.inputs import (
    check_dynamic_sequence,
    open_dynamic_capture,
    parse_frame_selection,
    selection_note,
)
from polarface.results import ResultFolder


def linked_copy(store: Path, out: Path, sequence: str | None = None) -> Path:
    """``store``'s records copied to ``out`` (its images linked): the same capture identity elsewhere, or
    with ``sequence`` its manifest relabelled (another identity)."""
    out.mkdir(parents=True)
    for name in ("rig.json", "manifest.json"):
        shutil.copyfile(store / name, out / name)
    shutil.copytree(store / "frames", out / "frames")
    for name in ("raw", "derived.zarr"):
        os.symlink(store / name, out / name)
    if sequence is not None:
        manifest = json.loads((out / "manifest.json").read_text())
        (out / "manifest.json").write_text(json.dumps({**manifest, "sequence": sequence}))
    return out


@pytest.fixture
def workspace(tiny_sim, tmp_path):
    """``(SIM, RESULT)``: the shared tiny simulation and a fake static RESULT of its static capture."""
    return tiny_sim, fake_static_result(tmp_path / "result", tiny_sim / "static")


# ---- 1. a dynamic capture that is the static one ------------------------------------------------------


def test_the_static_capture_is_refused_as_the_dynamic_one_before_anything_is_written(workspace, tmp_path):
    sim, result = workspace
    before = snapshot(tmp_path)
    # the RESULT's own static capture: by its recorded path, and a copy of it elsewhere by its identity
    with pytest.raises(ValueError, match=r"is the static capture that .* reconstructed from.*result\.json"):
        reconstruct_dynamic(result, sim / "static", progress=False)
    assert snapshot(tmp_path) == before
    elsewhere = linked_copy(sim / "static", tmp_path / "copies" / "static")
    before = snapshot(tmp_path)
    with pytest.raises(ValueError, match="is the static capture that"):
        reconstruct_dynamic(result, elsewhere, progress=False)
    # a static sequence that this RESULT was not made from: its manifest tells
    other = fake_static_result(tmp_path / "other", linked_copy(sim / "static", tmp_path / "mine", "dynamic"))
    before = snapshot(tmp_path)
    with pytest.raises(ValueError, match=r"manifest\.json' records sequence 'static'.*--sequence dynamic"):
        reconstruct_dynamic(other, sim / "static", progress=False)
    assert snapshot(tmp_path) == before
    assert not (result / "tracking").exists() and not (other / "tracking").exists()


def test_a_store_labelled_dynamic_is_still_refused_when_it_is_the_static_capture(tiny_sim, tmp_path):
    """The one-command form passes the static capture (``static_capture``): the same folder or a copy."""
    relabelled = linked_copy(tiny_sim / "static", tmp_path / "relabelled", sequence="dynamic")
    store = CaptureStore.open(relabelled)
    with pytest.raises(ValueError, match=r"is the static capture .* itself"):
        check_dynamic_sequence(store, static_capture=relabelled)
    copy = linked_copy(relabelled, tmp_path / "copy")
    with pytest.raises(ValueError, match=r"is the static capture .* itself"):
        open_dynamic_capture(copy, store.rig, relabelled / "rig.json", static_capture=relabelled)
    result = fake_static_result(tmp_path / "result", relabelled)
    with pytest.raises(ValueError, match="is the static capture that"):
        check_dynamic_sequence(CaptureStore.open(copy), result=ResultFolder(result))
    # the real dynamic capture passes every check
    dynamic = CaptureStore.open(tiny_sim / "dynamic")
    check_dynamic_sequence(dynamic, static_capture=relabelled, result=ResultFolder(result))


# ---- 2. --frames in reverse order ---------------------------------------------------------------------


def test_frame_selection_is_a_set_fitted_in_the_sequence_order_and_descending_ranges_are_refused():
    frames = [0, 1, 2, 3, 4]
    assert parse_frame_selection("3,1", frames) == [1, 3]
    assert parse_frame_selection("4,0-2,1", frames) == [0, 1, 2, 4]
    assert parse_frame_selection([4, 0], frames) == [0, 4]
    assert "fitted once each, in the sequence's order (1,3)" in selection_note("3,1", [1, 3])
    assert selection_note("0-2,4", [0, 1, 2, 4]) is None and selection_note(None, frames) is None
    with pytest.raises(ValueError, match=r"^argument '--frames': '4-0' is a descending range.*write '0-4'$"):
        parse_frame_selection("4-0", frames)
    with pytest.raises(ValueError, match=r"'--frames'.*descending"):
        parse_frame_selection("0,3-1", frames)
    with pytest.raises(ValueError, match=r"'--frames': '0--1': frame indices are >= 0"):
        parse_frame_selection("0--1", frames)
    with pytest.raises(ValueError, match=r"'--frames'.*selects no frame"):
        parse_frame_selection([], frames)
    # frames outside the capture are named compactly, even in a huge range (nothing enumerated)
    with pytest.raises(ValueError, match=r"frame\(s\) 5-9 are not in the dynamic capture \(its frames: 0-4"):
        parse_frame_selection("0-9", frames)
    with pytest.raises(ValueError, match=r"frame\(s\) 5-1000000000000 are not"):
        parse_frame_selection("2-1000000000000", frames)


def test_a_descending_range_is_refused_before_anything_is_written(workspace, tmp_path):
    sim, result = workspace
    before = snapshot(tmp_path)
    with pytest.raises(ValueError, match="'--frames': '1-0' is a descending range"):
        reconstruct_dynamic(result, sim, frames="1-0", progress=False)
    assert snapshot(tmp_path) == before


# ---- 3. threads < 1 -----------------------------------------------------------------------------------


@pytest.mark.parametrize("threads", [0, -2, 1.5, True])
def test_threads_below_one_are_refused_before_anything_is_written(workspace, tmp_path, threads):
    sim, result = workspace
    before = snapshot(tmp_path)
    with pytest.raises(ValueError, match=r"^argument '--threads' must be an integer >= 1"):
        reconstruct_dynamic(result, sim, threads=threads, progress=False)
    assert snapshot(tmp_path) == before
    check_thread_count(None)
    check_thread_count(3, maximum=4)
    with pytest.raises(ValueError, match=r"'--threads' must lie in \[1, 4\]"):
        check_thread_count(5, maximum=4)


# ---- 4. a truncated or corrupt frame ------------------------------------------------------------------


def test_a_truncated_stereo_image_is_refused_before_anything_is_written(workspace, tmp_path):
    sim, result = workspace
    capture = tmp_path / "dynamic"
    shutil.copytree(sim / "dynamic", capture)
    image = capture / "raw" / "stereo0_a" / "000001.png"
    image.write_bytes(image.read_bytes()[: image.stat().st_size // 2])
    before = snapshot(tmp_path)
    with pytest.raises(ValueError, match=r"raw image 'raw/stereo0_a/000001\.png' \(frame 1, camera "
                                         r"stereo0_a\) is truncated"):
        reconstruct_dynamic(result, capture, progress=False)
    assert snapshot(tmp_path) == before and not (result / "tracking").exists()
    # the polarimetric cameras' raws are not read (their derived arrays are): not the stage's concern
    check_raw_images_whole(CaptureStore.open(sim / "dynamic"))


def test_a_frame_corrupt_inside_is_one_error_naming_the_file_or_the_array(tiny_sim, tmp_path):
    """Corruption that keeps a file's length passes the checks and is found where the tracking decodes the
    frame: a ValueError (one line for the CLI) naming the image, or the camera and frame of derived.zarr."""
    capture = tmp_path / "dynamic"
    shutil.copytree(tiny_sim / "dynamic", capture)
    image = capture / "raw" / "stereo1_b" / "000001.png"
    data = bytearray(image.read_bytes())
    data[100:-12] = bytes(len(data) - 112)  # the PNG's data zeroed, its end chunk kept
    image.write_bytes(bytes(data))
    store = CaptureStore.open(capture)
    check_raw_images_whole(store)
    _tracking_images(store, 0)
    with pytest.raises(ValueError, match=r"stereo1_b/000001\.png"):
        _tracking_images(store, 1)
    chunks = [p for p in (capture / "derived.zarr" / "stacks" / "pol_upper" / "c" / "1").rglob("*")
              if p.is_file()]
    assert chunks
    for chunk in chunks:
        chunk.write_bytes(b"garbage" * 10)
    named = r"derived\.zarr.*pol_upper.*frame 1|frame 1.*pol_upper.*derived\.zarr"  # the store's message
    with pytest.raises(ValueError, match=named) as error:
        _tracking_images(CaptureStore.open(capture), 1)
    assert "\n" not in str(error.value)


def _stereo_stub(writes: list[int]):
    """``stereo_pass`` without the stereo: a placeholder mesh per frame not yet recorded, as it resumes."""
    def stereo(store, tracking, frames, config, progress, executor=None):
        for frame in frames:
            if str(frame) in tracking.summary["frames"]:
                continue
            path = tracking.stereo_path(frame)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text("ply")
            tracking.summary["frames"][str(frame)] = {"points": 1}
            writes.append(frame)
            tracking.save()
        return 0.0
    return stereo


def test_a_capture_refused_at_the_alignment_leaves_no_tracking_folder_but_an_interrupted_run_keeps_it(
        workspace, monkeypatch):
    """The capture is accepted once the reference mesh is placed in its first frame: a first run that fails
    before (another subject, no surface) removes the tracking folder it created, so that the next run with
    the right capture is not refused as 'another dynamic capture'; Ctrl-C keeps it (resume), and so does
    a failure in a run that found the folder there."""
    sim, result = workspace
    writes: list[int] = []
    monkeypatch.setattr(dynamic_module, "stereo_pass", _stereo_stub(writes))

    def refused(*args, **kwargs):
        raise ValueError("the reference mesh does not fit the first dynamic frame 0's stereo surface")

    monkeypatch.setattr(dynamic_module, "align_reference", refused)
    with pytest.raises(ValueError, match="does not fit"):
        reconstruct_dynamic(result, sim, progress=False)
    assert writes == [0, 1] and not (result / "tracking").exists()

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(dynamic_module, "align_reference", interrupted)
    with pytest.raises(KeyboardInterrupt):
        reconstruct_dynamic(result, sim, progress=False)
    kept = json.loads((result / "tracking" / "tracking.json").read_text())
    assert sorted(kept["frames"]) == ["0", "1"] and (result / "tracking" / "stereo" / "000001.ply").is_file()
    monkeypatch.setattr(dynamic_module, "align_reference", refused)
    with pytest.raises(ValueError, match="does not fit"):
        reconstruct_dynamic(result, sim, progress=False)
    assert (result / "tracking" / "stereo" / "000001.ply").is_file()  # not this run's folder: kept


def test_a_failure_after_the_alignment_keeps_the_complete_steps_and_the_next_run_resumes(workspace,
                                                                                        monkeypatch):
    sim, result = workspace
    writes: list[int] = []
    monkeypatch.setattr(dynamic_module, "stereo_pass", _stereo_stub(writes))
    alignments: list[int] = []

    def align(folder, reference, tracking, first, config, min_fitness):
        if "alignment" not in tracking.summary:
            alignments.append(first)
            tracking.summary["alignment"] = {"frame": first, "transform": np.eye(4).tolist()}
            tracking.save()
        return np.asarray(tracking.summary["alignment"]["transform"])

    def unreadable(*args, **kwargs):
        raise ValueError("cannot read image 'raw/stereo0_a/000001.png' (truncated, corrupt or not an image)")

    monkeypatch.setattr(dynamic_module, "align_reference", align)
    monkeypatch.setattr(dynamic_module, "track_sequence", unreadable)
    with pytest.raises(ValueError, match=r"stereo0_a/000001\.png"):
        reconstruct_dynamic(result, sim, progress=False)
    summary = json.loads((result / "tracking" / "tracking.json").read_text())
    assert summary["alignment"]["frame"] == 0 and sorted(summary["frames"]) == ["0", "1"]
    # the next run (the file repaired) reuses the stereo and the alignment and goes on to the tracking
    class Tracked(Exception):
        pass

    def tracked(*args, **kwargs):
        raise Tracked

    monkeypatch.setattr(dynamic_module, "track_sequence", tracked)
    with pytest.raises(Tracked):
        reconstruct_dynamic(result, sim, progress=False)
    assert writes == [0, 1] and alignments == [0]
