"""A small generic HTML page builder for run reports: sections, image grids, tables, plots.

Pages are self-contained HTML5 with inline CSS, laid out for a 1400 px wide window; images and plots
are referenced by **relative** paths (so a run folder can be moved or zipped as a whole), and every
grid thumbnail links to its full-size image. All text is HTML-escaped. Writing is atomic.

Example::

    page = HtmlPage("polarface demo", subtitle="rendered in 1.2 s")
    section = page.section("Analyzer images", "Intensities behind the four polarizer angles.")
    section.image_grid([ImageItem("png/I0.png", "I0: co-polarized"), ...], columns=4)
    section.table({"eta": 1.44, "alpha_s": 0.45})
    page.write(out_dir / "index.html")
"""

from __future__ import annotations

import html
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import PurePosixPath
from typing import Any

from polarface.io.atomic import atomic_path
from polarface.io.storage import PathOrUrl, StoragePath, storage_path

__all__ = ["HtmlPage", "ImageItem", "Section"]

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1400px; padding: 0 1em;
       color: #222; }
h1 { margin-bottom: 0.2em; } .subtitle { color: #666; margin-top: 0; }
section { margin: 2em 0; } h2 { border-bottom: 1px solid #ddd; padding-bottom: 0.2em; }
.grid { display: grid; gap: 1em; }
figure { margin: 0; } figure img { width: 100%; image-rendering: pixelated; border: 1px solid #ccc; }
figure a { display: block; }
figcaption { font-size: 0.9em; color: #444; margin-top: 0.3em; }
table { border-collapse: collapse; margin: 0.5em 0; }
td, th { border: 1px solid #ddd; padding: 0.3em 0.8em; text-align: left; }
th { background: #f4f4f4; } .plot img { max-width: 100%; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
.pass { color: #176f2c; font-weight: 600; } .fail { color: #b3261e; font-weight: 600; }
"""


def _check_relative(path: str) -> str:
    text = str(path).replace(os.sep, "/")
    pure = PurePosixPath(text)
    has_scheme = bool(pure.parts) and ":" in pure.parts[0]
    if not text or pure.is_absolute() or has_scheme:
        raise ValueError(f"argument 'path' must be relative to the page; got {path!r}")
    return text


def _format(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, list | tuple):
        return ", ".join(_format(v) for v in value)
    return str(value)


@dataclass(frozen=True)
class ImageItem:
    """One image in a grid: ``path`` relative to the page, a caption, optional alt text."""

    path: str
    caption: str = ""
    alt: str = ""


@dataclass
class Section:
    """A titled section holding an ordered list of blocks (paragraphs, grids, tables, plots)."""

    title: str
    blocks: list[str] = field(default_factory=list)

    def text(self, paragraph: str) -> Section:
        """Append a paragraph of plain text (escaped)."""
        self.blocks.append(f"<p>{html.escape(paragraph)}</p>")
        return self

    def link(self, path: str, label: str) -> Section:
        """Append a paragraph holding a link to ``path`` (relative to the page)."""
        href = html.escape(_check_relative(path), quote=True)
        self.blocks.append(f'<p><a href="{href}">{html.escape(label)}</a></p>')
        return self

    def image_grid(self, items: Iterable[ImageItem | tuple[str, str]], columns: int = 4) -> Section:
        """Append a grid of images with captions (``columns`` per row); each links to its full size."""
        if columns < 1:
            raise ValueError(f"argument 'columns' must be >= 1; got {columns}")
        figures = []
        for item in items:
            if not isinstance(item, ImageItem):
                item = ImageItem(*item)
            src = html.escape(_check_relative(item.path), quote=True)
            alt = html.escape(item.alt or item.caption, quote=True)
            figures.append(f'<figure><a href="{src}" title="open full size"><img src="{src}" alt="{alt}" '
                           f'loading="lazy"></a><figcaption>{html.escape(item.caption)}</figcaption></figure>')
        style = f"grid-template-columns: repeat({columns}, 1fr);"
        self.blocks.append(f'<div class="grid" style="{style}">' + "".join(figures) + "</div>")
        return self

    def table(self, rows: Mapping[str, Any] | Sequence[Sequence[Any]], header: Sequence[str] | None = None,
              column_classes: Sequence[str] = ()) -> Section:
        """Append a table: a key/value mapping, or a list of rows with an optional header.

        ``column_classes`` gives each column's CSS class (``num``: right-aligned numbers; ``""``: none).
        """
        body = list(rows.items()) if isinstance(rows, Mapping) else [tuple(r) for r in rows]
        if header is None and isinstance(rows, Mapping):
            header = ("quantity", "value")
        attrs = [f' class="{html.escape(c, quote=True)}"' if c else "" for c in column_classes]
        parts = ["<table>"]
        if header:
            parts.append("<tr>" + "".join(f"<th>{html.escape(str(h))}</th>" for h in header) + "</tr>")
        for row in body:
            cells = (
                f"<td{attrs[i] if i < len(attrs) else ''}>{html.escape(_format(c))}</td>"
                for i, c in enumerate(row)
            )
            parts.append("<tr>" + "".join(cells) + "</tr>")
        parts.append("</table>")
        self.blocks.append("".join(parts))
        return self

    def plot(self, path: str, caption: str = "") -> Section:
        """Append an embedded plot image (e.g. a matplotlib PNG/SVG) by relative path."""
        src = html.escape(_check_relative(path), quote=True)
        self.blocks.append(f'<figure class="plot"><img src="{src}" alt="{html.escape(caption, quote=True)}">'
                           f"<figcaption>{html.escape(caption)}</figcaption></figure>")
        return self

    def render(self) -> str:
        return f"<section><h2>{html.escape(self.title)}</h2>" + "\n".join(self.blocks) + "</section>"


class HtmlPage:
    """An HTML report page made of :class:`Section` blocks."""

    def __init__(self, title: str, subtitle: str | None = None) -> None:
        self.title = title
        self.subtitle = subtitle
        self.sections: list[Section] = []

    def section(self, title: str, text: str | None = None) -> Section:
        """Add and return a new section (optionally starting with a paragraph)."""
        section = Section(title)
        if text:
            section.text(text)
        self.sections.append(section)
        return section

    def render(self) -> str:
        """The complete HTML document as a string."""
        head = (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
                f"<title>{html.escape(self.title)}</title><style>{_STYLE}</style></head><body>")
        top = f"<h1>{html.escape(self.title)}</h1>"
        if self.subtitle:
            top += f'<p class="subtitle">{html.escape(self.subtitle)}</p>'
        return head + top + "\n".join(s.render() for s in self.sections) + "</body></html>\n"

    def write(self, path: PathOrUrl) -> StoragePath:
        """Write the page atomically (UTF-8; a local path or a URL) and return its path."""
        with atomic_path(path) as tmp:
            tmp.write_text(self.render(), encoding="utf-8")
        return storage_path(path)
