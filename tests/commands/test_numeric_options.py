"""Numeric options out of range (0, negative, huge, NaN) are refused at once, naming the option as typed
(issue 47): one line, exit 2, nothing written."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest

from command_fixtures import error_lines
from polarface.cli import main

SPECTRA = Path(__file__).resolve().parents[1] / "data" / "skin" / "nist_skin_reflectance_odd_subjects.csv"
BENCH = ["bench", "--side", "8", "--frames", "1", "--iterations", "1", "--baseline-texels", "1",
         "--threads", "1", "--seconds", "0.05", "--repeats", "1"]

CASES = [
    *[(["skin-fit", str(SPECTRA), *option], f"argument '{option[0]}' must lie in [") for option in (
        ["--iterations", "0"], ["--iterations", "1000000000"], ["--starts", "-1"], ["--starts", "100000000"],
        ["--max-offset", "nan"])],
    *[([*BENCH, *option], f"argument '{option[0]}' must") for option in (
        ["--side", "100000"], ["--frames", "100000"], ["--iterations", "1000000000"],
        ["--baseline-texels", "100000000"], ["--repeats", "100000000"], ["--seconds", "1e9"],
        ["--seconds", "nan"], ["--threads", "100000"])],
]


IDS = [f"{c[0][0]} {' '.join(c[0][-2:])}" for c in CASES]


@pytest.mark.parametrize(("argv", "needle"), CASES, ids=IDS)
def test_out_of_range_options_are_one_line(tmp_path, capsys, argv, needle):
    out = tmp_path / "out"
    if argv[0] == "skin-fit":
        argv = [*argv, "--out", str(out)]
    assert _within_seconds(10, argv) == 2
    lines = error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and lines[0].startswith(f"polarface {argv[0]}: error: "), lines
    assert needle in lines[0], lines[0]
    assert not out.exists()


def _within_seconds(seconds: float, argv: list[str]) -> int:
    """``main(argv)``, failing the test if it runs longer (an option not refused runs the job: for
    ``bench --iterations 1000000000``, for days)."""

    def expired(signum, frame):
        raise AssertionError(f"{argv[0]} still running after {seconds} s: the option was not refused")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        return main(argv)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
