"""Bad arguments and inputs fail first: exit status 2, one line naming the argument, field or file,
and nothing written to the output path (``polarface.cli.main`` in process, one row per bad input)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from disk_fixtures import write_ior_capture, write_plane_result
from polarface.capture.rig import paper_rig
from polarface.cli import main
from polarface.inverse.ior_validation import default_sphere_scene
from polarface.io import write_png


def _result(root: Path) -> Path:
    """A small RESULT (a skin plane facing the polarimetric module) that ``render`` accepts."""
    return write_plane_result(root, cells=4, resolution=16, width=48, height=40)


def _render(tmp: Path, *extra: str) -> list[str]:
    return ["render", str(_result(tmp / "result")), "--out", str(tmp / "out"), *extra]


def _render_infinite_light(tmp: Path) -> list[str]:
    result = _result(tmp / "result")
    text = (result / "rig.json").read_text()
    rig = json.loads(text)
    rig["lights"][3]["position_mm"][1] = float("inf")  # json.dumps writes Infinity, which json reads
    (result / "rig.json").write_text(json.dumps(rig))
    return ["render", str(result), "--out", str(tmp / "out"), "--no-mueller", "--no-strip"]


def _render_bad_pose_frame(tmp: Path) -> list[str]:
    poses = tmp / "poses.json"
    poses.write_text(json.dumps([np.eye(4).tolist()]))
    return _render(tmp, "--poses", str(poses), "--pose-frame", "3")


def _simulate(tmp: Path, *extra: str) -> list[str]:
    return ["simulate", "--preset", "tiny", "--out", str(tmp / "out"), *extra]


def _stokes(tmp: Path, *extra: str) -> list[str]:
    raw = tmp / "raw.png"
    write_png(raw, np.full((16, 16), 100, np.uint8))
    return ["stokes", str(raw), "--sensor", "mono-polarization", "--out", str(tmp / "out"), *extra]


def _skin_fit_header_only(tmp: Path) -> list[str]:
    spectra = tmp / "spectra.csv"
    spectra.write_text("wavelength_nm,forehead,cheek\n")
    return ["skin-fit", str(spectra), "--out", str(tmp / "out")]


def _calibrate_bad_list(tmp: Path) -> list[str]:
    rig = paper_rig(width=64, height=48)
    rig.save(tmp / "rig.json")
    listing = tmp / "list.xml"
    listing.write_text('<?xml version="1.0"?>\n<opencv_storage>\n<imagelist>\n"a.png" <b>\n</imagelist>\n')
    return [
        "calibrate",
        "--rig",
        str(tmp / "rig.json"),
        "--camera",
        rig.cameras[0].id,
        "--list",
        str(listing),
        "--square-mm",
        "20",
        "--out",
        str(tmp / "out" / "rig.json"),
    ]


def _ior(tmp: Path, *extra: str, **camera: object) -> list[str]:
    folder = tmp / "capture"
    folder.mkdir()
    write_ior_capture(folder, size=48, **camera)
    return ["ior", str(folder), *extra]


def _non_rigid_pose() -> list[list[float]]:
    pose = default_sphere_scene(48).world_to_camera.copy()
    pose[:3, :3] *= 1.2
    return pose.tolist()


CASES: list[tuple[str, Callable[[Path], list[str]], str]] = [
    ("render strip width", lambda t: _render(t, "--strip-width-mm", "-3"), "--strip-width-mm"),
    ("render exposure", lambda t: _render(t, "--exposure", "nan"), "--exposure"),
    ("render camera", lambda t: _render(t, "--camera", "nosuch"), "--camera"),
    ("render pose frame", _render_bad_pose_frame, "--pose-frame"),
    ("render edit", lambda t: _render(t, "--edit", "C_m=-2x"), "edit"),
    ("rig.json Infinity", _render_infinite_light, "lights[3].position_mm"),
    ("simulate seed", lambda t: _simulate(t, "--seed", "-1"), "seed"),
    ("simulate skin type", lambda t: _simulate(t, "--skin-type", "VII"), "skin_type"),
    ("simulate sequences", lambda t: _simulate(t, "--sequences", "static,nosuch"), "sequences"),
    ("simulate threads", lambda t: _simulate(t, "--threads", "0"), "--threads"),
    ("stokes phase", lambda t: _stokes(t, "--phase", "5", "-1"), "phase"),
    ("stokes exposure", lambda t: _stokes(t, "--exposure", "0"), "exposure"),
    ("skin-fit header-only csv", _skin_fit_header_only, "holds no spectra"),
    (
        "skin-fit band",
        lambda t: [*_skin_fit_header_only(t), "--min-nm", "800", "--max-nm", "700"],
        "fit band",
    ),
    ("calibrate malformed list", _calibrate_bad_list, "list.xml"),
    ("ior focal length", lambda t: _ior(t, K=[[-1500.0, 0, 24], [0, 1500.0, 24], [0, 0, 1]]), "camera.K"),
    ("ior rigid pose", lambda t: _ior(t, world_to_camera=_non_rigid_pose()), "camera.world_to_camera"),
    ("ior eta range", lambda t: _ior(t, "--eta-range", "3", "1.5"), "eta_range"),
    ("ior eta on bound", lambda t: _ior(t, "--eta-range", "1.7", "3"), "bound"),
]


@pytest.mark.parametrize(("build", "needle"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_exits_2_with_one_line_and_writes_nothing(tmp_path, capsys, build, needle):
    argv = build(tmp_path)
    out = tmp_path / "out"
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"polarface {argv[0]}: error: ") and "\n" not in err, err
    assert needle in err, err
    assert not out.exists() or not any(out.rglob("*")), sorted(out.rglob("*"))


def test_biophysical_checks_the_ground_truth_before_the_fit(tmp_path):
    """``biophysical --gt nosuch`` used to fail only after the fit had written the maps: the stage now
    checks ``ground_truth`` first (the command passes ``--gt`` as ``ground_truth``)."""
    from polarface.pipeline.biophysical import run_biophysical_stage

    result = _result(tmp_path / "result")
    before = sorted(p.relative_to(result) for p in result.rglob("*"))
    with pytest.raises(FileNotFoundError, match=r"argument 'gt'.*nosuch"):
        run_biophysical_stage(result, ground_truth=tmp_path / "nosuch", progress=False)
    (tmp_path / "sim" / "ground_truth" / "maps").mkdir(parents=True)
    with pytest.raises(FileNotFoundError, match=r"argument 'gt'.*c_m\.exr"):
        run_biophysical_stage(result, ground_truth=tmp_path / "sim", progress=False)
    assert sorted(p.relative_to(result) for p in result.rglob("*")) == before


def test_biophysical_gt_is_checked_before_the_stage(tmp_path, capsys):
    """``biophysical --gt nosuch`` fails before the stage starts: nothing is fitted or written."""
    result = tmp_path / "result"
    (result / "maps").mkdir(parents=True)
    before = sorted(p.name for p in result.rglob("*"))
    assert main(["biophysical", str(result), "--gt", str(tmp_path / "nosuch")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "nosuch" in err
    assert sorted(p.name for p in result.rglob("*")) == before
