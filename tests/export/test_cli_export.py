"""``polarface export`` on the command line: formats, the output-folder policy, missing maps."""

from __future__ import annotations

import json
import shutil

import pytest

from polarface.cli import main


def _copy(result, folder):
    shutil.copytree(result, folder, ignore=shutil.ignore_patterns("unwrap.zarr"))
    return folder


def test_export_writes_the_formats_and_refuses_to_overwrite_without_force(tiny_export, tmp_path, capsys):
    _, result = tiny_export
    out = tmp_path / "exports"
    assert main(["export", str(result), "--format", "kernels", "--out", str(out)]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["format"] == "polarface-export" and list(record["formats"]) == ["kernels"]
    assert record["frames"] == [0, 1]
    for name in record["formats"]["kernels"]["files"]:
        assert (out / "kernels" / name).is_file(), name
    assert json.loads((out / "export.json").read_text())["formats"]["kernels"]["seconds"] >= 0
    before = (out / "export.json").read_bytes()

    assert main(["export", str(result), "--format", "kernels", "--out", str(out)]) == 2
    assert "pass --force" in capsys.readouterr().err
    assert (out / "export.json").read_bytes() == before

    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "notes.txt").write_text("mine")
    assert main(["export", str(result), "--format", "kernels", "--out", str(tmp_path / "foreign")]) == 2
    assert (tmp_path / "foreign" / "notes.txt").read_text() == "mine"

    assert main(["export", str(result), "--format", "kernels", "--out", str(out), "--force"]) == 0
    assert json.loads(capsys.readouterr().out)["formats"]["kernels"]["files"]


def test_missing_map_is_named_and_nothing_is_written(tiny_export, tmp_path, capsys):
    _, result = tiny_export
    copy = _copy(result, tmp_path / "r")
    (copy / "maps" / "alpha_s.exr").unlink()
    out = tmp_path / "out"
    assert main(["export", str(copy), "--format", "kernels,gltf", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "'gltf' needs" in err and "alpha_s.exr" in err
    assert not out.exists() or not any(p.name != ".polarface-output.json" for p in out.iterdir())


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--format", "obj"], "unknown format"),
        (["--frames", "7"], "frames"),
    ],
)
def test_bad_arguments_are_named(tiny_export, tmp_path, capsys, argv, message):
    _, result = tiny_export
    try:
        code = main(["export", str(result), "--out", str(tmp_path / "o"), *argv])
    except SystemExit as exc:  # argparse's own argument errors
        code = exc.code
    assert code == 2
    assert message in capsys.readouterr().err
