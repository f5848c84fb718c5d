"""The dynamic section of the report (``polarface.report.dynamic``) on small fake dynamic RESULTs: the
animations (frame count, loop, one colour scale), the changing region, the frame table with failed
frames, a single frame and no frame done."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from dynamic_fixtures import RES, write_dynamic_result
from polarface.report import HtmlPage, dynamic_section
from polarface.report.dynamic import FRAMES_PER_SECOND, changing_region, write_animation
from polarface.results import ResultFolder


def _gif_frames(path: Path) -> list[np.ndarray]:
    with Image.open(path) as image:
        assert image.info.get("loop") == 0  # loops forever
        assert image.info.get("duration") == pytest.approx(1000 / FRAMES_PER_SECOND, abs=1)
        out = []
        for index in range(image.n_frames):
            image.seek(index)
            out.append(np.asarray(image.convert("RGB")))
        return out


def test_section_with_a_failed_frame(tmp_path):
    root = write_dynamic_result(tmp_path / "result", frames=5, failed={2: "tracking lost"})
    page = HtmlPage("test")
    metrics = {"frames": 4, "tracking_mm": {"median_per_frame": [0.1], "max": None}}
    section = dynamic_section(page, root, metrics)
    html = page.render()
    for name in ("dynamic_rho_sss_bar.gif", "dynamic_c_h_out.gif", "dynamic_subsurface_srgb.gif",
                 "dynamic_chromophores.png"):
        assert f"previews/{name}" in html and (root / "previews" / name).is_file()
    rho = _gif_frames(root / "previews" / "dynamic_rho_sss_bar.gif")
    assert len(rho) == 4  # the failed frame is not shown
    # one scale for all frames: rho 0.2 (frame 0) and 0.4 (frame 4, the scale) -> sRGB(0.5) and 1
    centre = (RES // 2, RES // 2)
    assert rho[0][centre] == pytest.approx([188, 188, 188], abs=3)
    assert rho[-1][centre] == pytest.approx([255, 255, 255], abs=3)
    assert "failed: tracking lost" in html and "tracking_mm.median_per_frame" in html
    assert "n/a" in html  # a None metric
    assert len(section.blocks) >= 4


def test_changing_region_is_the_largest_strongly_changing_blob(tmp_path):
    root = write_dynamic_result(tmp_path / "result", frames=5)
    folder = ResultFolder(root)
    stack = np.stack([folder.frame(t).read_scalar_map("c_h_out") for t in range(5)])
    mask = folder.frame(0).read_mask()
    region = changing_region(stack, mask)
    # 95th percentile of 900 texels: ~45 texels, all around the strong blob's centre (10, 20)
    rows, cols = np.nonzero(region)
    assert 30 <= region.sum() <= 50
    assert np.hypot(rows - 10, cols - 20).max() < 5.0
    # no change at all: no region
    assert not changing_region(stack[:1], mask).any()


def test_single_frame_and_no_frame(tmp_path):
    single = write_dynamic_result(tmp_path / "single", frames=1)
    page = HtmlPage("test")
    dynamic_section(page, single)
    assert len(_gif_frames(single / "previews" / "dynamic_c_h_out.gif")) == 1
    assert (single / "previews" / "dynamic_chromophores.png").is_file()
    none_done = write_dynamic_result(tmp_path / "none", frames=2, failed={0: "a", 1: "b"})
    page = HtmlPage("test")
    dynamic_section(page, none_done)
    html = page.render()
    assert "No frame has maps yet." in html and "failed: b" in html
    assert not (none_done / "previews").exists()


def test_write_animation_checks_its_input(tmp_path):
    with pytest.raises(ValueError, match="images"):
        write_animation(tmp_path / "a.gif", np.zeros((0, 4, 4, 3)))
    with pytest.raises(ValueError, match="labels"):
        write_animation(tmp_path / "a.gif", np.zeros((2, 4, 4, 3)), ["one"])
    big = np.random.default_rng(0).random((2, 1000, 700, 3))
    with Image.open(write_animation(tmp_path / "big.gif", big)) as image:
        assert image.size == (350, 500)  # subsampled by 2 to at most 512 px


def test_animations_do_not_depend_on_what_is_held(tmp_path, monkeypatch):
    """The scales found by reading the frames again (nothing held) give the same animations as
    the scales of the values held in memory."""
    from polarface.report import streamed

    held = write_dynamic_result(tmp_path / "held", frames=4)
    dynamic_section(HtmlPage("test"), held)
    monkeypatch.setattr(streamed, "HELD_VALUES", 7)
    again = write_dynamic_result(tmp_path / "again", frames=4)
    dynamic_section(HtmlPage("test"), again)
    for name in ("dynamic_rho_sss_bar.gif", "dynamic_c_h_out.gif", "dynamic_subsurface_srgb.gif"):
        assert (held / "previews" / name).read_bytes() == (again / "previews" / name).read_bytes()


def test_tracking_confidence_is_animated_and_the_flagged_share_listed(tmp_path):
    """Frames whose dynamic stage wrote a tracking confidence map and the flagged share: the section
    animates the map on one 0..1 scale and lists the share per frame."""
    root = write_dynamic_result(tmp_path / "result", frames=3)
    folder = ResultFolder(root)
    for t in range(3):
        confidence = np.ones((RES, RES), np.float32)
        confidence[: 4 * (t + 1)] = 0.0  # a growing untracked band
        folder.frame(t).write_scalar_map("tracking_confidence", confidence)
        folder.frame(t).record_stage("polarimetric", {"tracking": {"flagged_fraction": 0.0125 * (t + 1)}})
    page = HtmlPage("test")
    dynamic_section(page, root)
    html = page.render()
    assert "previews/dynamic_tracking_confidence.gif" in html
    frames = _gif_frames(root / "previews" / "dynamic_tracking_confidence.gif")
    assert len(frames) == 3
    # viridis(0) is dark purple, viridis(1) yellow: the band grows frame by frame
    dark = [int((frame[:, RES // 2].sum(-1) < 200).sum()) for frame in frames]
    assert dark[0] < dark[1] < dark[2]
    for share in ("1.2", "2.5", "3.8"):
        assert f">{share}<" in html
    assert "untracked texels (%)" in html
