"""The backward pass through the height map shared by the static and the per-frame fused steps.

:class:`polarface.inverse.polarimetric.step.FusedObjective` (static loss) and
:class:`polarface.inverse.polarimetric.dynamic_step.FusedDynamicObjective` (per-frame loss) both carry
their height regularisers (``H^2`` and ``(Laplacian H)^2``, of the heights or of their change) and the
data gradient of the shading normals back to the heights ``H`` ``(h, w)`` (mm) with these numba
functions: :func:`laplacian`, :func:`normal_slopes` and :func:`height_gradient`. Normals from heights:
:class:`~polarface.geometry.heights.HeightNormals` (its stencils ``(3, h, w)`` and ``dn~/dH'`` factors
``(h, w, 3)``).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["height_gradient", "laplacian", "normal_slopes"]

_JIT = {"cache": True, "error_model": "numpy", "nogil": True}


@numba.njit(inline="always", **_JIT)
def laplacian(values, i, j):
    """4-neighbour Laplacian of ``values`` at interior texel ``(i, j)``."""
    return values[i - 1, j] + values[i + 1, j] + values[i, j - 1] + values[i, j + 1] - 4.0 * values[i, j]


@numba.njit(inline="always", **_JIT)
def normal_slopes(i, j, unit, data_grad, per_dh_dv, per_dh_du, slopes):
    """Texel ``(i, j)``'s data gradient of its unit normal carried back to its height slopes: unit normal
    -> ``n~`` -> ``(dH/du, dH/dv)``, into ``slopes[i, j]``; nothing where the base normal is kept
    (``unit[i, j, 3] == 0``)."""
    inv = unit[i, j, 3]
    if inv == 0.0:
        return
    t = i * slopes.shape[1] + j
    nx, ny, nz = unit[i, j, 0], unit[i, j, 1], unit[i, j, 2]
    gx, gy, gz = data_grad[t, 0], data_grad[t, 1], data_grad[t, 2]
    along = nx * gx + ny * gy + nz * gz
    gx, gy, gz = (gx - along * nx) * inv, (gy - along * ny) * inv, (gz - along * nz) * inv  # d/dn~
    slopes[i, j, 0] = gx * per_dh_du[i, j, 0] + gy * per_dh_du[i, j, 1] + gz * per_dh_du[i, j, 2]
    slopes[i, j, 1] = gx * per_dh_dv[i, j, 0] + gy * per_dh_dv[i, j, 1] + gz * per_dh_dv[i, j, 2]


@numba.njit(**_JIT)
def height_gradient(values, mask, w_ht, lap_valid, lap_g, unit, slopes, stencil_u, stencil_v):
    """``(h, w)`` gradient with respect to the heights of ``w_ht sum_mask values^2``, the Laplacian term
    (``lap_g = 2 w_hl Laplacian(values)`` at its valid texels, 0 elsewhere) and the data terms through the
    normals (``slopes``, :func:`normal_slopes`; the transposed stencils carry them to the heights).

    Each texel gathers what its neighbours and itself contribute, in the order in which a pass over the
    texels that scatters each texel's terms to its neighbours would add them (so the sums are the same
    to the last bit). The scattering pass chained read-modify-writes from one texel to the next: two
    thirds of a per-frame patch's backward pass (docs/performance.md).
    """
    rows, cols = values.shape
    g_h = np.empty((rows, cols))
    for i in range(rows):
        for j in range(cols):
            acc = 0.0
            if i > 0:
                if lap_valid[i - 1, j]:
                    acc += lap_g[i - 1, j]
                if unit[i - 1, j, 3] != 0.0:
                    acc += stencil_v[0, i - 1, j] * slopes[i - 1, j, 1]
            if j > 0:
                if lap_valid[i, j - 1]:
                    acc += lap_g[i, j - 1]
                if unit[i, j - 1, 3] != 0.0:
                    acc += stencil_u[0, i, j - 1] * slopes[i, j - 1, 0]
            if mask[i, j]:
                acc += 2.0 * w_ht * values[i, j]
            if lap_valid[i, j]:
                acc -= 4.0 * lap_g[i, j]
            if unit[i, j, 3] != 0.0:
                acc += stencil_u[1, i, j] * slopes[i, j, 0] + stencil_v[1, i, j] * slopes[i, j, 1]
            if j < cols - 1:
                if lap_valid[i, j + 1]:
                    acc += lap_g[i, j + 1]
                if unit[i, j + 1, 3] != 0.0:
                    acc += stencil_u[2, i, j + 1] * slopes[i, j + 1, 0]
            if i < rows - 1:
                if lap_valid[i + 1, j]:
                    acc += lap_g[i + 1, j]
                if unit[i + 1, j, 3] != 0.0:
                    acc += stencil_v[2, i + 1, j] * slopes[i + 1, j, 1]
            g_h[i, j] = acc
    return g_h
