"""The plane RESULT of :mod:`command_fixtures`, fresh for each test."""

from __future__ import annotations

from pathlib import Path

import pytest

from command_fixtures import write_command_result


@pytest.fixture
def plane_result(tmp_path) -> Path:
    """A fresh plane RESULT under ``tmp_path / "result"`` (the test may modify it)."""
    return write_command_result(tmp_path / "result")
