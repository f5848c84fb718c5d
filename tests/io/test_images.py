"""EXR/PNG round trips and atomic writes."""

import numpy as np
import pytest

from polarface.io import (
    agg_figure,
    atomic_path,
    colormap_png,
    read_exr,
    read_png,
    write_exr,
    write_figure_png,
    write_png,
)


def test_exr_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    a = rng.random((5, 7)).astype(np.float32)
    write_exr(tmp_path / "a.exr", {"I0": a, "I90": 2 * a})
    back = read_exr(tmp_path / "a.exr")
    np.testing.assert_array_equal(back["I0"], a)
    np.testing.assert_array_equal(back["I90"], 2 * a)
    rgb = rng.random((4, 3, 3)).astype(np.float32)
    write_exr(tmp_path / "rgb.exr", rgb)
    back = read_exr(tmp_path / "rgb.exr")
    np.testing.assert_array_equal(np.stack([back[c] for c in "RGB"], -1), rgb)


def test_png_round_trip_16bit(tmp_path):
    raw = (np.arange(64, dtype=np.uint16).reshape(8, 8) * 60).astype(np.uint16)
    write_png(tmp_path / "raw.png", raw, bit_depth=16)
    back = read_png(tmp_path / "raw.png")
    assert back.dtype == np.uint16
    np.testing.assert_array_equal(back, raw)


def test_truncated_png_named(tmp_path):
    write_png(tmp_path / "x.png", np.zeros((16, 16), np.uint8))
    data = (tmp_path / "x.png").read_bytes()
    (tmp_path / "bad.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"bad\.png"):
        read_png(tmp_path / "bad.png")


def test_atomic_path_leaves_nothing_on_error(tmp_path):
    with pytest.raises(RuntimeError), atomic_path(tmp_path / "out.json") as tmp:
        tmp.write_text("partial")
        raise RuntimeError("crash")
    assert list(tmp_path.iterdir()) == []


def test_colormap_png(tmp_path):
    img = np.linspace(0, 1, 100).reshape(10, 10)
    colormap_png(tmp_path / "c.png", img, mask=img > 0.2)
    out = read_png(tmp_path / "c.png")
    assert out.shape == (10, 10, 3) and (out[0, 0] == 0).all()
    colormap_png(tmp_path / "d.png", img, title="t", colorbar=True)
    assert read_png(tmp_path / "d.png").ndim == 3


def test_write_figure_png_matches_savefig(tmp_path):
    """One Agg draw encoded by OpenCV: the pixels matplotlib's own savefig writes, without alpha; the
    figure is closed; a non-figure is refused before anything is written."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    def figure():
        fig, ax = plt.subplots(figsize=(3.2, 2.4), dpi=50, layout="constrained")
        handle = ax.imshow(np.linspace(0, 1, 64).reshape(8, 8), cmap="viridis")
        ax.set_title("map")
        fig.colorbar(handle, ax=ax, label="unit")
        return fig

    reference = figure()
    reference.savefig(tmp_path / "savefig.png", format="png", dpi=100)
    plt.close(reference)
    drawn = figure()
    write_figure_png(tmp_path / "fast.png", drawn, dpi=100)
    assert not plt.fignum_exists(drawn.number)
    fast, saved = read_png(tmp_path / "fast.png"), read_png(tmp_path / "savefig.png")
    assert fast.shape == (240, 320, 3) and fast.dtype == np.uint8
    np.testing.assert_array_equal(fast, saved[..., :3])
    with pytest.raises(TypeError, match="argument 'figure'"):
        write_figure_png(tmp_path / "bad.png", np.zeros((4, 4)))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fast.png", "savefig.png"]


def test_agg_figure_draws_the_pyplot_figure_outside_pyplot(tmp_path):
    """``agg_figure`` makes what ``plt.subplots`` makes (the same pixels once written, layout engine and
    subplot options included) without registering it with pyplot; a bad grid is refused by matplotlib."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    def draw(fig, axes):
        for k, ax in enumerate(axes.flat):
            handle = ax.imshow(np.linspace(0, 1, 64).reshape(8, 8) ** (k + 1), cmap="magma")
            ax.set_title(f"map {k}")
            fig.colorbar(handle, ax=ax, label="unit")
        return fig

    options = {"figsize": (4.0, 2.2), "dpi": 60, "layout": "constrained", "squeeze": False}
    before = plt.get_fignums()
    figure, axes = agg_figure(1, 2, **options)
    assert axes.shape == (1, 2) and plt.get_fignums() == before
    write_figure_png(tmp_path / "agg.png", draw(figure, axes))
    write_figure_png(tmp_path / "pyplot.png", draw(*plt.subplots(1, 2, **options)))
    assert plt.get_fignums() == before  # the pyplot figure is closed
    agg, pyplot = read_png(tmp_path / "agg.png"), read_png(tmp_path / "pyplot.png")
    assert agg.shape == (132, 240, 3)
    np.testing.assert_array_equal(agg, pyplot)
    single_figure, single_axes = agg_figure(figsize=(2.0, 2.0))
    assert single_figure.dpi == matplotlib.rcParams["figure.dpi"] and single_axes.figure is single_figure
    with pytest.raises(ValueError):
        agg_figure(0, 1, figsize=(2.0, 2.0))


def test_map_previews_leave_pyplot_alone(tmp_path):
    """Writing a map preview with a scale bar does not import pyplot (whose import picks a backend and
    whose figures must be closed): the package's figures are made by ``agg_figure``."""
    import subprocess
    import sys

    script = (
        "import sys, numpy as np\n"
        "from polarface.io import colormap_png\n"
        f"colormap_png({str(tmp_path / 'p.png')!r}, np.eye(8), title='t', colorbar=True)\n"
        "print('matplotlib.pyplot' in sys.modules)\n"
    )
    shown = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert shown.stdout.strip() == "False" and (tmp_path / "p.png").is_file()


def test_a_corrupt_png_gives_one_error_and_no_opencv_line(tmp_path):
    """OpenCV's PNG decoder printed its own ``[ERROR:0@...] global grfmt_png.cpp ... readHeader`` line on
    stderr (file descriptor 2, besides the error the CLI prints: two lines, issue 47) for a file cut
    after its signature. In a fresh process, as a user's command runs."""
    import subprocess
    import sys

    import cv2

    from polarface.io import read_png

    bad = tmp_path / "cut.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n")
    code = ("import sys\nfrom polarface.io import read_png\ntry:\n    read_png(sys.argv[1])\n"
            "except ValueError as exc:\n    print(exc, file=sys.stderr)\n")
    run = subprocess.run([sys.executable, "-c", code, str(bad)], capture_output=True, text=True, timeout=120)
    expected = f"cannot read image '{bad}' (truncated, corrupt or not an image)"
    assert run.stderr.strip().splitlines() == [expected]
    level = cv2.utils.logging.getLogLevel()
    with pytest.raises(ValueError, match=r"cut\.png"):
        read_png(bad)
    assert cv2.utils.logging.getLogLevel() == level  # restored
