"""Bad-input campaign: every ``polarface`` command, one table row per malformed input.

Each row runs ``polarface.cli.main(argv)`` in-process and asserts the CLI's contract for bad input:
exit code 2; stderr is exactly one line ``polarface CMD: error: ...`` (after argparse's usage block,
for argument-syntax errors) naming the file, field or argument (a substring); no traceback; and
the row's workspace (inputs, the ``--out`` path, pre-existing user data there) is unchanged: no
partial output and nothing lost (file names, sizes and mtimes compared before and after).

The inputs are built once per session (a 16-texel sphere capture, one reconstruction of it, a raw
mosaic, a rig, spectra, an IOR capture) and each row corrupts its own copies. Rows that fail on
today's code are listed in ``XFAIL`` with the defect they show (strict: a fixed defect turns the row
into a failure, and its entry is then removed).
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import signal
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from authors_fixtures import write_fake_session
from disk_fixtures import write_ior_capture
from polarface.capture.rig import Rig, paper_rig
from polarface.capture.sensor import mosaic, simulate_raw
from polarface.capture.synthetic import stokes_pattern
from polarface.cli import main
from polarface.io import write_exr, write_png
from polarface.optics.analyzer import AnalyzerModel
from polarface.optics.stokes import intensities_from_stokes
from polarface.simulate.sphere_capture import SphereCaptureConfig, make_sphere_capture
from polarization_targets import target_frames

TEST_DATA = Path(__file__).parent / "data"
RES = 16
ROW_TIMEOUT_S = 10  # a row that has not failed by then is running the job instead of rejecting its input


# ----------------------------------------------------------------------------------------------------------
# Session inputs (valid); rows copy what they corrupt


@pytest.fixture(scope="session")
def inputs(tmp_path_factory) -> dict[str, Path]:
    """Valid inputs of every command, built once: keys are the row placeholders."""
    root = tmp_path_factory.mktemp("bad_inputs")
    sim = root / "sim"
    make_sphere_capture(sim, SphereCaptureConfig(texture_resolution=RES, frames=4))
    result = root / "result"
    argv = ["reconstruct", str(sim / "static"), "--geometry", str(sim / "ground_truth")]
    argv += ["--out", str(result), "--texture-resolution", str(RES), "--iterations", "3", "--quiet"]
    assert main(argv) == 0
    stokes = stokes_pattern("smooth", 32, 48, colour=True)
    raw = simulate_raw(
        mosaic(*np.moveaxis(intensities_from_stokes(stokes), -1, 0), sensor="color-polarization")
    )
    write_png(root / "raw.png", raw, bit_depth=16)
    paper_rig(width=48, height=32).save(root / "rig.json")
    for frame in range(2):
        for cam in ("pol_upper", "pol_lower"):
            write_png(root / "rawdir" / cam / f"{frame}.png", raw, bit_depth=16)
    lines = (TEST_DATA / "skin" / "nist_skin_reflectance_odd_subjects.csv").read_text().splitlines()
    (root / "spectra.csv").write_text("\n".join(",".join(line.split(",")[:3]) for line in lines) + "\n")
    write_ior_capture(root / "ior", size=32)
    Rig.model_validate({"cameras": [_stereo_camera(c) for c in ("left", "right")]}).save(root / "calrig.json")
    pol_camera = paper_rig(width=48, height=32).camera("pol_upper")
    pol_angles = (0, 45, 90, 135)
    for angle, frame in zip(pol_angles, target_frames(pol_camera, [AnalyzerModel(200.0)] * 3, pol_angles)):
        write_png(root / "polframes" / f"pol_{angle:03d}.png", frame, bit_depth=16)
    write_fake_session(root / "authors", frames=2, resolution=4)
    return {
        "sim": sim,
        "result": result,
        "png": root / "raw.png",
        "rig": root / "rig.json",
        "rawdir": root / "rawdir",
        "csv": root / "spectra.csv",
        "ior": root / "ior",
        "calrig": root / "calrig.json",
        "polframes": root / "polframes",
        "authors": root / "authors",
    }


def _stereo_camera(cam: str) -> dict:
    K = [[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]
    return {"id": cam, "role": "stereo", "sensor": "rgb", "width": 640, "height": 480, "K": K}


# ----------------------------------------------------------------------------------------------------------
# Corruptions: each takes the row workspace and returns nothing


Setup = Callable[[Path], None]


def text(rel: str, content: str) -> Setup:
    def setup(ws: Path) -> None:
        (ws / rel).parent.mkdir(parents=True, exist_ok=True)
        (ws / rel).write_text(content)

    return setup


def data(rel: str, content: bytes) -> Setup:
    def setup(ws: Path) -> None:
        (ws / rel).parent.mkdir(parents=True, exist_ok=True)
        (ws / rel).write_bytes(content)

    return setup


def truncate(rel: str, fraction: float = 0.5) -> Setup:
    def setup(ws: Path) -> None:
        content = (ws / rel).read_bytes()
        (ws / rel).write_bytes(content[: int(len(content) * fraction)])

    return setup


def remove(rel: str) -> Setup:
    def setup(ws: Path) -> None:
        path = ws / rel
        shutil.rmtree(path) if path.is_dir() else path.unlink()

    return setup


def as_dir(rel: str) -> Setup:
    """Replace a file by an (empty) folder of the same name."""

    def setup(ws: Path) -> None:
        remove(rel)(ws)
        (ws / rel).mkdir()

    return setup


def edit_json(rel: str, change: Callable[[dict], object]) -> Setup:
    """``change(payload)`` edits the parsed JSON in place (or returns a replacement)."""

    def setup(ws: Path) -> None:
        payload = json.loads((ws / rel).read_text())
        replaced = change(payload)
        (ws / rel).write_text(json.dumps(payload if replaced is None else replaced))

    return setup


def foreign(rel: str) -> Setup:
    """A non-empty folder of someone else's files at ``rel``."""
    return text(f"{rel}/thesis.txt", "years of work\n")


def readonly(rel: str) -> Setup:
    def setup(ws: Path) -> None:
        (ws / rel).mkdir(parents=True, exist_ok=True)
        (ws / rel).chmod(0o500)

    return setup


def chain(*setups: Setup) -> Setup:
    def setup(ws: Path) -> None:
        for step in setups:
            step(ws)

    return setup


def _set(path: list, value: object) -> Callable[[dict], None]:
    def change(payload: dict) -> None:
        node = payload
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value

    return change


def _delete(path: list) -> Callable[[dict], None]:
    def change(payload: dict) -> None:
        node = payload
        for key in path[:-1]:
            node = node[key]
        del node[path[-1]]

    return change


GARBAGE = b"\x00\x01not an image at all\xff" * 8
PNG_HEADER_ONLY = b"\x89PNG\r\n\x1a\n"
EXR_HEADER_ONLY = b"\x76\x2f\x31\x01\x02\x00\x00\x00"
NAN = float("nan")


@dataclasses.dataclass(frozen=True)
class Row:
    """One bad input: ``argv`` (with ``{placeholders}``); ``names``: substrings (``|``-separated
    alternatives) one of which the error line must contain; ``setup``: the corruption applied to the
    row's workspace copies first; ``readonly``: relies on directory permissions (skipped as root)."""

    id: str
    argv: tuple[str, ...]
    names: str
    setup: Setup | None = None
    readonly: bool = False


def row(id: str, argv: str, names: str, setup: Setup | None = None, readonly: bool = False) -> Row:
    return Row(id, tuple(argv.split()), names, setup, readonly)


# ----------------------------------------------------------------------------------------------------------
# The table.  Placeholders: {ws} the row's workspace; {sim} {result} {png} {rig} {rawdir} {csv} {ior}
# {calrig}: the row's own copies of the session inputs; {data}: tests/data (read-only).

SIMR = "reconstruct {sim}/static --geometry {sim}/ground_truth --texture-resolution 16 --quiet --out {ws}/out"
MESHR = (
    "reconstruct {sim}/static --mesh {ws}/m.obj --poses {sim}/ground_truth/static/poses.json --quiet"
    " --out {ws}/out"
)
POSER = (
    "reconstruct {sim}/static --mesh {sim}/ground_truth/mesh_rest.obj --poses {ws}/p.json --quiet"
    " --out {ws}/out"
)
STOKES = "stokes {png} --sensor color-polarization --out {ws}/out"
INGEST = "ingest {rawdir} --rig {rig} --no-progress --out {ws}/out"
SKIN = "skin-fit {csv} --out {ws}/out"
RENDER = "render {result} --no-mueller --no-strip --out {ws}/out"
BIO = "biophysical {result} --no-progress"
EVAL = "evaluate {result} --gt {sim}"
CAL = (
    "calibrate --rig {calrig} --camera left --images {data}/calibration/left01.jpg --square-mm 25"
    " --out {ws}/out.json"
)
CAL3 = CAL.replace("left01.jpg", "left0[123].jpg")
DEMO = "demo --sphere --out {ws}/out"
BENCH = "bench --side 8 --frames 1 --iterations 1 --baseline-texels 1 --threads 1 --seconds 0.05 --repeats 1"
IOR = "ior {ior}"
AUTHORS = "import-authors {authors} --no-progress --out {ws}/out"


def _import_authors_rows() -> list[Row]:
    """A partial download of an authors' session is refused before anything is written, naming the file."""
    mismatch = chain(remove("authors/texture/90/exr/img2_0001.exr"),
                     remove("authors/texture/90/exr/visible_img2_0001.exr"))
    return [
        row("import-authors-missing-session", "import-authors {ws}/nothing --out {ws}/out", "nothing"),
        row("import-authors-missing-angle-folder", AUTHORS, "texture/45/exr", remove("authors/texture/45")),
        row("import-authors-frame-count-mismatch", AUTHORS, "texture/90/exr", mismatch),
        row("import-authors-missing-visibility", AUTHORS, "visible_img1_0000.exr",
            remove("authors/texture/0/exr/visible_img1_0000.exr")),
        row("import-authors-missing-icp-pose", AUTHORS, "icp-pose", remove("authors/icp-pose/0001.txt")),
        row("import-authors-missing-cameras", AUTHORS, "cameras.txt", remove("authors/cameras.txt")),
        row("import-authors-missing-vertex-map", AUTHORS, "vertex.exr", remove("authors/texture/vertex.exr")),
        row("import-authors-bad-white-balance", AUTHORS, "white_balance.txt",
            text("authors/white_balance.txt", "1 1.0 1.0\n")),
        row("import-authors-out-is-foreign", AUTHORS, "out", foreign("out")),
    ]


def _stokes_rows() -> list[Row]:
    rows = [
        row(
            "stokes-missing-raw",
            "stokes {ws}/nope.png --sensor color-polarization --out {ws}/out",
            "nope.png",
        ),
        row("stokes-raw-is-dir", "stokes {ws} --sensor color-polarization --out {ws}/out", "{ws}"),
        row("stokes-raw-empty", STOKES, "raw.png", data("raw.png", b"")),
        row("stokes-raw-truncated", STOKES, "raw.png", truncate("raw.png")),
        row("stokes-raw-header-only", STOKES, "raw.png", data("raw.png", PNG_HEADER_ONLY)),
        row("stokes-raw-garbage", STOKES, "raw.png", data("raw.png", GARBAGE)),
        row("stokes-raw-text", STOKES, "raw.png", text("raw.png", "hello\n")),
        row(
            "stokes-raw-rgb",
            STOKES,
            "raw.png",
            lambda ws: write_png(ws / "raw.png", np.zeros((8, 8, 3), np.uint8)),
        ),
        row(
            "stokes-raw-1x1", STOKES, "raw", lambda ws: write_png(ws / "raw.png", np.zeros((1, 1), np.uint8))
        ),
        row(
            "stokes-raw-odd-size",
            STOKES,
            "raw",
            lambda ws: write_png(ws / "raw.png", np.zeros((7, 9), np.uint8)),
        ),
        row("stokes-bad-sensor", STOKES + " --sensor rgb", "--sensor"),
        row("stokes-bad-method", STOKES + " --method magic", "--method"),
        row("stokes-no-out", "stokes {png} --sensor color-polarization", "--out"),
        row("stokes-bit-depth-text", STOKES + " --bit-depth twelve", "--bit-depth"),
        row("stokes-phase-one-value", STOKES + " --phase 1", "--phase"),
        row("stokes-out-is-file", "stokes {png} --sensor color-polarization --out {png}", "raw.png"),
        row("stokes-out-foreign", STOKES, "out", foreign("out")),
        row("stokes-out-readonly", STOKES.replace("{ws}/out", "{ws}/ro/out"), "ro", readonly("ro"), True),
        row("stokes-rig-without-camera", STOKES + " --rig {rig}", "camera"),
        row("stokes-camera-without-rig", STOKES + " --camera pol_upper", "rig"),
        row("stokes-rig-missing", STOKES + " --rig {ws}/nope.json --camera pol_upper", "nope.json"),
        row("stokes-rig-unknown-camera", STOKES + " --rig {rig} --camera pol_sideways", "pol_sideways"),
        row("stokes-rig-stereo-camera", STOKES + " --rig {rig} --camera stereo0_a", "camera"),
        *_analyzer_rows("stokes", STOKES + " --rig {rig} --camera pol_upper"),
    ]
    for arg, values in {
        "--bit-depth": ("0", "-1", "33", "64"),
        "--black-level": ("-1", "nan", "inf", "65535"),
        "--white-level": ("0", "-1", "nan", "inf"),
        "--exposure": ("0", "-1", "nan", "inf"),
        "--phase": ("4 0", "-1 0", "0 5"),  # the colour mosaic repeats every 4 pixels
    }.items():
        for value in values:
            names = f"{arg.lstrip('-')}|{arg.lstrip('-').replace('-', '_')}"
            rows.append(row(f"stokes{arg}={value.replace(' ', ',')}", f"{STOKES} {arg} {value}", names))
    return rows


def _rig_rows(command: str, argv: str, rel: str) -> list[Row]:
    cam = ["cameras", 0]
    cases = {
        "empty": text(rel, ""),
        "truncated": truncate(rel),
        "not-json": text(rel, "{cameras: oops"),
        "list": text(rel, "[1, 2, 3]"),
        "no-cameras": edit_json(rel, _delete(["cameras"])),
        "cameras-empty": edit_json(rel, _set(["cameras"], [])),
        "cameras-string": edit_json(rel, _set(["cameras"], "pol_upper")),
        "K-string": edit_json(rel, _set([*cam, "K"], "identity")),
        "K-2x2": edit_json(rel, _set([*cam, "K"], [[1.0, 0.0], [0.0, 1.0]])),
        "K-nan": text(rel, "{}"),  # replaced below (json.dumps would write NaN; kept explicit)
        "width-negative": edit_json(rel, _set([*cam, "width"], -48)),
        "width-zero": edit_json(rel, _set([*cam, "width"], 0)),
        "width-string": edit_json(rel, _set([*cam, "width"], "wide")),
        "height-float": edit_json(rel, _set([*cam, "height"], 31.5)),
        "pose-3x3": edit_json(rel, _set([*cam, "world_to_camera"], np.eye(3).tolist())),
        "pose-inf": edit_json(rel, _set([*cam, "world_to_camera"], [[float("inf")] * 4] * 4)),
        "bit-depth-negative": edit_json(rel, _set([*cam, "bit_depth"], -12)),
        "white-below-black": edit_json(
            rel, chain_json(_set([*cam, "black_level"], 100), _set([*cam, "white_level"], 10))
        ),
        "duplicate-camera": edit_json(rel, lambda p: p["cameras"].append(p["cameras"][0])),
        "bad-role": edit_json(rel, _set([*cam, "role"], "spy")),
        "lights-string": edit_json(rel, _set(["lights"], "many")),
        "light-position-nan": edit_json(rel, lambda p: p["lights"][0].update(position_mm=[NAN, 0, 0])),
        "units-inch": edit_json(rel, _set(["units"], "inch")),
    }
    cases["cameras-empty"] = edit_json(rel, _set(["cameras"], []))
    cases["K-nan"] = edit_json(rel, _set([*cam, "K"], [[NAN, 0, 1], [0, 1, 1], [0, 0, 1]]))
    names = {"cameras-empty": "cameras"}
    return [
        row(f"{command}-rig-{name}", argv, f"{Path(rel).name}|{names.get(name, Path(rel).name)}", setup)
        for name, setup in cases.items()
    ]


def _analyzer_rows(command: str, argv: str) -> list[Row]:
    """A polarization camera's ``analyzer`` calibration in ``rig.json`` (docs/sensors.md) gone bad: the
    error names the field ``cameras[0].analyzer``."""
    cases = {
        "ratio-below-one": {"extinction_ratio": 0.5},
        "ratio-text": {"extinction_ratio": "high"},
        "angles-three": {"extinction_ratio": 100, "analyzer_angles_deg": [0, 45, 90]},
        "angles-out-of-order": {"analyzer_angles_deg": [45, 0, 90, 135]},
        "unknown-field": {"extinction": 100},
        "colour-ratio-below-one": {"R": {"extinction_ratio": 1.0}},
        "string": "ideal",
    }
    field = ["cameras", 0, "analyzer"]
    return [
        row(f"{command}-rig-analyzer-{name}", argv, "analyzer", edit_json("rig.json", _set(field, value)))
        for name, value in cases.items()
    ]


def chain_json(*changes: Callable[[dict], None]) -> Callable[[dict], None]:
    def change(payload: dict) -> None:
        for step in changes:
            step(payload)

    return change


def _ingest_rows() -> list[Row]:
    rows = [
        row("ingest-missing-rawdir", "ingest {ws}/nope --rig {rig} --out {ws}/out", "nope"),
        row("ingest-rawdir-is-file", "ingest {rig} --rig {rig} --out {ws}/out", "rig.json"),
        row("ingest-rawdir-empty", "ingest {ws}/empty --rig {rig} --out {ws}/out", "empty", folder("empty")),
        row("ingest-missing-rig", "ingest {rawdir} --rig {ws}/nope.json --out {ws}/out", "nope.json"),
        row("ingest-rig-is-dir", "ingest {rawdir} --rig {rawdir} --out {ws}/out", "rawdir"),
        row("ingest-unknown-camera", INGEST, "pol_sideways", text("rawdir/pol_sideways/0.png", "x")),
        row("ingest-missing-frame", INGEST, "frame 1", remove("rawdir/pol_lower/1.png")),
        row("ingest-missing-camera", INGEST, "pol_lower", remove("rawdir/pol_lower")),
        row("ingest-bad-frame-name", INGEST, "first.png", data("rawdir/pol_upper/first.png", b"")),
        row("ingest-png-empty", INGEST, "1.png", data("rawdir/pol_upper/1.png", b"")),
        row("ingest-png-truncated", INGEST, "1.png", truncate("rawdir/pol_upper/1.png")),
        row("ingest-png-garbage", INGEST, "1.png", data("rawdir/pol_upper/1.png", GARBAGE)),
        row("ingest-png-is-dir", INGEST, "1.png", as_dir("rawdir/pol_upper/1.png")),
        row(
            "ingest-png-wrong-size",
            INGEST,
            "1.png",
            lambda ws: write_png(ws / "rawdir/pol_upper/1.png", np.zeros((16, 16), np.uint16), bit_depth=16),
        ),
        row(
            "ingest-png-rgb",
            INGEST,
            "1.png",
            lambda ws: write_png(ws / "rawdir/pol_upper/1.png", np.zeros((32, 48, 3), np.uint8)),
        ),
        row(
            "ingest-timestamps-header",
            INGEST,
            "timestamps.csv",
            text("rawdir/timestamps.csv", "a,b\n0,0\n1,1\n"),
        ),
        row(
            "ingest-timestamps-value",
            INGEST,
            "timestamps.csv",
            text("rawdir/timestamps.csv", "frame,timestamp_s\n0,0\n1,soon\n"),
        ),
        row(
            "ingest-timestamps-missing",
            INGEST,
            "timestamps.csv",
            text("rawdir/timestamps.csv", "frame,timestamp_s\n0,0\n"),
        ),
        row(
            "ingest-timestamps-nan",
            INGEST,
            "timestamps.csv",
            text("rawdir/timestamps.csv", "frame,timestamp_s\n0,0\n1,nan\n"),
        ),
        row(
            "ingest-timestamps-backwards",
            INGEST,
            "timestamps.csv",
            text("rawdir/timestamps.csv", "frame,timestamp_s\n0,1\n1,0\n"),
        ),
        row("ingest-bad-sequence", INGEST + " --sequence both", "--sequence"),
        row("ingest-fps-text", INGEST + " --fps fast", "--fps"),
        row("ingest-out-is-file", "ingest {rawdir} --rig {rig} --no-progress --out {rig}", "rig.json"),
        row("ingest-out-foreign", INGEST, "out", foreign("out")),
        row("ingest-out-readonly", INGEST.replace("{ws}/out", "{ws}/ro/out"), "ro", readonly("ro"), True),
    ]
    rows += [row(f"ingest-fps={v}", f"{INGEST} --fps {v}", "fps") for v in ("0", "-20", "nan", "inf")]
    return rows + _rig_rows("ingest", INGEST, "rig.json") + _analyzer_rows("ingest", INGEST)


def folder(rel: str) -> Setup:
    def setup(ws: Path) -> None:
        (ws / rel).mkdir(parents=True, exist_ok=True)

    return setup


def _calibrate_rows() -> list[Row]:
    base = "calibrate --rig {calrig} --camera left --square-mm 25 --out {ws}/out.json"
    rows = [
        row("calibrate-missing-rig", CAL.replace("{calrig}", "{ws}/nope.json"), "nope.json"),
        row("calibrate-rig-is-dir", CAL.replace("{calrig}", "{ws}"), "{ws}"),
        row(
            "calibrate-unknown-camera",
            CAL.replace("left01", "left02").replace("--camera left", "--camera middle"),
            "middle",
        ),
        row(
            "calibrate-unknown-stereo",
            CAL + " --stereo-camera middle --stereo-images {data}/calibration/right01.jpg",
            "middle",
        ),
        row("calibrate-no-images", base, "images"),
        row("calibrate-missing-image", f"{base} --images {{ws}}/nope.jpg", "nope.jpg"),
        row("calibrate-glob-nothing", f"{base} --images {{ws}}/*.nothing", "nothing"),
        row(
            "calibrate-image-garbage", f"{base} --images {{ws}}/bad.jpg", "bad.jpg", data("bad.jpg", GARBAGE)
        ),
        row("calibrate-image-empty", f"{base} --images {{ws}}/bad.jpg", "bad.jpg", data("bad.jpg", b"")),
        row("calibrate-image-is-dir", f"{base} --images {{ws}}/bad.jpg", "bad.jpg", folder("bad.jpg")),
        row("calibrate-missing-list", f"{base} --list {{ws}}/nope.xml", "nope.xml"),
        row("calibrate-list-garbage", f"{base} --list {{ws}}/l.xml", "l.xml", data("l.xml", GARBAGE)),
        row("calibrate-list-empty", f"{base} --list {{ws}}/l.xml", "l.xml", data("l.xml", b"")),
        row(
            "calibrate-no-board-found",
            f"{base} --images {{data}}/polarization/fruits_IMX250MZR_crop.png",
            "views",
        ),
        row("calibrate-stereo-unpaired", CAL + " --stereo-camera right", "stereo"),
        row("calibrate-square-text", CAL.replace("--square-mm 25", "--square-mm wide"), "--square-mm"),
        row("calibrate-no-camera", CAL.replace("--camera left", ""), "--camera"),
        row("calibrate-out-is-dir", CAL3.replace("{ws}/out.json", "{ws}/outdir"), "outdir", folder("outdir")),
        row("calibrate-rig-corrupt", CAL, "calrig.json", text("calrig.json", "{oops")),
        row("calibrate-rig-empty", CAL, "calrig.json", text("calrig.json", "")),
        row(
            "calibrate-marker-bigger",
            CAL.replace("chessboard", "") + " --board charuco:5x7 --marker-mm 30",
            "marker",
        ),
    ]
    rows += [
        row(f"calibrate-square-mm={v}", CAL.replace("--square-mm 25", f"--square-mm {v}"), "square")
        for v in ("0", "-25", "nan", "inf")
    ]
    rows += [
        row(f"calibrate-marker-mm={v}", f"{CAL} --board charuco:5x7 --marker-mm {v}", "marker")
        for v in ("0", "-5", "nan")
    ]
    for board in (
        "chessboard:9",
        "chessboard:axb",
        "chessboard:1x1",
        "chessboard:0x6",
        "abacus:9x6",
        "charuco:5x7:NOPE",
        "charuco:x",
    ):
        rows.append(row(f"calibrate-board={board}", f"{CAL} --board {board}", "board|NOPE"))
    return rows


CALPOL = "calibrate-polarization {polframes} --rig {rig} --camera pol_upper --out {ws}/out.json"


def _png16(rel: str, value: int, shape: tuple[int, int] = (32, 48)) -> Setup:
    def setup(ws: Path) -> None:
        write_png(ws / rel, np.full(shape, value, np.uint16), bit_depth=16)

    return setup


def _calibrate_polarization_rows() -> list[Row]:
    frame = "polframes/pol_090.png"
    mono = chain_json(
        _set(["cameras", 0, "sensor"], "mono-polarization"), _set(["cameras", 0, "colour_channels"], {})
    )
    return [
        row("calpol-missing-frames", CALPOL.replace("{polframes}", "{ws}/nope"), "nope"),
        row("calpol-frames-empty", CALPOL.replace("{polframes}", "{ws}/empty"), "empty", folder("empty")),
        row("calpol-frames-is-file", CALPOL.replace("{polframes}", "{rig}"), "rig.json"),
        row("calpol-no-camera", CALPOL.replace("--camera pol_upper", ""), "--camera"),
        row("calpol-unknown-camera", CALPOL.replace("pol_upper", "nope"), "nope"),
        row("calpol-rgb-camera", CALPOL.replace("pol_upper", "stereo0_a"), "stereo0_a"),
        row("calpol-missing-rig", CALPOL.replace("{rig}", "{ws}/nope.json"), "nope.json"),
        row("calpol-rig-corrupt", CALPOL, "rig.json", text("rig.json", "{oops")),
        row("calpol-mono-colours", CALPOL + " --colours G", "--colours", edit_json("rig.json", mono)),
        row("calpol-colour-unknown", CALPOL + " --colours X", "colours"),
        row(
            "calpol-two-angles",
            CALPOL,
            "3 distinct",
            chain(remove("polframes/pol_090.png"), remove("polframes/pol_135.png")),
        ),
        row("calpol-angles-repeat", CALPOL + " --angles-deg 0 180 0 90", "3 distinct"),
        row("calpol-angles-count", CALPOL + " --angles-deg 0 45", "--angles-deg"),
        row("calpol-angles-text", CALPOL + " --angles-deg north", "--angles-deg"),
        row("calpol-unnamed-frame", CALPOL, "frame.png", _png16("polframes/frame.png", 100)),
        row("calpol-frame-saturated", CALPOL, "pol_090", _png16(frame, 4095)),
        row("calpol-frame-dark", CALPOL, "pol_090", _png16(frame, 0)),
        row("calpol-frame-garbage", CALPOL, "pol_090", data(frame, GARBAGE)),
        row("calpol-frame-empty", CALPOL, "pol_090", data(frame, b"")),
        row("calpol-frame-size", CALPOL, "pol_090", _png16(frame, 100, (16, 16))),
        row("calpol-listing-garbage", CALPOL, "frames.json", text("polframes/frames.json", "{oops")),
        row(
            "calpol-listing-no-angle",
            CALPOL,
            "polarizer_deg",
            text("polframes/frames.json", json.dumps({"frames": [{"file": "pol_000.png"}]})),
        ),
        row("calpol-roi-outside", CALPOL + " --roi 0,0,999,999", "roi"),
        row("calpol-roi-text", CALPOL + " --roi middle", "--roi"),
        row("calpol-out-foreign", CALPOL, "out.json", text("out.json", "thesis")),
        row("calpol-out-is-dir", CALPOL, "out.json", folder("out.json")),
    ]


def _skin_rows() -> list[Row]:
    rows = [
        row("skin-missing-csv", "skin-fit {ws}/nope.csv --out {ws}/out", "nope.csv"),
        row("skin-csv-is-dir", "skin-fit {ws} --out {ws}/out", "{ws}"),
        row("skin-csv-empty", SKIN, "spectra.csv", text("spectra.csv", "")),
        row("skin-csv-header-only", SKIN, "spectra.csv", text("spectra.csv", "wavelength_nm,a\n")),
        row("skin-csv-no-wavelength", SKIN, "wavelength_nm", text("spectra.csv", "nm,a\n500,0.3\n600,0.4\n")),
        row("skin-csv-no-samples", SKIN, "spectra.csv", text("spectra.csv", "wavelength_nm\n500\n600\n")),
        row(
            "skin-csv-text-value",
            SKIN,
            "spectra.csv",
            text("spectra.csv", "wavelength_nm,a\n500,pale\n600,0.4\n"),
        ),
        row(
            "skin-csv-ragged",
            SKIN,
            "spectra.csv",
            text("spectra.csv", "wavelength_nm,a,b\n500,0.3\n600,0.4,0.5\n"),
        ),
        row("skin-csv-binary", SKIN, "spectra.csv", data("spectra.csv", GARBAGE)),
        row("skin-csv-truncated", SKIN, "spectra.csv", truncate("spectra.csv", 0.01)),
        row("skin-csv-nan", SKIN, "spectra.csv", _spectra_edit(lambda r: r.__setitem__(5, np.nan))),
        row("skin-csv-inf", SKIN, "spectra.csv", _spectra_edit(lambda r: r.__setitem__(5, np.inf))),
        row("skin-csv-above-one", SKIN, "spectra.csv", _spectra_edit(lambda r: r.__setitem__(5, 1.7))),
        row("skin-csv-negative", SKIN, "spectra.csv", _spectra_edit(lambda r: r.__setitem__(5, -0.2))),
        row("skin-csv-percent", SKIN, "spectra.csv", _spectra_edit(lambda r: r.__imul__(100.0))),
        row(
            "skin-csv-duplicate-wavelength",
            SKIN,
            "spectra.csv",
            text("spectra.csv", "wavelength_nm,a\n500,0.3\n500,0.4\n600,0.4\n"),
        ),
        row(
            "skin-csv-decreasing",
            SKIN,
            "spectra.csv",
            text("spectra.csv", "wavelength_nm,a\n600,0.3\n550,0.4\n500,0.4\n"),
        ),
        row(
            "skin-csv-outside-band",
            SKIN,
            "spectra.csv",
            text("spectra.csv", "wavelength_nm,a\n900,0.3\n950,0.4\n1000,0.4\n"),
        ),
        row("skin-band-reversed", SKIN + " --min-nm 700 --max-nm 420", "nm"),
        row("skin-band-empty", SKIN + " --min-nm 500 --max-nm 500", "nm"),
        row("skin-out-is-file", "skin-fit {csv} --out {csv}", "spectra.csv"),
        row("skin-out-foreign", SKIN, "out", foreign("out")),
        row("skin-out-readonly", SKIN.replace("{ws}/out", "{ws}/ro/out"), "ro", readonly("ro"), True),
        row("skin-iterations-text", SKIN + " --iterations many", "--iterations"),
    ]
    for arg, values in {
        "--min-nm": ("-10", "nan"),
        "--max-nm": ("nan", "inf"),
        "--max-offset": ("-0.1", "nan", "inf"),
        "--iterations": ("0", "-1"),
        "--starts": ("0", "-1"),
    }.items():
        names = "nm" if arg.endswith("-nm") else arg.lstrip("-").split("-")[0]
        rows += [row(f"skin{arg}={v}", f"{SKIN} {arg} {v}", names) for v in values]
    return rows


def _spectra_edit(change: Callable[[np.ndarray], object]) -> Setup:
    def setup(ws: Path) -> None:
        lines = (ws / "spectra.csv").read_text().splitlines()
        values = np.array([[float(x) for x in line.split(",")] for line in lines[1:]])
        column = values[:, 1].copy()
        change(column)
        values[:, 1] = column
        body = "\n".join(",".join(repr(float(x)) for x in r) for r in values)
        (ws / "spectra.csv").write_text(lines[0] + "\n" + body + "\n")

    return setup


def _simulate_demo_bench_rows() -> list[Row]:
    sim = "simulate --preset tiny --out {ws}/out"
    angle = sim + " --analyzer-angle-error-deg"
    rows = [
        row("simulate-skin-type-VII", sim + " --skin-type VII", "skin"),
        row("simulate-skin-type-empty", sim + " --skin-type x", "skin"),
        row("simulate-sequences-unknown", sim + " --sequences static,wobbly", "wobbly"),
        row("simulate-sequences-empty", sim + " --sequences ,", "sequences"),
        row("simulate-seed-negative", sim + " --seed -1", "seed"),
        row("simulate-seed-text", sim + " --seed lucky", "--seed"),
        row("simulate-preset-unknown", sim + " --preset huge", "--preset"),
        row("simulate-extinction-ratio-one", sim + " --extinction-ratio 1", "--extinction-ratio"),
        row("simulate-extinction-ratio-nan", sim + " --extinction-ratio nan", "--extinction-ratio"),
        row("simulate-extinction-ratio-text", sim + " --extinction-ratio high", "--extinction-ratio"),
        row("simulate-extinction-ratio-two", sim + " --extinction-ratio 100,50", "--extinction-ratio"),
        row("simulate-angle-error-negative", angle + " -1", "--analyzer-angle-error"),
        row("simulate-angle-error-inf", angle + " inf", "--analyzer-angle-error"),
        row("simulate-angle-error-three", angle + " 1,2,3", "--analyzer-angle-error"),
        row("simulate-angle-error-large", angle + " 0,0,30,0", "--analyzer-angle-error"),
        row("simulate-angle-error-text", angle + " one", "--analyzer-angle-error"),
        row("simulate-analyzer-seed-negative", sim + " --analyzer-seed -1", "--analyzer-seed"),
        row("simulate-analyzer-seed-text", sim + " --analyzer-seed x", "--analyzer-seed"),
        row("simulate-calibration-both", sim + " --write-calibration --no-calibration", "calibration"),
        row("simulate-no-out", "simulate --preset tiny", "--out"),
        row("simulate-out-is-file", "simulate --preset tiny --out {ws}/f", "f", text("f", "mine\n")),
        row("simulate-out-foreign", sim, "out", foreign("out")),
        row("simulate-out-readonly", sim.replace("{ws}/out", "{ws}/ro/out"), "ro", readonly("ro"), True),
        row("demo-skin-type-VII", "demo --preset tiny --skin-type VII --out {ws}/out", "skin"),
        row("demo-preset-unknown", DEMO + " --preset huge", "--preset"),
        row("demo-size-text", DEMO + " --size big", "--size"),
        row("demo-eta-text", DEMO + " --eta glass", "--eta"),
        row("demo-out-is-file", "demo --sphere --out {ws}/f", "f", text("f", "mine\n")),
        row("demo-out-foreign", DEMO, "out", foreign("out")),
        row("demo-tiny-out-is-file", "demo --preset tiny --out {ws}/f", "f", text("f", "mine\n")),
        row("demo-tiny-out-foreign", "demo --preset tiny --out {ws}/out", "out", foreign("out")),
        row("demo-out-readonly", DEMO.replace("{ws}/out", "{ws}/ro/out"), "ro", readonly("ro"), True),
        row("bench-side-text", BENCH + " --side wide", "--side"),
        row("bench-device-unknown", BENCH + " --device quantum", "quantum"),
        row("bench-device-gpu-index", BENCH + " --device cuda:99", "cuda"),
    ]
    rows += [row(f"demo-size={v}", f"{DEMO} --size {v}", "size") for v in ("0", "-8", "1", "100000")]
    rows += [row(f"demo-eta={v}", f"{DEMO} --eta {v}", "eta") for v in ("0", "-1.4", "0.5", "nan", "inf")]
    for arg, values in {
        "--side": ("0", "-1", "7"),
        "--frames": ("0", "-1"),
        "--iterations": ("0", "-1"),
        "--baseline-texels": ("0", "-3"),
        "--threads": ("0", "-1"),
        "--seconds": ("0", "-1", "nan", "inf"),
        "--repeats": ("0", "-2"),
    }.items():
        rows += [row(f"bench{arg}={v}", f"{BENCH} {arg} {v}", arg.lstrip("-")) for v in values]
    return rows


def _mesh_rows() -> list[Row]:
    mesh = "{sim}/ground_truth/mesh_rest.obj"

    def copy_mesh(transform: Callable[[str], str]) -> Setup:
        def setup(ws: Path) -> None:
            (ws / "m.obj").write_text(transform((ws / "sim/ground_truth/mesh_rest.obj").read_text()))

        return setup

    no_uv = copy_mesh(
        lambda s: "\n".join(
            line.split()[0] + " " + " ".join(t.split("/")[0] for t in line.split()[1:])
            if line.startswith("f ")
            else line
            for line in s.splitlines()
            if not line.startswith("vt ")
        )
    )
    return [
        row("reconstruct-mesh-missing", MESHR, "m.obj"),
        row("reconstruct-mesh-empty", MESHR, "m.obj", text("m.obj", "")),
        row("reconstruct-mesh-garbage", MESHR, "m.obj", data("m.obj", GARBAGE)),
        row("reconstruct-mesh-truncated", MESHR, "m.obj", copy_mesh(lambda s: s[: len(s) // 2])),
        row("reconstruct-mesh-no-uv", MESHR, "m.obj", no_uv),
        row(
            "reconstruct-mesh-nan-vertex",
            MESHR,
            "m.obj",
            copy_mesh(lambda s: re.sub(r"^v .*$", "v nan 0 0", s, count=1, flags=re.M)),
        ),
        row(
            "reconstruct-mesh-bad-index",
            MESHR,
            "m.obj",
            copy_mesh(lambda s: s + "f 999999/1 999998/1 999997/1\n"),
        ),
        row("reconstruct-mesh-is-dir", MESHR, "m.obj", folder("m.obj")),
        row(
            "reconstruct-mesh-unknown-type",
            MESHR.replace("m.obj", "m.stl"),
            "m.stl",
            text("m.stl", "solid x\n"),
        ),
        row(
            "reconstruct-mesh-without-poses",
            "reconstruct {sim}/static --mesh " + mesh + " --quiet --out {ws}/out",
            "poses",
        ),
        row(
            "reconstruct-poses-without-mesh",
            "reconstruct {sim}/static --poses {sim}/ground_truth/static/poses.json --quiet --out {ws}/out",
            "mesh",
        ),
    ]


def _poses_rows() -> list[Row]:
    def poses(change: Callable[[list], object]) -> Setup:
        def setup(ws: Path) -> None:
            payload = json.loads((ws / "sim/ground_truth/static/poses.json").read_text())
            matrices = payload["poses"] if isinstance(payload, dict) else payload
            replaced = change(matrices)
            (ws / "p.json").write_text(json.dumps(matrices if replaced is None else replaced))

        return setup

    return [
        row("reconstruct-poses-missing", POSER, "p.json"),
        row("reconstruct-poses-empty", POSER, "p.json", text("p.json", "")),
        row("reconstruct-poses-not-json", POSER, "p.json", text("p.json", "[[1, 0")),
        row("reconstruct-poses-empty-list", POSER, "p.json", text("p.json", "[]")),
        row("reconstruct-poses-object", POSER, "p.json", text("p.json", '{"frames": 4}')),
        row("reconstruct-poses-too-few", POSER, "p.json", poses(lambda m: m[:2])),
        row("reconstruct-poses-too-many", POSER, "p.json", poses(lambda m: m + m)),
        row("reconstruct-poses-3x3", POSER, "p.json", poses(lambda m: [np.eye(3).tolist() for _ in m])),
        row("reconstruct-poses-nan", POSER, "p.json", poses(lambda m: m[1][0].__setitem__(3, NAN))),
        row("reconstruct-poses-inf", POSER, "p.json", poses(lambda m: m[0][2].__setitem__(3, float("inf")))),
        row("reconstruct-poses-string", POSER, "p.json", poses(lambda m: m[0][0].__setitem__(0, "one"))),
        row(
            "reconstruct-poses-singular",
            POSER,
            "p.json",
            poses(lambda m: [np.zeros((4, 4)).tolist() for _ in m]),
        ),
        row(
            "reconstruct-poses-npy-garbage", POSER.replace("p.json", "p.npy"), "p.npy", data("p.npy", GARBAGE)
        ),
        row(
            "reconstruct-poses-npy-shape",
            POSER.replace("p.json", "p.npy"),
            "p.npy",
            lambda ws: np.save(ws / "p.npy", np.zeros((4, 3))),
        ),
        row("reconstruct-poses-is-dir", POSER, "p.json", folder("p.json")),
    ]


def _capture_store_rows() -> list[Row]:
    """The capture store's manifest, rig and derived.zarr, corrupted."""
    static = "sim/static"
    return [
        row("reconstruct-manifest-missing", SIMR, "manifest.json", remove(f"{static}/manifest.json")),
        row("reconstruct-manifest-empty", SIMR, "manifest.json", text(f"{static}/manifest.json", "")),
        row("reconstruct-manifest-corrupt", SIMR, "manifest.json", truncate(f"{static}/manifest.json")),
        row(
            "reconstruct-manifest-format",
            SIMR,
            "manifest.json",
            edit_json(f"{static}/manifest.json", _set(["format"], "other")),
        ),
        row(
            "reconstruct-manifest-incomplete",
            SIMR,
            "complete",
            edit_json(f"{static}/manifest.json", _set(["complete"], False)),
        ),
        row(
            "reconstruct-manifest-frames-string",
            SIMR,
            "frames",
            edit_json(f"{static}/manifest.json", _set(["frames"], "all")),
        ),
        row(
            "reconstruct-manifest-frame-count",
            SIMR,
            "frame",
            edit_json(f"{static}/manifest.json", _set(["frame_count"], 40)),
        ),
        row("reconstruct-capture-rig-missing", SIMR, "rig.json", remove(f"{static}/rig.json")),
        row("reconstruct-capture-rig-corrupt", SIMR, "rig.json", text(f"{static}/rig.json", "{")),
        row(
            "reconstruct-capture-rig-nan-K",
            SIMR,
            "rig.json",
            edit_json(f"{static}/rig.json", _set(["cameras", 0, "K", 0, 0], NAN)),
        ),
        row("reconstruct-zarr-missing", SIMR, "derived.zarr", remove(f"{static}/derived.zarr")),
        row(
            "reconstruct-zarr-meta-missing", SIMR, "derived.zarr", remove(f"{static}/derived.zarr/zarr.json")
        ),
        row(
            "reconstruct-zarr-meta-corrupt",
            SIMR,
            "derived.zarr",
            text(f"{static}/derived.zarr/zarr.json", "{"),
        ),
        row("reconstruct-zarr-stacks-missing", SIMR, "stacks", remove(f"{static}/derived.zarr/stacks")),
        row(
            "reconstruct-zarr-chunks-corrupt",
            SIMR,
            "derived.zarr",
            _corrupt_chunks(f"{static}/derived.zarr/stacks"),
        ),
    ]


def _reconstruct_rows() -> list[Row]:
    rows = [
        row("reconstruct-capture-missing", SIMR.replace("{sim}/static", "{ws}/nope"), "nope"),
        row("reconstruct-capture-is-file", SIMR.replace("{sim}/static", "{rig}"), "rig.json"),
        row(
            "reconstruct-capture-empty-dir",
            SIMR.replace("{sim}/static", "{ws}/empty"),
            "empty",
            folder("empty"),
        ),
        row("reconstruct-geometry-missing", SIMR.replace("{sim}/ground_truth", "{ws}/nope"), "nope"),
        row("reconstruct-geometry-no-poses", SIMR, "poses", remove("sim/ground_truth/static/poses.json")),
        row("reconstruct-geometry-no-mesh", SIMR, "mesh_rest.obj", remove("sim/ground_truth/mesh_rest.obj")),
        row("reconstruct-iterations-text", SIMR + " --iterations some", "--iterations"),
        row("reconstruct-optimizer-unknown", SIMR + " --optimizer sgd", "--optimizer"),
        row("reconstruct-no-out", "reconstruct {sim}/static --quiet", "--out"),
        row("reconstruct-device-unknown", SIMR + " --device quantum", "quantum"),
        row("reconstruct-out-is-file", SIMR.replace("{ws}/out", "{rig}"), "rig.json"),
        row("reconstruct-out-is-capture", SIMR.replace("{ws}/out", "{sim}/static"), "static"),
        row("reconstruct-out-foreign", SIMR, "out", foreign("out")),
        row("reconstruct-resume-foreign", SIMR + " --resume", "out", foreign("out")),
        row("reconstruct-out-readonly", SIMR.replace("{ws}/out", "{ws}/ro/out"), "ro", readonly("ro"), True),
    ]
    for arg, values in {
        "--texture-resolution": ("0", "-16", "1", "1000000"),
        "--iterations": ("0", "-1"),
        "--lr": ("0", "-0.03", "nan", "inf"),
        "--refine-lobes": ("-1",),
        "--unwrap-cache-mb": ("-1", "lots"),
        "--patch": ("0", "3", "lots"),
        "--sample-budget": ("999", "-1"),
        "--holdout-every": ("-1",),
        "--threads": ("0", "-1"),
    }.items():
        name = arg.lstrip("-").split("-")[0]
        rows += [row(f"reconstruct{arg}={v}", f"{SIMR} {arg} {v}", name) for v in values]
    return rows + _capture_store_rows() + _mesh_rows() + _poses_rows()


def _corrupt_chunks(rel: str) -> Setup:
    def setup(ws: Path) -> None:
        for path in sorted((ws / rel).rglob("*")):
            if path.is_file() and path.name != "zarr.json":
                path.write_bytes(GARBAGE)

    return setup


def _result_corruptions(
    prefix: str, argv: str, maps: tuple[str, ...], files: bool = True, result_json: bool = True
) -> list[Row]:
    """The RESULT folder's files, one corruption each (missing, empty, truncated, garbage, a folder)."""
    rows = [
        row(f"{prefix}-result-missing", argv.replace("{result}", "{ws}/nope"), "nope"),
        row(f"{prefix}-result-is-file", argv.replace("{result}", "{rig}"), "rig.json"),
        row(f"{prefix}-result-empty-dir", argv.replace("{result}", "{ws}/empty"), "empty", folder("empty")),
    ]
    json_rows = [
        row(f"{prefix}-result-json-corrupt", argv, "result.json", truncate("result/result.json")),
        row(f"{prefix}-result-json-list", argv, "result.json", text("result/result.json", "[]")),
        row(
            f"{prefix}-result-json-format",
            argv,
            "result.json",
            edit_json("result/result.json", _set(["format"], "other")),
        ),
        row(
            f"{prefix}-result-json-version",
            argv,
            "version",
            edit_json("result/result.json", _set(["version"], 99)),
        ),
        row(
            f"{prefix}-result-json-channels",
            argv,
            "channel_names",
            edit_json("result/result.json", _set(["channel_names"], ["r"])),
        ),
        row(
            f"{prefix}-result-json-resolution",
            argv,
            "texture_resolution",
            edit_json("result/result.json", _set(["texture_resolution"], [-1, 0])),
        ),
    ]
    file_rows = [
        row(f"{prefix}-mesh-missing", argv, "mesh.obj", remove("result/mesh.obj")),
        row(f"{prefix}-mesh-garbage", argv, "mesh.obj", data("result/mesh.obj", GARBAGE)),
        row(f"{prefix}-rig-missing", argv, "rig.json", remove("result/rig.json")),
        row(f"{prefix}-rig-corrupt", argv, "rig.json", truncate("result/rig.json")),
    ]
    rows += (
        (json_rows if result_json else [])
        + (file_rows if files else [])
        + [
            row(f"{prefix}-mask-missing", argv, "mask.png", remove("result/maps/mask.png")),
            row(f"{prefix}-mask-garbage", argv, "mask.png", data("result/maps/mask.png", GARBAGE)),
            row(
                f"{prefix}-mask-wrong-size",
                argv,
                "mask.png",
                lambda ws: write_png(ws / "result/maps/mask.png", np.full((5, 7), 255, np.uint8)),
            ),
        ]
    )
    for name in maps:
        rel = f"result/maps/{name}.exr"
        rows += [
            row(f"{prefix}-{name}-missing", argv, f"{name}.exr", remove(rel)),
            row(f"{prefix}-{name}-empty", argv, f"{name}.exr", data(rel, b"")),
            row(f"{prefix}-{name}-truncated", argv, f"{name}.exr", truncate(rel)),
            row(f"{prefix}-{name}-garbage", argv, f"{name}.exr", data(rel, EXR_HEADER_ONLY + GARBAGE)),
        ]
    rows.append(row(f"{prefix}-{maps[0]}-wrong-size", argv, f"{maps[0]}.exr|mask.png", _small_map(maps[0])))
    rows.append(row(f"{prefix}-{maps[0]}-nan", argv, f"{maps[0]}.exr|'{maps[0]}'", _nan_map(maps[0])))
    return rows


def _small_map(name: str) -> Setup:
    def setup(ws: Path) -> None:
        from polarface.io import read_exr

        channels = read_exr(ws / f"result/maps/{name}.exr")
        write_exr(ws / f"result/maps/{name}.exr", {k: v[:5, :7].copy() for k, v in channels.items()})

    return setup


def _nan_map(name: str) -> Setup:
    def setup(ws: Path) -> None:
        from polarface.io import read_exr

        channels = read_exr(ws / f"result/maps/{name}.exr")
        write_exr(ws / f"result/maps/{name}.exr", {k: np.full_like(v, np.nan) for k, v in channels.items()})

    return setup


def _evaluate_rows() -> list[Row]:
    return [
        *_result_corruptions("evaluate", EVAL, ("eta", "rho_sss_bar", "alpha_s"), files=False),
        row("evaluate-gt-missing", EVAL.replace("--gt {sim}", "--gt {ws}/nope"), "nope"),
        row("evaluate-gt-is-file", EVAL.replace("--gt {sim}", "--gt {rig}"), "rig.json"),
        row("evaluate-gt-empty-dir", EVAL.replace("--gt {sim}", "--gt {ws}/empty"), "empty", folder("empty")),
        row("evaluate-gt-map-missing", EVAL, "eta.exr", remove("sim/ground_truth/maps/eta.exr")),
        row("evaluate-gt-map-garbage", EVAL, "eta.exr", data("sim/ground_truth/maps/eta.exr", GARBAGE)),
        row("evaluate-gt-mask-missing", EVAL, "mask.png", remove("sim/ground_truth/maps/mask.png")),
        row("evaluate-groups-unknown", EVAL + " --groups nope", "nope"),
        row("evaluate-no-gt", "evaluate {result}", "--gt"),
        row("evaluate-out-is-dir", EVAL + " --out {ws}/o", "o", foreign("o")),
        row("evaluate-out-readonly", EVAL + " --out {ws}/ro/m.json", "ro", readonly("ro"), True),
    ]


def _biophysical_rows() -> list[Row]:
    rows = _result_corruptions("biophysical", BIO, ("rho_sss_bar",))
    rows += [
        row("biophysical-gt-missing", BIO + " --gt {ws}/nope", "nope"),
        row("biophysical-device-unknown", BIO + " --device quantum", "quantum"),
        row("biophysical-coarse-text", BIO + " --coarse-factor big", "--coarse-factor"),
        row(
            "biophysical-result-readonly",
            BIO.replace("{result}", "{ws}/ro"),
            "ro",
            chain(folder("ro"), readonly("ro")),
            True,
        ),
    ]
    for arg, values in {
        "--coarse-factor": ("0", "-2"),
        "--shape-rounds": ("-1",),
        "--gamut-tolerance": ("-0.1", "nan"),
        "--threads": ("0", "-1"),
    }.items():
        rows += [
            row(f"biophysical{arg}={v}", f"{BIO} {arg} {v}", arg.lstrip("-").split("-")[0]) for v in values
        ]
    return rows


def _render_rows() -> list[Row]:
    rows = _result_corruptions("render", RENDER, ("eta", "rho_s", "c_h_out"), result_json=False)
    rows += [
        row("render-sog-corrupt", RENDER, "sog.json", truncate("result/maps/sog.json")),
        row("render-sog-empty", RENDER, "sog.json", text("result/maps/sog.json", "")),
        row("render-camera-unknown", RENDER + " --camera pol_sideways", "pol_sideways"),
        row("render-poses-missing", RENDER + " --poses {ws}/nope.json", "nope.json"),
        row("render-poses-corrupt", RENDER + " --poses {ws}/p.json", "p.json", text("p.json", "[[")),
        row("render-poses-empty-list", RENDER + " --poses {ws}/p.json", "p.json", text("p.json", "[]")),
        row(
            "render-pose-frame-out-of-range",
            RENDER + " --poses {sim}/ground_truth/static/poses.json --pose-frame 99",
            "pose-frame",
        ),
        row(
            "render-pose-frame-negative",
            RENDER + " --poses {sim}/ground_truth/static/poses.json --pose-frame -1",
            "pose-frame",
        ),
        row("render-pose-frame-text", RENDER + " --pose-frame first", "--pose-frame"),
        row("render-out-is-file", RENDER.replace("{ws}/out", "{rig}"), "rig.json"),
        row("render-out-foreign", RENDER, "out", foreign("out")),
        row("render-out-readonly", RENDER.replace("{ws}/out", "{ws}/ro/out"), "ro", readonly("ro"), True),
    ]
    for edit in (
        "C_h_out",
        "C_h_out=abc",
        "nope=2x",
        "C_m=-1x",
        "C_m=nanx",
        "C_m=infx",
        "C_m=2x,C_m=3x",
        "=",
    ):
        rows.append(row(f"render-edit={edit}", f"{RENDER} --edit {edit}", "edit"))
    for arg, values in {
        "--polarizer-deg": ("nan", "inf"),
        "--strip-width-mm": ("0", "-10", "nan"),
        "--exposure": ("0", "-1", "nan", "inf"),
    }.items():
        argv = RENDER.replace(" --no-strip", "") if arg == "--strip-width-mm" else RENDER
        rows += [row(f"render{arg}={v}", f"{argv} {arg} {v}", arg.lstrip("-").split("-")[0]) for v in values]
    return rows


def _ior_rows() -> list[Row]:
    scene = "ior/scene.json"
    rows = [
        row("ior-no-dir", "ior", "dir"),
        row("ior-dir-missing", "ior {ws}/nope", "nope"),
        row("ior-dir-is-file", "ior {rig}", "rig.json"),
        row("ior-scene-missing", IOR, "scene.json", remove(scene)),
        row("ior-scene-empty", IOR, "scene.json", text(scene, "")),
        row("ior-scene-truncated", IOR, "scene.json", truncate(scene)),
        row("ior-scene-list", IOR, "scene", text(scene, "[]")),
        row("ior-scene-is-dir", IOR, "scene.json", as_dir(scene)),
        row("ior-scene-units", IOR, "units", edit_json(scene, _set(["units"], "inch"))),
        row("ior-scene-no-camera", IOR, "camera", edit_json(scene, _delete(["camera"]))),
        row("ior-scene-no-sphere", IOR, "sphere", edit_json(scene, _delete(["sphere"]))),
        row("ior-scene-K-shape", IOR, "K", edit_json(scene, _set(["camera", "K"], [1, 2, 3]))),
        row("ior-scene-K-nan", IOR, "NaN", edit_json(scene, _set(["camera", "K", 0, 0], NAN))),
        row("ior-scene-K-string", IOR, "K", edit_json(scene, _set(["camera", "K"], "pinhole"))),
        row("ior-scene-radius-negative", IOR, "radius", edit_json(scene, _set(["sphere", "radius"], -40))),
        row("ior-scene-radius-nan", IOR, "radius", edit_json(scene, _set(["sphere", "radius"], NAN))),
        row("ior-scene-width-zero", IOR, "width|image size", edit_json(scene, _set(["camera", "width"], 0))),
        row("ior-scene-width-string", IOR, "width", edit_json(scene, _set(["camera", "width"], "wide"))),
        row("ior-scene-size-mismatch", IOR, "scene camera", edit_json(scene, _set(["camera", "width"], 64))),
        row(
            "ior-scene-sphere-behind",
            IOR,
            "sphere",
            edit_json(scene, _set(["sphere", "center"], [0.0, 0.0, -1000.0])),
        ),
        row("ior-scene-lights-string", IOR, "lights", edit_json(scene, _set(["lights"], "on"))),
        row(
            "ior-scene-polarizer-er",
            IOR,
            "polarizer",
            edit_json(scene, _set(["polarizer"], {"extinction_ratio": 0.5})),
        ),
        row("ior-eta-range-text", IOR + " --eta-range low high", "--eta-range"),
        row(
            "ior-images-zero",
            IOR,
            "sphere pixel",
            lambda ws: [
                write_exr(ws / f"ior/{n}.exr", {"Y": np.zeros((32, 32), np.float32)})
                for n in ("I0", "I45", "I90", "I135")
            ],
        ),
        row(
            "ior-image-wrong-size",
            IOR,
            "I45",
            lambda ws: write_exr(ws / "ior/I45.exr", {"Y": np.ones((16, 16), np.float32)}),
        ),
        row(
            "ior-image-nan",
            IOR,
            "I90",
            lambda ws: write_exr(ws / "ior/I90.exr", {"Y": np.full((32, 32), np.nan, np.float32)}),
        ),
        row(
            "ior-image-negative",
            IOR,
            "I90|sphere pixel",
            lambda ws: write_exr(ws / "ior/I90.exr", {"Y": np.full((32, 32), -1.0, np.float32)}),
        ),
    ]
    for name in ("I0", "I45", "I90", "I135"):
        rows += [
            row(f"ior-{name}-missing", IOR, f"{name}.exr", remove(f"ior/{name}.exr")),
            row(f"ior-{name}-garbage", IOR, f"{name}.exr", data(f"ior/{name}.exr", GARBAGE)),
        ]
    rows += [
        row("ior-I0-empty", IOR, "I0.exr", data("ior/I0.exr", b"")),
        row("ior-I0-truncated", IOR, "I0.exr", truncate("ior/I0.exr")),
    ]
    for lo_hi in ("3.0 1.05", "1.5 1.5", "-1 2", "0 2", "nan 2", "1.05 inf", "0.5 0.9"):
        rows.append(row(f"ior-eta-range={lo_hi.replace(' ', ',')}", f"{IOR} --eta-range {lo_hi}", "eta"))
    return rows


GEOMR = "geometry {sim}/static --quiet --out {ws}/out"


def _same_centre(first: int, second: int) -> Callable[[dict], None]:
    """A rig whose camera ``second`` sits where camera ``first`` is (a broken stereo calibration)."""

    def change(payload: dict) -> None:
        cameras = payload["cameras"]
        cameras[second]["world_to_camera"] = cameras[first]["world_to_camera"]

    return change


def _geometry_rows() -> list[Row]:
    """``polarface geometry`` and ``reconstruct``'s default stereo geometry stage. The session's sphere
    capture has black stereo images: its reference frame has no stereo point."""
    rig = "sim/static/rig.json"
    return [
        row("geometry-capture-missing", GEOMR.replace("{sim}/static", "{ws}/nope"), "nope"),
        row("geometry-capture-is-file", GEOMR.replace("{sim}/static", "{rig}"), "rig.json"),
        row("geometry-no-out", "geometry {sim}/static --quiet", "--out"),
        row("geometry-texture-resolution=4", GEOMR + " --texture-resolution 4", "resolution"),
        row("geometry-reference-frame=99", GEOMR + " --reference-frame 99", "reference_frame"),
        row("geometry-no-stereo-points", GEOMR, "--mesh MESH --poses POSES"),
        row("geometry-pair-broken", GEOMR, "stereo1_a + stereo1_b", edit_json(rig, _same_centre(4, 5))),
        row("geometry-out-foreign", GEOMR, "out", foreign("out")),
        row(
            "reconstruct-stereo-no-points",
            "reconstruct {sim}/static --texture-resolution 16 --quiet --out {ws}/out",
            "--mesh MESH --poses POSES",
        ),
    ]


ROWS: list[Row] = [
    *_stokes_rows(),
    *_ingest_rows(),
    *_calibrate_rows(),
    *_calibrate_polarization_rows(),
    *_skin_rows(),
    *_simulate_demo_bench_rows(),
    *_reconstruct_rows(),
    *_geometry_rows(),
    *_evaluate_rows(),
    *_biophysical_rows(),
    *_render_rows(),
    *_ior_rows(),
    *_import_authors_rows(),
]

#: Rows that fail on today's code, grouped by the defect they show (run as strict xfail; empty when every
#: row passes).
DEFECTS: dict[str, tuple[str, ...]] = {}
XFAIL: dict[str, str] = {case: reason for reason, cases in DEFECTS.items() for case in cases}


# ----------------------------------------------------------------------------------------------------------
# The runner

COPIED = {
    "sim": "sim",
    "result": "result",
    "png": "raw.png",
    "rig": "rig.json",
    "rawdir": "rawdir",
    "csv": "spectra.csv",
    "ior": "ior",
    "calrig": "calrig.json",
    "polframes": "polframes",
    "authors": "authors",
}


def _snapshot(root: Path) -> dict[str, tuple]:
    """Every entry under ``root``: relative path -> (kind, size, mtime_ns)."""
    entries = {}
    for path in [root, *root.rglob("*")]:
        stat = path.lstat()
        kind = "dir" if path.is_dir() else "file"
        entries[str(path.relative_to(root))] = (
            kind,
            stat.st_size if kind == "file" else 0,
            stat.st_mtime_ns if kind == "file" else 0,
        )
    return entries


class RowTimeout(Exception):
    """The command ran for ROW_TIMEOUT_S seconds instead of rejecting its input."""


def _on_alarm(signum, frame):
    raise RowTimeout(f"still running after {ROW_TIMEOUT_S} s: the input was not rejected up front")


def _run(argv: list[str]) -> int:
    previous = signal.signal(signal.SIGALRM, _on_alarm)
    signal.setitimer(signal.ITIMER_REAL, ROW_TIMEOUT_S)
    try:
        return main(argv)
    except SystemExit as exc:  # argparse errors
        return exc.code if isinstance(exc.code, int) else 1
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


TQDM = re.compile(r"^[^\n]*?\d+%\|[^|\n]*\| *[\d?]+/[\d?]+ \[[^\]]*\]")


def _error_lines(stderr: str) -> list[str]:
    """stderr without progress bars (tqdm's carriage-return frames) and argparse's usage block
    (``usage: ...`` and its indented continuation lines)."""
    segments = re.split(r"[\r\n]", stderr)
    lines = [TQDM.sub("", seg) for seg in segments]
    lines = [line for line in lines if line.strip()]
    if lines and lines[0].startswith("usage:"):
        lines = lines[1:]
        while lines and lines[0].startswith(" "):
            lines = lines[1:]
    return [line for line in lines if line.strip()]


def _params():
    for case in ROWS:
        marks = []
        if case.id in XFAIL:
            marks.append(pytest.mark.xfail(strict=True, reason=XFAIL[case.id]))
        yield pytest.param(case, id=case.id, marks=marks)


def test_table_is_large_and_unique():
    ids = [case.id for case in ROWS]
    assert len(ids) >= 200 and len(set(ids)) == len(ids)
    assert not set(XFAIL) - set(ids), "XFAIL names rows that no longer exist"
    commands = {case.argv[0] for case in ROWS}
    assert commands == {
        "demo",
        "stokes",
        "ingest",
        "calibrate",
        "calibrate-polarization",
        "skin-fit",
        "simulate",
        "reconstruct",
        "geometry",
        "evaluate",
        "biophysical",
        "render",
        "ior",
        "bench",
        "import-authors",
    }


@pytest.mark.parametrize("case", list(_params()))
def test_bad_input(case: Row, inputs, tmp_path, capsys):
    if case.readonly and os.geteuid() == 0:
        pytest.skip("root ignores directory permissions")
    ws = tmp_path / "ws"
    ws.mkdir()
    places = {"ws": str(ws), "data": str(TEST_DATA)}
    joined = " ".join(case.argv)
    for key, name in COPIED.items():
        if "{" + key + "}" in joined:
            source = inputs[key]
            (shutil.copytree if source.is_dir() else shutil.copy2)(source, ws / name)
            places[key] = str(ws / name)
    if case.setup is not None:
        case.setup(ws)
    argv = [arg.format(**places) for arg in case.argv]
    before = _snapshot(ws)
    capsys.readouterr()
    try:
        code = _run(argv)
    finally:
        for path in [ws, *ws.rglob("*")]:  # let tmp_path clean-up remove read-only folders
            if path.is_dir() and not path.is_symlink():
                path.chmod(0o700)
    _, err = capsys.readouterr()
    assert "Traceback" not in err, err
    assert code == 2, f"exit {code}; stderr: {err[-2000:]}"
    lines = _error_lines(err)
    assert len(lines) == 1, f"stderr must be one line; got {len(lines)}:\n{err[-2000:]}"
    assert lines[0].startswith(f"polarface {argv[0]}: error: "), lines[0]
    names = case.names.format(**places).split("|")
    assert any(name in lines[0] for name in names), f"error does not name {case.names!r}: {lines[0]}"
    after = _snapshot(ws)
    changed = sorted(k for k in set(before) & set(after) if before[k] != after[k])
    assert after == before, (
        f"workspace changed: added {sorted(set(after) - set(before))[:5]}, "
        f"removed {sorted(set(before) - set(after))[:5]}, changed {changed[:5]}"
    )
