"""End-to-end tests of ``polarface skin-fit`` on the NIST skin reflectance set and on bad input."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest

from polarface.cli import main
from polarface.skin.layers import PARAMETER_RANGES

NIST = "skin/nist_skin_reflectance_odd_subjects.csv"


@pytest.mark.slow
def test_nist_fifty_subjects(test_data, tmp_path, capsys):
    out = tmp_path / "fit"
    assert main(["skin-fit", str(test_data / NIST), "--out", str(out)]) == 0
    payload = json.loads((out / "fit.json").read_text())
    assert (out / "fit.png").stat().st_size > 10_000
    assert (out / "fitted_spectra.csv").is_file()
    samples = payload["samples"]
    assert len(samples) == 50 and "subject_001" in samples
    rmse = np.array([s["rmse"] for s in samples.values()])
    # Target: median RMSE <= 0.015 over 420-700 nm.
    assert np.median(rmse) <= 0.015
    assert rmse.max() <= 0.04
    assert payload["summary"]["rmse_median"] == pytest.approx(np.median(rmse))
    for sample in samples.values():
        for name, (low, high) in PARAMETER_RANGES.items():
            assert low <= sample[name] <= high
        assert 0.0 <= sample["surface_offset"] <= 0.15
    # Fitted parameters are plausible: melanin varies across subjects, far below its bound.
    c_m = np.array([s["c_m"] for s in samples.values()])
    assert c_m.max() < 0.2 and c_m.std() > 0.003
    assert "RMSE median" in capsys.readouterr().out


def _write(path, header, rows):
    path.write_text(",".join(header) + "\n" + "\n".join(",".join(str(v) for v in r) for r in rows) + "\n")
    return path


def _good_rows(scale=1.0):
    wl = np.arange(400.0, 721.0, 10.0)
    return [[w, 0.3 * scale, 0.4 * scale] for w in wl]


def _run(tmp_path, csv_path, *extra):
    return main(
        [
            "skin-fit",
            str(csv_path),
            "--out",
            str(tmp_path / "o"),
            "--iterations",
            "3",
            "--starts",
            "1",
            *extra,
        ]
    )


@pytest.mark.parametrize(
    ("header", "rows", "message"),
    [
        (["wl", "a", "b"], _good_rows(), "wavelength_nm"),
        (["wavelength_nm"], [[r[0]] for r in _good_rows()], "no sample columns"),
        (["wavelength_nm", "a", "b"], _good_rows(100.0), "percent"),
        (["wavelength_nm", "a", "b"], [r if r[0] != 500 else [500, "", 0.3] for r in _good_rows()], "NaN"),
        (["wavelength_nm", "a", "b"], [[w + 600, a, b] for w, a, b in _good_rows()], "does not include"),
        (["wavelength_nm", "a", "b"], [[w, -0.1, b] for w, a, b in _good_rows()], r"\[0, 1\]"),
        (["wavelength_nm", "a", "a"], _good_rows(), "duplicate"),
    ],
)
def test_bad_input(tmp_path, capsys, header, rows, message):
    path = _write(tmp_path / "bad.csv", header, rows)
    assert _run(tmp_path, path) == 2
    import re

    assert re.search(message, capsys.readouterr().err)


def test_band_outside_model_range(tmp_path, capsys):
    path = _write(tmp_path / "ok.csv", ["wavelength_nm", "a", "b"], _good_rows())
    assert _run(tmp_path, path, "--max-nm", "1100") == 2
    assert "model range" in capsys.readouterr().err


def test_missing_file(tmp_path, capsys):
    assert _run(tmp_path, tmp_path / "nope.csv") == 2
    assert "does not exist" in capsys.readouterr().err


def test_small_file_runs(tmp_path, test_data):
    # A subset of the real data with three subjects runs quickly and writes every artifact.
    src = np.genfromtxt(test_data / NIST, delimiter=",", names=True)
    names = src.dtype.names[:4]
    path = tmp_path / "three.csv"
    _write(path, list(names), [[row[n] for n in names] for row in src])
    out = tmp_path / "o"
    assert main(["skin-fit", str(path), "--out", str(out), "--iterations", "30", "--starts", "2"]) == 0
    payload = json.loads((out / "fit.json").read_text())
    assert set(payload["samples"]) == set(names[1:])
    assert payload["summary"]["rmse_max"] < 0.03
    shutil.rmtree(out)


@pytest.mark.parametrize(
    ("value", "message"),
    [("nan", "NaN"), ("inf", "infinite"), ("1.2", r"\[0, 1\]"), ("-0.01", r"\[0, 1\]")],
)
def test_reflectance_outside_the_fit_band_is_checked_too(tmp_path, capsys, value, message):
    rows = [[300.0, 0.3, 0.4], *_good_rows()]
    rows[0][2] = value
    path = _write(tmp_path / "bad.csv", ["wavelength_nm", "a", "b"], rows)
    assert _run(tmp_path, path) == 2
    err = capsys.readouterr().err
    assert re.search(message, err) and "bad.csv" in err and "line 2 (300 nm), column 'b'" in err
    assert not (tmp_path / "o").exists()


def test_non_utf8_csv_names_the_file(tmp_path, capsys):
    path = tmp_path / "bad.csv"
    path.write_bytes(b"wavelength_nm,a\n\xff\xfe\x00garbage\n")
    assert _run(tmp_path, path) == 2
    assert "bad.csv" in capsys.readouterr().err
