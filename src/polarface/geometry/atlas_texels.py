"""The texel-level steps of :func:`polarface.geometry.atlas.cylindrical_atlas`, at the atlas resolution:
the triangles hidden behind a triangle farther from the axis (removal rule (3) of that module's
docstring) and the per-texel size statistics (``CylindricalAtlas.texel_size_mm``).

Inputs: UVs ``(N, 2)`` in [0, 1], v up; faces ``(F, 3)`` int; a square ``size x size`` texture with texel
centres as in :func:`polarface.geometry.uv_raster.texel_uv`; radii and texel sizes in mm.
"""

from __future__ import annotations

import numpy as np

from polarface.geometry.mesh import TriangleMesh

__all__ = ["hidden_faces", "texel_size_stats"]


def hidden_faces(
    uv: np.ndarray, faces: np.ndarray, radius: np.ndarray, size: int, batch: int = 1_000_000
) -> np.ndarray:
    """``(F,)`` bool: triangles that lose a texel (strictly inside two or more) to an outer triangle.

    Texel centres as in :func:`polarface.geometry.uv_raster.texel_uv`; the texel's radius is
    interpolated with the barycentrics; ties go to the higher face index.
    """
    x = uv[faces][..., 0] * size - 0.5
    y = (1.0 - uv[faces][..., 1]) * size - 0.5
    area2 = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    lo_x = np.clip(np.ceil(x.min(axis=1)), 0, size - 1).astype(np.int64)
    hi_x = np.clip(np.floor(x.max(axis=1)), 0, size - 1).astype(np.int64)
    lo_y = np.clip(np.ceil(y.min(axis=1)), 0, size - 1).astype(np.int64)
    hi_y = np.clip(np.floor(y.max(axis=1)), 0, size - 1).astype(np.int64)
    box_w = np.maximum(hi_x - lo_x + 1, 0)
    counts = np.where(np.abs(area2) > 1e-12, box_w * np.maximum(hi_y - lo_y + 1, 0), 0)
    texels, owners, radii = [], [], []
    face_order = np.nonzero(counts)[0]
    cumulative = np.cumsum(counts[face_order])
    start = 0
    while start < len(face_order):
        base = cumulative[start - 1] if start else 0
        stop = max(int(np.searchsorted(cumulative, base + batch, side="right")), start + 1)
        chunk = face_order[start:stop]
        owner = np.repeat(chunk, counts[chunk])
        local = np.arange(owner.size) - np.repeat(np.cumsum(counts[chunk]) - counts[chunk], counts[chunk])
        col = lo_x[owner] + local % box_w[owner]
        row = lo_y[owner] + local // box_w[owner]
        fx, fy = x[owner], y[owner]
        w_b = ((col - fx[:, 0]) * (fy[:, 2] - fy[:, 0]) - (fx[:, 2] - fx[:, 0]) * (row - fy[:, 0])) / area2[
            owner
        ]
        w_c = ((fx[:, 1] - fx[:, 0]) * (row - fy[:, 0]) - (col - fx[:, 0]) * (fy[:, 1] - fy[:, 0])) / area2[
            owner
        ]
        w_a = 1.0 - w_b - w_c
        inside = (w_a > 1e-9) & (w_b > 1e-9) & (w_c > 1e-9)
        rad = radius[faces[owner]]
        texels.append((row * size + col)[inside])
        owners.append(owner[inside])
        radii.append((w_a * rad[:, 0] + w_b * rad[:, 1] + w_c * rad[:, 2])[inside])
        start = stop
    hidden = np.zeros(len(faces), dtype=bool)
    if not texels:
        return hidden
    texel, owner, rad = (np.concatenate(a) for a in (texels, owners, radii))
    order = np.lexsort((owner, rad, texel))  # per texel: ascending radius, the winner last
    texel, owner = texel[order], owner[order]
    last = np.ones(texel.size, dtype=bool)
    last[:-1] = texel[1:] != texel[:-1]
    hidden[owner[~last]] = True
    return hidden


def texel_size_stats(mesh: TriangleMesh, in_face: np.ndarray, size: int) -> dict[str, float]:
    """UV-area-weighted statistics of per-triangle texel sizes over ``in_face`` triangles."""
    p = mesh.vertices[mesh.faces[in_face]]
    t = mesh.uv[mesh.faces[in_face]]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    du1, dv1 = t[:, 1, 0] - t[:, 0, 0], t[:, 1, 1] - t[:, 0, 1]
    du2, dv2 = t[:, 2, 0] - t[:, 0, 0], t[:, 2, 1] - t[:, 0, 1]
    det = du1 * dv2 - du2 * dv1
    ok = det > 0
    if not ok.any():
        nan = float("nan")
        return {k: nan for k in ("median", "p5", "p95", "median_u", "median_v", "median_anisotropy")}
    inv = 1.0 / det[ok, None]
    s_u = np.linalg.norm((e1[ok] * dv2[ok, None] - e2[ok] * dv1[ok, None]) * inv, axis=1) / size
    s_v = np.linalg.norm((e2[ok] * du1[ok, None] - e1[ok] * du2[ok, None]) * inv, axis=1) / size
    weight = 0.5 * det[ok]

    def quantile(values, q):
        order = np.argsort(values)
        cdf = np.cumsum(weight[order]) - 0.5 * weight[order]
        return float(np.interp(q * weight.sum(), cdf, values[order]))

    linear = np.sqrt(s_u * s_v)
    return {
        "median": quantile(linear, 0.5),
        "p5": quantile(linear, 0.05),
        "p95": quantile(linear, 0.95),
        "median_u": quantile(s_u, 0.5),
        "median_v": quantile(s_v, 0.5),
        "median_anisotropy": quantile(s_u / s_v, 0.5),
    }
