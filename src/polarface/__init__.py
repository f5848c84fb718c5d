"""polarface: polarimetric BSSRDF acquisition of dynamic faces.

Implements Ha et al., "Polarimetric BSSRDF Acquisition of Dynamic Faces", ACM TOG 43(6), 2024.
Data flows one way: optics -> skin -> geometry -> capture -> results -> texture -> render ->
simulate -> inverse -> export -> report -> pipeline -> commands (the README's "Layout"). See
``docs/conventions.md`` for units, shapes and frames.
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
