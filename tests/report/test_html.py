"""HTML report builder: structure, escaping, relative paths, atomic write."""

import pytest

from polarface.report import HtmlPage, ImageItem


def test_page_renders_sections_grids_tables(tmp_path):
    page = HtmlPage("Run <1>", subtitle="sub & title")
    section = page.section("Images", "Four analyzer images.")
    section.image_grid([ImageItem("png/I0.png", "I0 caption"), ("png/I90.png", "I90 <cross>")], columns=2)
    section.table({"eta": 1.44, "rho": (0.1, 0.2)})
    section.table([("a", 1), ("b", 2.5)], header=("name", "value"))
    page.section("Plots").plot("plots/loss.png", "loss curve")
    path = page.write(tmp_path / "index.html")
    text = path.read_text(encoding="utf-8")
    assert text.startswith("<!DOCTYPE html>")
    assert "Run &lt;1&gt;" in text and "sub &amp; title" in text
    assert 'src="png/I0.png"' in text and "I90 &lt;cross&gt;" in text
    assert "repeat(2, 1fr)" in text
    assert "<td>eta</td><td>1.44</td>" in text and "<td>0.1, 0.2</td>" in text
    assert "<th>name</th>" in text and 'src="plots/loss.png"' in text
    assert text.count("<section>") == 2
    assert not list(tmp_path.glob(".tmp-*"))


@pytest.mark.parametrize("bad", ["/abs/path.png", "C:/x.png", "javascript:alert(1)", ""])
def test_rejects_non_relative_paths(bad):
    section = HtmlPage("x").section("s")
    with pytest.raises(ValueError, match="path"):
        section.image_grid([ImageItem(bad, "c")])
    with pytest.raises(ValueError, match="path"):
        section.plot(bad)


def test_columns_validated():
    with pytest.raises(ValueError, match="columns"):
        HtmlPage("x").section("s").image_grid([], columns=0)
