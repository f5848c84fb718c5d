"""The CLI ends every failure in one line: OSError (exit 2), Ctrl-C (exit 130), busy and foreign folders."""

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import polarface.pipeline
from polarface.cli import main
from polarface.io.output_folder import lock_output

SRC = Path(__file__).resolve().parents[1] / "src"
RERUN = "rerun the same command to continue"


def _error_lines(capsys) -> list[str]:
    return [line for line in capsys.readouterr().err.splitlines() if line.strip()]


@pytest.mark.parametrize(
    ("exc", "expected"),
    [
        (OSError(errno.ENOSPC, "No space left on device", "/out/i0.exr"), "'/out/i0.exr': No space"),
        (PermissionError(errno.EACCES, "Permission denied", "/ro/out"), "'/ro/out': Permission denied"),
        (IsADirectoryError(errno.EISDIR, "Is a directory", "/x/metrics.json"), "'/x/metrics.json': Is a dir"),
    ],
)
def test_os_errors_end_in_one_line(tmp_path, capsys, monkeypatch, exc, expected):
    def fail(*args, **kwargs):
        raise exc

    monkeypatch.setattr(polarface.pipeline, "run_sphere_demo", fail)
    assert main(["demo", "--sphere", "--out", str(tmp_path / "s")]) == 2
    lines = _error_lines(capsys)
    assert len(lines) == 1 and lines[0].startswith("polarface demo: error: ") and expected in lines[0]


def test_out_below_a_file_is_one_line(tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    assert main(["demo", "--sphere", "--size", "8", "--out", str(tmp_path / "file" / "sub")]) == 2
    lines = _error_lines(capsys)
    assert len(lines) == 1 and "file" in lines[0] and "Traceback" not in lines[0]


def test_keyboard_interrupt_is_one_line_with_exit_130(tmp_path, capsys, monkeypatch):
    def interrupted(out, *args, **kwargs):
        if "partial" in str(out):
            (out / "sim").mkdir()
        raise KeyboardInterrupt

    monkeypatch.setattr(polarface.pipeline, "run_demo_pipeline", interrupted)
    out = tmp_path / "partial"
    assert main(["demo", "--preset", "tiny", "--out", str(out)]) == 130
    lines = _error_lines(capsys)
    assert lines == [f"polarface demo: interrupted; partial results kept in {out}; {RERUN}"]
    assert main(["demo", "--preset", "tiny", "--out", str(tmp_path / "early")]) == 130
    assert _error_lines(capsys) == ["polarface demo: interrupted"]  # nothing written: the folder is gone
    assert not (tmp_path / "early").exists()
    assert main(["demo", "--preset", "tiny", "--force", "--out", str(out)]) == 130
    assert _error_lines(capsys) == [f"polarface demo: interrupted; {out} left as it was (--force replaces it "
                                    "only after a complete run)"]  # fmt: skip
    assert sorted(p.name for p in tmp_path.iterdir()) == ["partial"] and (out / "sim").is_dir()


def test_help_shows_defaults(capsys):
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "size preset (default: demo)" in text
    assert "skin type I..VI (default: II)" in text
    with pytest.raises(SystemExit):
        main(["reconstruct", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "default 4)" in text and "(default: 4)" not in text  # stated once
    assert "(default: None)" not in text and "(default: False)" not in text


@pytest.mark.parametrize(
    "argv",
    [
        ["simulate", "--preset", "tiny", "--out", "{d}"],
        ["stokes", "raw.png", "--sensor", "mono-polarization", "--out", "{d}"],
        ["skin-fit", "spectra.csv", "--out", "{d}"],
        ["reconstruct", "capture", "--out", "{d}", "--resume"],
        ["ingest", "raw", "--rig", "rig.json", "--out", "{d}"],
        ["render", "result", "--out", "{d}"],
    ],
)
def test_foreign_folder_is_refused(tmp_path, capsys, argv):
    folder = tmp_path / "d"
    folder.mkdir()
    (folder / "notes.txt").write_text("x")
    assert main([a.format(d=folder) for a in argv]) == 2
    lines = _error_lines(capsys)
    assert len(lines) == 1 and "not written by" in lines[0] and "--force" in lines[0]
    assert [p.name for p in folder.iterdir()] == ["notes.txt"]


def test_reconstruct_own_folder_needs_resume_or_force(tmp_path, capsys):
    result = tmp_path / "result"
    result.mkdir()
    (result / "result.json").write_text(json.dumps({"format": "polarface-result", "version": 1}))
    assert main(["reconstruct", "capture", "--out", str(result)]) == 2
    assert "--resume" in capsys.readouterr().err


def test_files_and_results_are_checked(tmp_path, capsys):
    metrics = tmp_path / "metrics.json"
    metrics.write_text("my notes")
    assert main(["evaluate", "result", "--gt", "sim", "--out", str(metrics)]) == 2
    assert "exists and was not written" in capsys.readouterr().err
    assert metrics.read_text() == "my notes"
    with lock_output(tmp_path, "reconstruct"):  # the RESULT is being written: biophysical waits for nothing
        assert main(["biophysical", str(tmp_path)]) == 2
    assert f"in use by 'polarface reconstruct' (pid {os.getpid()})" in capsys.readouterr().err


def _start(argv: list[str]) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    return subprocess.Popen(
        [sys.executable, "-m", "polarface.cli", *argv],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # a shell's background job inherits SIGINT ignored; a terminal's Ctrl-C is what is tested
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


def test_second_process_is_refused_and_ctrl_c_exits_130(tmp_path, capsys):
    """Two real processes on one folder: the second is refused at once naming the first's pid; SIGINT ends
    the first with exit code 130, one line, the lock released and the partial results kept.

    The first is paused (SIGSTOP) once it has written something, so that it cannot finish meanwhile."""
    out = tmp_path / "sim"
    lock = tmp_path / ".sim.polarface.lock"
    first = _start(["simulate", "--preset", "tiny", "--out", str(out)])
    try:
        deadline = time.monotonic() + 300
        while not (out / "ground_truth").exists() and first.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        first.send_signal(signal.SIGSTOP)
        assert first.poll() is None and json.loads(lock.read_text())["pid"] == first.pid
        started = time.monotonic()
        assert main(["simulate", "--preset", "tiny", "--out", str(out)]) == 2
        assert time.monotonic() - started < 1.0
        lines = _error_lines(capsys)
        assert len(lines) == 1 and f"(pid {first.pid})" in lines[0]
        second = _start(["simulate", "--preset", "tiny", "--out", str(out)])
        _, err = second.communicate(timeout=120)
        assert second.returncode == 2 and f"(pid {first.pid})" in err and "Traceback" not in err
        first.send_signal(signal.SIGINT)
        first.send_signal(signal.SIGCONT)
        _, err = first.communicate(timeout=120)
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert first.returncode == 130
    assert "Traceback" not in err
    messages = [line for line in err.splitlines() if line.startswith("polarface")]  # not the progress bars
    assert messages == [f"polarface simulate: interrupted; partial results kept in {out}; {RERUN}"]
    assert not lock.exists() and (out / "ground_truth").is_dir()


def test_reconstruct_force_replaces_only_its_own_run(tmp_path, capsys):
    from polarface.simulate.sphere_capture import SphereCaptureConfig, make_sphere_capture

    sim = tmp_path / "sim"
    make_sphere_capture(sim, SphereCaptureConfig(texture_resolution=16, frames=4))
    out = tmp_path / "result"
    argv = ["reconstruct", str(sim / "static"), "--geometry", str(sim / "ground_truth"), "--out", str(out),
            "--texture-resolution", "16", "--iterations", "5", "--quiet"]  # fmt: skip
    assert main(argv) == 0
    (out / "notes.txt").write_text("old run")
    assert main(argv) == 2
    assert "--resume" in capsys.readouterr().err
    assert main([*argv, "--resume"]) == 0 and (out / "notes.txt").exists()
    assert main([*argv, "--force"]) == 0
    assert not (out / "notes.txt").exists() and (out / "result.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result", "sim"]
