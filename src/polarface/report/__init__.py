"""Human-readable reports: a small, dependency-free HTML page builder (:mod:`polarface.report.html`)."""

from polarface.report.html import HtmlPage, ImageItem, Section

__all__ = ["HtmlPage", "ImageItem", "Section"]
