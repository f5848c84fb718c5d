"""One real tiny RESULT (static + 2 dynamic frames) shared by every export test, built once per test run:
:func:`tiny_sequence_dynamic` of tests/conftest.py (the tiny simulation reconstructed with its
ground-truth geometry and a shortened fit, then its dynamic sequence). Tests must not modify it: copy it
first."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def tiny_export(tiny_sequence, tiny_sequence_dynamic) -> tuple[Path, Path]:
    """``(SIM, RESULT)``: the tiny simulation and its static + dynamic reconstruction (read-only)."""
    return tiny_sequence[0], tiny_sequence_dynamic
