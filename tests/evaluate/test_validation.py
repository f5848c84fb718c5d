"""The ``validation`` group (``polarface.evaluate.validation``): the tiny simulation's ground truth used as
its own RESULT renders the validation camera's images again (errors ~0, an independent path: the
RESULT's maps, mesh and diffusion through ``render.relight`` against the simulator's render), a
perturbed RESULT scores the error it carries, a fitted RESULT is scored, and bad input is named."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from polarface.evaluate import METRIC_GROUPS
from polarface.evaluate.validation import validation_metrics
from polarface.io import read_exr, write_exr
from polarface.results import CHROMOPHORE_MAPS, POLARIMETRIC_MAPS, RHO_SSS_BAR, ResultFolder
from polarface.simulate.validation import VALIDATION_FOLDER, VALIDATION_JSON


def write_truth_result(sim: Path, root: Path, scale: dict[str, float] | None = None,
                       offset: dict[str, float] | None = None) -> Path:
    """A static RESULT made of the ground truth (maps, rest mesh, the capture's rig; its poses are the
    ground truth's, so the model alignment is the identity), each map scaled and offset as given."""
    gt = sim / "ground_truth"
    summary = json.loads((sim / "simulation.json").read_text())
    folder = ResultFolder(root)
    folder.write_result_header(summary["channel_names"], (256, 256), 1.0)
    shutil.copy(gt / "mesh_rest.obj", root / "mesh.obj")
    shutil.copy(sim / "static" / "rig.json", root / "rig.json")
    for name in (*POLARIMETRIC_MAPS, *CHROMOPHORE_MAPS, RHO_SSS_BAR):
        channels = read_exr(gt / "maps" / f"{name}.exr")
        factor, shift = (scale or {}).get(name, 1.0), (offset or {}).get(name, 0.0)
        write_exr(folder.map_path(name), {k: v * factor + shift for k, v in channels.items()})
    shutil.copy(gt / "maps" / "mask.png", folder.map_path("mask", ".png"))
    folder.record_stage("prepare", {"poses": str(gt / "static" / "poses.json"), "reference_frame": 0})
    return root


@pytest.fixture(scope="module")
def truth(tiny_sim, tmp_path_factory) -> dict:
    return validation_metrics(write_truth_result(tiny_sim, tmp_path_factory.mktemp("truth")), tiny_sim)


def test_the_truth_renders_the_validation_images_again(truth):
    assert "validation" in METRIC_GROUPS
    assert truth["views"] == 4 and truth["coverage"] > 0.95
    # the same maps through another path (RESULT files, diffusion profiles fitted at the median texel)
    assert truth["full_rmse"] < 0.01
    assert truth["specular_rmse"] < 1e-5 and truth["dop"]["median_abs_error"] < 1e-3
    assert len(truth["per_view"]["full_rmse"]) == 4


def test_a_wrong_specular_albedo_or_index_is_seen(tiny_sim, tmp_path, truth):
    brighter = validation_metrics(write_truth_result(tiny_sim, tmp_path / "rho_s", {"rho_s": 1.5}), tiny_sim)
    # 50 % more specular light: the specular error is half the specular image, the full error shows it
    assert brighter["specular_rmse_over_mean_specular"] > 0.3
    assert brighter["full_rmse"] > truth["full_rmse"] + 0.5 * brighter["specular_rmse"]
    assert brighter["specular_rmse"] < brighter["full_rmse"] + 1e-6
    denser = validation_metrics(write_truth_result(tiny_sim, tmp_path / "eta", offset={"eta": 0.3}), tiny_sim)
    assert denser["dop"]["median_abs_error"] > 10 * truth["dop"]["median_abs_error"] + 1e-3


def test_a_fitted_result_is_scored(tiny_sequence):
    sim, static = tiny_sequence
    metrics = validation_metrics(static, sim)
    print({k: v for k, v in metrics.items() if k != "per_view"})
    # the tiny capture turns the head by +-12 deg: its mask covers less than half of what the novel views see
    assert metrics["views"] == 4 and 0.3 < metrics["coverage"] <= 1.0
    assert 0.0 < metrics["specular_rmse"] < metrics["full_rmse"] < 0.5


def test_no_validation_folder_is_skipped_and_a_bad_one_is_named(tiny_sim, tmp_path):
    gt = tmp_path / "sim" / "ground_truth"
    shutil.copytree(tiny_sim / "ground_truth" / "maps", gt / "maps")
    result = write_truth_result(tiny_sim, tmp_path / "result")
    assert "does not exist" in validation_metrics(result, gt)["skipped"]
    shutil.copytree(tiny_sim / "ground_truth" / VALIDATION_FOLDER, gt / VALIDATION_FOLDER)
    index_path = gt / VALIDATION_FOLDER / VALIDATION_JSON
    index = json.loads(index_path.read_text())
    index_path.write_text(json.dumps({**index, "format": "other"}))
    with pytest.raises(ValueError, match=r"validation\.json.*format"):
        validation_metrics(result, gt)
    index_path.write_text(json.dumps(index))
    image = gt / VALIDATION_FOLDER / index["views"][0]["file"]
    channels = read_exr(image)
    write_exr(image, {k: v for k, v in channels.items() if not k.startswith("specular.")})
    with pytest.raises(ValueError, match=rf"{image.name}.*lacks.*specular"):
        validation_metrics(result, gt)


def test_validation_images_obey_the_physics(tiny_sim):
    folder = tiny_sim / "ground_truth" / VALIDATION_FOLDER
    index = json.loads((folder / VALIDATION_JSON).read_text())
    assert index["format"] == "polarface-validation" and len(index["views"]) == 4
    for view in index["views"]:
        channels = read_exr(folder / view["file"])
        mask = channels["mask"] > 0.5
        assert 0.2 < mask.mean() < 0.95
        for name in index["channel_names"]:
            s0, s1, s2 = (channels[f"{k}.{name}"][mask] for k in ("s0", "s1", "s2"))
            specular = channels[f"specular.{name}"][mask]
            # off the LEDs' axis the camera sees shadowed skin too (s0 = 0 where no LED reaches)
            assert (s0 >= 0).all() and (s0 > 0).mean() > 0.9
            assert (np.hypot(s1, s2) <= s0 * (1 + 1e-5) + 1e-9).all()  # DoP <= 1
            assert (specular >= 0).all() and (specular <= s0 * (1 + 1e-5)).all()
            assert (channels[f"s0.{name}"][~mask] == 0).all()
