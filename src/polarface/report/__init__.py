"""Human-readable reports: a small HTML page builder and the RESULT folder's reconstruction report."""

from polarface.report.biophysical import biophysical_section
from polarface.report.dynamic import dynamic_section
from polarface.report.html import HtmlPage, ImageItem, Section
from polarface.report.reconstruction import write_report

__all__ = ["HtmlPage", "ImageItem", "Section", "biophysical_section", "dynamic_section", "write_report"]
