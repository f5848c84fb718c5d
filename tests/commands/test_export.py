"""``polarface export`` and its output folder (issue 47): never the RESULT itself, never a partial export.

Each failure was seen by the held-out bad-input campaign against 13019e4: ``export RESULT --out RESULT
--force`` left the RESULT without ``result.json`` and its maps (the swap replaced it by the export), and an
export whose input check failed half-way (a truncated EXR, a corrupt ``sog.json``, NaN in ``rig.json``,
``--format authors-layout`` without an unwrap store) left ``RESULT/exports`` behind.
"""

from __future__ import annotations

import json

import pytest

from command_fixtures import error_lines, files
from polarface.cli import main

FAST = ["--format", "mitsuba"]  # the quickest format (about 1 s)


def _fails_with_one_line(capsys, argv: list[str], *needles: str) -> str:
    capsys.readouterr()
    assert main(argv) == 2
    lines = error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and lines[0].startswith(f"polarface {argv[0]}: error: "), lines
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


@pytest.mark.parametrize("where", ["result", "parent", "maps"])
def test_export_refuses_an_out_that_is_contains_or_lies_in_the_result(plane_result, capsys, where):
    out = {"result": plane_result, "parent": plane_result.parent, "maps": plane_result / "maps"}[where]
    before = files(plane_result.parent)
    _fails_with_one_line(capsys, ["export", str(plane_result), "--out", str(out), "--force", *FAST],
                         "argument '--out'", "the input RESULT")
    assert files(plane_result.parent) == before


def test_export_writes_its_default_folder_inside_the_result(plane_result, capsys):
    """``RESULT/exports`` is the RESULT's own exports folder: allowed, as given or by default."""
    assert main(["export", str(plane_result), *FAST]) == 0
    assert json.loads((plane_result / "exports" / "export.json").read_text())["formats"].keys() == {"mitsuba"}
    assert main(["export", str(plane_result), "--out", str(plane_result / "exports"), "--force", *FAST]) == 0
    assert not [p.name for p in plane_result.iterdir() if p.name.startswith(".")]  # no temporary left


def _truncate(path) -> None:
    path.write_bytes(path.read_bytes()[:300])


def _nan_light(path) -> None:
    rig = json.loads(path.read_text())
    rig["lights"][0]["position_mm"] = [float("nan"), 0.0, 0.0]
    path.write_text(json.dumps(rig))  # writes NaN, which json reads back


@pytest.mark.parametrize(
    ("case", "corrupt", "formats", "needle"),
    [
        ("truncated exr", lambda r: _truncate(r / "maps" / "rho_sss_bar.exr"), "mitsuba", "rho_sss_bar.exr"),
        ("truncated mesh", lambda r: _truncate(r / "mesh.obj"), "mitsuba", "mesh.obj"),
        ("nan in rig", lambda r: _nan_light(r / "rig.json"), "mitsuba", "rig.json"),
        ("corrupt sog", lambda r: (r / "maps" / "sog.json").write_text("{"), "kernels", "sog.json"),
        ("no unwrap store", lambda r: None, "authors-layout", "unwrap"),
    ],
)
def test_a_failed_export_leaves_no_folder(plane_result, capsys, case, corrupt, formats, needle):
    corrupt(plane_result)
    before = files(plane_result)
    _fails_with_one_line(capsys, ["export", str(plane_result), "--format", formats], needle)
    assert files(plane_result) == before
    assert sorted(p.name for p in plane_result.iterdir()) == ["maps", "mesh.obj", "result.json", "rig.json"]
