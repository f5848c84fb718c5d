"""``polarface dynamic`` (and ``reconstruct --dynamic``) on bad input, as a user types it: exit 2, one line
``polarface CMD: error: ...`` naming the file, field or argument (after argparse's usage block for an
argument's syntax), and nothing written: the RESULT, the captures and the folder around them unchanged
(issue 47's bad-input campaign). Every case is refused before any work, so the RESULT is a fake one (its
files, not a reconstruction) and the capture the shared tiny simulation (tests/conftest.py).
"""

from __future__ import annotations

import os
import shutil

import pytest

from dynamic_fixtures import fake_static_result, snapshot
from polarface.cli import main


@pytest.fixture
def workspace(tiny_sim, tmp_path):
    """``(SIM, RESULT, work folder)``: a fake static RESULT of the tiny simulation's static capture, a
    copy of the dynamic capture with one stereo image truncated, a RESULT without its static stage."""
    result = fake_static_result(tmp_path / "result", tiny_sim / "static")
    fake_static_result(tmp_path / "unfinished", tiny_sim / "static", polarimetric=False)
    truncated = tmp_path / "truncated"
    shutil.copytree(tiny_sim / "dynamic", truncated)
    image = truncated / "raw" / "stereo0_a" / "000001.png"
    image.write_bytes(image.read_bytes()[: image.stat().st_size // 2])
    (tmp_path / "notes.txt").write_text("a user's file\n")
    return tiny_sim, result, tmp_path


def _refused(argv: list[str], capsys, *, argparse_error: bool = False) -> str:
    """Run the CLI, assert exit 2 and one error line (after argparse's usage block for an argument
    error); return that line."""
    try:
        code = main(argv)
    except SystemExit as exit_:  # argparse: usage block, then the error line
        code = exit_.code
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2, err
    errors = [line for line in lines if line.startswith(f"polarface {argv[0]}: error:")]
    assert len(errors) == 1 and errors[0] == lines[-1], err
    if not argparse_error:
        assert len(lines) == 1, err
    assert "Traceback" not in err
    return errors[0]


CASES = {
    # defect 1: the static capture given as the dynamic one
    "the static capture": (["{result}", "{sim}/static"], ["is the static capture that", "result.json"]),
    # defect 2: a descending range (was: nothing fitted, exit 0)
    "a descending --frames": (["{result}", "{sim}", "--frames", "1-0"], ["'--frames'", "'1-0'", "'0-1'"]),
    "frames outside the capture": (["{result}", "{sim}", "--frames", "0-9"], ["'--frames'", "2-9"]),
    # defect 3: --threads 0 (was: every frame failed, exit 0); beyond this machine's CPUs
    "--threads 0": (["{result}", "{sim}", "--threads", "0"], ["'--threads' must lie in [1, "]),
    "--threads beyond the CPUs": (["{result}", "{sim}", "--threads", str((os.cpu_count() or 1) + 1)],
                                  ["'--threads'", "this machine's CPUs"]),
    # defect 4: a truncated stereo image (was: tracking/ left behind after a minute of stereo)
    "a truncated stereo image": (["{result}", "{work}/truncated"],
                                 ["raw/stereo0_a/000001.png", "truncated"]),
    # RESULT that is not one, or has no static stage
    "a SIM folder as RESULT": (["{sim}", "{sim}"], ["holds no static result", "rig.json"]),
    "a capture store as RESULT": (["{sim}/dynamic", "{sim}"], ["holds no static result", "mesh.obj"]),
    "a file as RESULT": (["{work}/notes.txt", "{sim}"], ["notes.txt", "is a file"]),
    "a missing RESULT": (["{work}/nowhere", "{sim}"], ["nowhere", "does not exist"]),
    "a RESULT without its static stage": (["{work}/unfinished", "{sim}"],
                                          ["unfinished", "polarimetric stage is not complete"]),
    # the dynamic capture
    "a missing dynamic capture": (["{result}", "{work}/nowhere"], ["nowhere", "does not exist"]),
    "a folder that is no capture": (["{result}", "{sim}/ground_truth"],
                                    ["ground_truth", "not a capture store"]),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_is_one_line_naming_it_and_nothing_is_written(workspace, case, capsys):
    sim, result, work = workspace
    args, named = CASES[case]
    argv = ["dynamic", *(a.format(sim=sim, result=result, work=work) for a in args), "--quiet"]
    before, inputs = snapshot(work), snapshot(sim)
    line = _refused(argv, capsys)
    for text in named:
        assert text in line, line
    assert snapshot(work) == before and snapshot(sim) == inputs
    assert not (result / "tracking").exists()


def test_a_url_of_an_unknown_scheme_is_reported_as_a_url(workspace, capsys):
    """argparse's ``type=Path`` would collapse ``foo://x`` into ``foo:/x`` and report a missing folder."""
    sim, result, work = workspace
    before = snapshot(work)
    for argv in (["dynamic", str(result), "foo://x"], ["dynamic", "foo://x", str(sim)]):
        line = _refused(argv, capsys, argparse_error=True)
        assert "'foo://x'" in line and "protocol" in line and "does not exist" not in line, line
    assert snapshot(work) == before


def test_reconstruct_refuses_the_static_capture_or_a_descending_range_as_dynamic_before_writing(
        workspace, capsys):
    sim, _, work = workspace
    fresh = work / "fresh"
    before = snapshot(work)
    line = _refused(["reconstruct", str(sim), "--dynamic", str(sim / "static"), "--out", str(fresh),
                     "--quiet"], capsys)
    assert f"dynamic capture '{sim / 'static'}' is the static capture" in line
    line = _refused(["reconstruct", str(sim), "--dynamic", str(sim), "--frames", "1-0", "--out", str(fresh),
                     "--quiet"], capsys)
    assert "'--frames'" in line and "descending" in line
    assert not fresh.exists() and snapshot(work) == before
