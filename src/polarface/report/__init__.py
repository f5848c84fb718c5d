"""Human-readable reports: a small HTML page builder, the RESULT folder's reconstruction report and the
offline 3D viewer page of an export."""

from polarface.report.biophysical import biophysical_section
from polarface.report.dynamic import dynamic_section
from polarface.report.html import HtmlPage, ImageItem, Section
from polarface.report.reconstruction import write_report
from polarface.report.viewer import write_viewer

__all__ = ["HtmlPage", "ImageItem", "Section", "biophysical_section", "dynamic_section", "write_report",
           "write_viewer"]
