"""RESULT/tracking's summary (pipeline/dynamic_geometry.py TrackingFolder): a resumed run refuses a folder
written with another capture or configuration, including one written before an option existed (its run
used that option's earlier behaviour, e.g. ICP to the iteration cap and chromophore fits from scratch)."""

from __future__ import annotations

import json

import pytest

from polarface.pipeline.dynamic import DynamicStageConfig, TrackingFolder

#: A capture identity (polarface.results.fingerprint.capture_identity): only its hash and frame count count.
CAPTURE = {"path": "/data/dynamic", "frames": 2, "sha256": "a" * 64}


def _header(config: dict) -> dict:
    return {"format": "polarface-tracking", "version": 1, "capture": CAPTURE, "config": config}


def test_the_same_capture_and_configuration_resume(tmp_path):
    defaults = DynamicStageConfig().to_json()
    TrackingFolder(tmp_path, _header(defaults)).save()
    assert TrackingFolder(tmp_path, _header(defaults)).summary["config"] == defaults
    # the capture moved or copied elsewhere: the same content, the same capture
    moved = {**_header(defaults), "capture": {**CAPTURE, "path": "/elsewhere/dynamic"}}
    assert TrackingFolder(tmp_path, moved).summary["capture"]["path"] == "/elsewhere/dynamic"


def test_another_option_value_an_older_configuration_or_another_capture_is_refused(tmp_path):
    defaults = DynamicStageConfig().to_json()
    TrackingFolder(tmp_path, _header(defaults)).save()
    scratch = DynamicStageConfig(biophysical_start="scratch").to_json()
    with pytest.raises(ValueError, match=r"tracking\.json.*another dynamic config"):
        TrackingFolder(tmp_path, _header(scratch))
    with pytest.raises(ValueError, match=r"another dynamic capture.*sha256 aaaa.*delete"):
        TrackingFolder(tmp_path, {**_header(defaults), "capture": {**CAPTURE, "sha256": "b" * 64}})
    with pytest.raises(ValueError, match="another dynamic capture"):
        TrackingFolder(tmp_path, {**_header(defaults), "capture": {**CAPTURE, "frames": 3}})
    older = json.loads(json.dumps(defaults))
    del older["biophysical_start"]
    TrackingFolder(tmp_path / "older", _header(older)).save()
    with pytest.raises(ValueError, match="another dynamic config"):
        TrackingFolder(tmp_path / "older", _header(defaults))
