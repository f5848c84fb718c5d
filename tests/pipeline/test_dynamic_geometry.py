"""RESULT/tracking's summary (pipeline/dynamic_geometry.py TrackingFolder): a resumed run refuses a folder
written with another capture or configuration, and counts options an older folder did not record as
their defaults."""

from __future__ import annotations

import json

import pytest

from polarface.pipeline.dynamic import DynamicStageConfig
from polarface.pipeline.dynamic_geometry import TrackingFolder


def _header(config: dict) -> dict:
    return {"format": "polarface-tracking", "version": 1, "capture": "CAPTURE", "config": config}


def test_an_older_folder_without_a_new_option_resumes_with_its_default(tmp_path):
    defaults = DynamicStageConfig().to_json()
    older = json.loads(json.dumps(defaults))
    del older["biophysical_start"]
    del older["alignment"]["icp_tolerance"]
    TrackingFolder(tmp_path, _header(older)).save()
    folder = TrackingFolder(tmp_path, _header(defaults), defaults)
    assert folder.summary["config"] == defaults
    with pytest.raises(ValueError, match="another dynamic config"):  # without defaults: a different config
        TrackingFolder(tmp_path, _header(defaults))


def test_a_folder_with_another_option_value_or_capture_is_refused(tmp_path):
    defaults = DynamicStageConfig().to_json()
    TrackingFolder(tmp_path, _header(defaults)).save()
    scratch = DynamicStageConfig(biophysical_start="scratch").to_json()
    with pytest.raises(ValueError, match=r"tracking\.json.*another dynamic config"):
        TrackingFolder(tmp_path, _header(scratch), defaults)
    with pytest.raises(ValueError, match="another dynamic capture"):
        TrackingFolder(tmp_path, {**_header(defaults), "capture": "OTHER"}, defaults)
