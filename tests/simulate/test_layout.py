"""The simulation folder's layout (``polarface.simulate.layout``): the one ground-truth resolver."""

from __future__ import annotations

import pytest

from polarface.simulate.layout import GROUND_TRUTH, SIMULATION_JSON, ground_truth_folder, is_simulation_folder


def test_ground_truth_folder_takes_the_simulation_or_its_ground_truth(tmp_path):
    (tmp_path / "sim" / GROUND_TRUTH / "maps").mkdir(parents=True)
    expected = tmp_path / "sim" / GROUND_TRUTH
    assert ground_truth_folder(tmp_path / "sim", require="maps") == expected
    assert ground_truth_folder(expected, require="maps") == expected
    assert ground_truth_folder(tmp_path / "sim") == expected
    with pytest.raises(FileNotFoundError, match=r"holds no ground truth 'maps'.*ground_truth/maps"):
        ground_truth_folder(tmp_path, require="maps")
    with pytest.raises(FileNotFoundError, match="'dynamic'"):
        ground_truth_folder(tmp_path / "sim", require="dynamic")


def test_is_simulation_folder(tmp_path):
    assert not is_simulation_folder(tmp_path)
    (tmp_path / SIMULATION_JSON).write_text("{}")
    assert is_simulation_folder(tmp_path)
    older = tmp_path / "older"
    (older / "static").mkdir(parents=True)
    (older / "static" / "manifest.json").write_text("{}")
    assert not is_simulation_folder(older)
    (older / GROUND_TRUTH).mkdir()
    assert is_simulation_folder(older)
