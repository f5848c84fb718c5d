"""``polarface render``: what it needs (``maps/sog.json``), its output folder and Ctrl-C (issue 47).

The held-out bad-input campaign against 13019e4 saw ``render`` of a RESULT whose ``maps/sog.json`` was
missing exit 0 with profiles silently fitted elsewhere, ``render --out memory://x`` exit 0 with nothing kept,
and ``render`` stopped by Ctrl-C exit 130 without a word.
"""

from __future__ import annotations

import json
import signal
import sys

import pytest

import polarface.render.result_views as result_views
from command_fixtures import error_lines, files
from polarface.cli import main
from polarface.results import ResultFolder

FAST = ["--no-mueller", "--no-strip", "--exposure", "1.0"]


def test_a_result_whose_biophysical_stage_wrote_sog_json_needs_it(plane_result, tmp_path, capsys):
    ResultFolder(plane_result).record_stage("biophysical", {"texels": 256})
    out = tmp_path / "out"
    assert main(["render", str(plane_result), "--out", str(out), *FAST]) == 2
    lines = error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and "maps/sog.json' does not exist" in lines[0], lines
    assert "polarface biophysical" in lines[0] and not out.exists()


def test_maps_without_a_biophysical_record_render_with_an_announced_fallback(plane_result, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["render", str(plane_result), "--out", str(out), *FAST]) == 0
    captured = capsys.readouterr()
    warnings = [line for line in error_lines(captured.err) if "warning" in line]
    assert len(warnings) == 1 and warnings[0].startswith("polarface render: warning: '"), warnings
    assert "median texel" in warnings[0]
    assert json.loads((out / "render.json").read_text())["profiles"] == "median texel"
    assert json.loads(captured.out)["profiles"] == "median texel"


@pytest.mark.parametrize("where", ["maps", "result", "poses"])
def test_render_out_apart_from_its_inputs(plane_result, tmp_path, capsys, where):
    poses = tmp_path / "poses" / "poses.json"
    poses.parent.mkdir()
    poses.write_text(json.dumps([[[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]]))
    out = {"maps": plane_result / "maps", "result": plane_result, "poses": poses.parent}[where]
    before = files(tmp_path)
    argv = ["render", str(plane_result), "--out", str(out), "--force", "--poses", str(poses), *FAST]
    assert main(argv) == 2
    lines = error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and "argument '--out'" in lines[0] and "the input" in lines[0], lines
    assert files(tmp_path) == before


def test_render_writes_its_default_folder_inside_the_result(plane_result, capsys):
    assert main(["render", str(plane_result), *FAST]) == 0
    assert (plane_result / "render" / "srgb.png").is_file()
    assert main(["render", str(plane_result), *FAST]) == 0  # its own folder: replaced whole


def test_ctrl_c_during_render_is_one_line_and_leaves_nothing(plane_result, tmp_path, capsys, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(result_views, "_write_strip", interrupted)  # after the first images are written
    out = tmp_path / "out"
    assert main(["render", str(plane_result), "--out", str(out), "--no-mueller", "--exposure", "1.0"]) == 130
    lines = [line for line in error_lines(capsys.readouterr().err) if "warning" not in line]
    assert lines == ["polarface render: interrupted; nothing was written (the output is written whole or "
                     "not at all; an existing one is left as it was)"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result"]


def test_the_program_ignores_ctrl_c_once_the_command_is_over(monkeypatch, capsys):
    """Python restores SIGINT's default action before it tears down torch and numba (seconds): a Ctrl-C
    then killed a finished ``render`` silently with status 130. ``main`` as the program ignores it then;
    ``main(argv)`` in a caller's process leaves its handler alone."""
    previous = signal.getsignal(signal.SIGINT)
    try:
        monkeypatch.setattr(sys, "argv", ["polarface", "render", "/nonexistent/result", "--no-mueller"])
        assert main() == 2
        assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
        signal.signal(signal.SIGINT, previous)
        assert main(["render", "/nonexistent/result"]) == 2
        assert signal.getsignal(signal.SIGINT) == previous
    finally:
        signal.signal(signal.SIGINT, previous)
    capsys.readouterr()


def test_ctrl_c_while_the_commands_load_is_one_line(monkeypatch, capsys):
    import polarface.cli as cli

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", interrupted)
    assert main(["render", "x"]) == 130
    assert error_lines(capsys.readouterr().err) == ["polarface: interrupted while loading the commands; "
                                                     "nothing was run"]


@pytest.mark.parametrize("command", ["render", "biophysical"])
def test_a_truncated_mesh_is_named(plane_result, tmp_path, capsys, command):
    """A truncated OBJ failed in numpy ("setting an array element with a sequence") with no file name."""
    mesh = plane_result / "mesh.obj"
    mesh.write_bytes(mesh.read_bytes()[:300])
    extra = ["--out", str(tmp_path / "out"), *FAST] if command == "render" else ["--no-progress"]
    before = files(tmp_path)
    assert main([command, str(plane_result), *extra]) == 2
    lines = error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and f"cannot read '{mesh}'" in lines[0], lines
    assert files(tmp_path) == before
