"""The argparse types of ``polarface.commands`` (issue 47): a URL is reported as the URL the user typed,
with the reason, and a URL that a later process cannot read (``memory://``) is refused everywhere.

The held-out bad-input campaign against 13019e4 saw ``memory://`` accepted as ``--out`` of ingest, stokes,
render, evaluate and calibrate-polarization (exit 0, nothing kept: ``type=Path`` even made a local folder
``memory:``), and ``foo://cap`` reported as a missing local path ``'foo:/cap' does not exist``.
"""

from __future__ import annotations

import argparse

import pytest

from command_fixtures import error_lines
from polarface.cli import main
from polarface.commands import local_folder, local_path, store_location


def test_types_name_the_url_and_the_reason():
    refused = argparse.ArgumentTypeError
    for kind in (store_location, local_folder, local_path):
        with pytest.raises(refused, match=r"'memory://x' is a URL of memory://.*one process"):
            kind("memory://x")
    with pytest.raises(refused, match=r"'foo://cap' is a URL of an unknown protocol 'foo'"):
        local_path("foo://cap")
    with pytest.raises(argparse.ArgumentTypeError, match=r"'foo://cap': unknown protocol"):
        store_location("foo://cap")
    with pytest.raises(argparse.ArgumentTypeError, match=r"'s3://b/k' is a URL; this argument takes a local"):
        local_path("s3://b/k")
    assert local_path("file:///tmp/x").as_posix() == "/tmp/x" and local_path("a/b").as_posix() == "a/b"


def _argv(tmp_path, case: str) -> list[str]:
    result, sim, rig = str(tmp_path / "result"), str(tmp_path / "sim"), str(tmp_path / "rig.json")
    return {
        "stokes --out": ["stokes", rig, "--sensor", "mono-polarization", "--out", "memory://x"],
        "render --out": ["render", result, "--out", "memory://x"],
        "evaluate --out": ["evaluate", result, "--gt", sim, "--out", "memory://m.json"],
        "evaluate --figures": ["evaluate", result, "--gt", sim, "--figures", "memory://f"],
        "calibrate-polarization --out": ["calibrate-polarization", sim, "--rig", rig, "--camera", "c",
                                         "--out", "memory://rig.json"],
        "ingest --out": ["ingest", sim, "--rig", rig, "--out", "memory://cap"],
        "export --out": ["export", result, "--out", "memory://x"],
        "skin-fit --out": ["skin-fit", rig, "--out", "memory://x"],
        "render result": ["render", "memory://result"],
        "info path": ["info", "memory://result"],
        "evaluate --gt": ["evaluate", result, "--gt", "foo://cap"],
        "stokes raw": ["stokes", "foo://raw.png", "--sensor", "mono-polarization", "--out",
                       str(tmp_path / "o")],
        "stokes --rig": ["stokes", rig, "--sensor", "mono-polarization", "--rig", "s3://b/rig.json",
                         "--camera", "c", "--out", str(tmp_path / "o")],
        "ior dir": ["ior", "foo://dir"],
        "biophysical --gt": ["biophysical", result, "--gt", "foo://sim"],
        "calibrate --rig": ["calibrate", "--rig", "foo://rig.json", "--camera", "c", "--square-mm", "20"],
        "render --poses": ["render", result, "--poses", "foo://poses.json"],
        "skin-fit spectra": ["skin-fit", "foo://spectra.csv", "--out", str(tmp_path / "o")],
        "calibrate-polarization frames": ["calibrate-polarization", "foo://frames", "--rig", rig,
                                          "--camera", "c"],
    }[case]


CASES = [
    ("stokes --out", "argument --out: 'memory://x'"),
    ("render --out", "argument --out: 'memory://x'"),
    ("evaluate --out", "argument --out: 'memory://m.json'"),
    ("evaluate --figures", "argument --figures: 'memory://f'"),
    ("calibrate-polarization --out", "argument --out: 'memory://rig.json'"),
    ("ingest --out", "argument --out: 'memory://cap'"),
    ("export --out", "argument --out: 'memory://x'"),
    ("skin-fit --out", "argument --out: 'memory://x'"),
    ("render result", "argument result: 'memory://result'"),
    ("info path", "argument PATH: 'memory://result'"),
    ("evaluate --gt", "argument --gt: 'foo://cap' is a URL of an unknown protocol 'foo'"),
    ("stokes raw", "argument raw: 'foo://raw.png' is a URL of an unknown protocol"),
    ("stokes --rig", "argument --rig: 's3://b/rig.json' is a URL; this argument takes a local path"),
    ("ior dir", "argument dir: 'foo://dir'"),
    ("biophysical --gt", "argument --gt: 'foo://sim'"),
    ("calibrate --rig", "argument --rig: 'foo://rig.json'"),
    ("render --poses", "argument --poses: 'foo://poses.json'"),
    ("skin-fit spectra", "argument spectra: 'foo://spectra.csv'"),
    ("calibrate-polarization frames", "argument frames: 'foo://frames'"),
]


@pytest.mark.parametrize(("case", "needle"), CASES, ids=[c[0] for c in CASES])
def test_urls_are_refused_naming_the_argument_and_the_url(tmp_path, monkeypatch, capsys, case, needle):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as stopped:
        main(_argv(tmp_path, case))
    assert stopped.value.code == 2
    lines = error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and lines[0].startswith(f"polarface {case.split()[0]}: error: "), lines
    assert needle in lines[0], lines[0]
    assert list(tmp_path.iterdir()) == []  # no local folder 'memory:' or 'foo:'
