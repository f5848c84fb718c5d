"""Normals from a displacement (height) map on the UV atlas: pure torch, differentiable.

Paper supplement, "Computing normals from heights" (after Riviere et al. 2020): the displaced surface
``P + H n`` has, per texel, the non-unit normal

    n~ = (s_u t_u + dH/du n) x (s_v t_v + dH/dv n),

with ``t_u``, ``t_v`` the unit tangent directions of the base mesh, ``s_u``, ``s_v`` their lengths per
texel step (mm per texel; :class:`~polarface.geometry.uv_raster.UVRaster` ``texel_size_u/v``), ``n`` the
unit base normal and ``dH/du``, ``dH/dv`` finite differences of ``H`` (mm) per texel step, hence in mm.
For an orthonormal frame this expands to ``-s_v dH/du t_u - s_u dH/dv t_v + s_u s_v n``.

Erratum: the supplement's matrix form ``[t_u t_v n] diag(s_u, s_v, s_u s_v) [-dH/du, -dH/dv, 1]^T``
swaps ``s_u`` and ``s_v`` relative to its own cross product (they agree only when ``s_u = s_v``). We
implement the cross product, which gives the exact normal of a tilted plane (tests).

Robustness choices (documented, tested):

* The tangents are projected onto the plane orthogonal to ``n`` before the cross product, so a flat
  ``H`` returns exactly the (interpolated) base normal even where ``t_u``, ``t_v`` are not orthogonal
  to it, and the result is oriented to the side of ``n`` (mirrored UV charts give the same result).
* Finite differences on the texture grid: central ``(H[j+1] - H[j-1]) / 2`` where both neighbours are
  valid texels, one-sided where only one is, zero where none is (borders of the atlas and of UV charts).
  Columns are +u; rows grow downwards while +v is up, so ``dH/dv = (H[i-1] - H[i+1]) / 2``.
* Texels outside ``mask``, or with a zero tangent length, return the base normal unchanged.
"""

from __future__ import annotations

import dataclasses

import torch

from polarface._validation import array_api, broadcast_named, check_last_dim, check_range

__all__ = ["HeightNormals", "height_gradients", "normals_from_height_gradients", "normals_from_heights"]


def _grid_mask(mask: torch.Tensor | None, height: torch.Tensor) -> torch.Tensor:
    if mask is None:
        return torch.ones(height.shape[-2:], dtype=torch.bool, device=height.device)
    mask = torch.as_tensor(mask, device=height.device)
    if mask.dtype != torch.bool:
        mask = mask != 0
    if mask.shape != height.shape[-2:]:
        raise ValueError(
            f"argument 'mask' must have shape {tuple(height.shape[-2:])}; got {tuple(mask.shape)}"
        )
    return mask


def _shifted(values: torch.Tensor, dim: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``values`` at the next and the previous texel along ``dim`` (-1 or -2), zero beyond the border."""
    size = values.shape[dim]
    pad = [0, 0, 0, 0]
    pad_index = 0 if dim == -1 else 2
    pad[pad_index] = pad[pad_index + 1] = 1
    padded = torch.nn.functional.pad(values, pad)
    return padded.narrow(dim, 2, size), padded.narrow(dim, 0, size)


def _neighbours_valid(valid: torch.Tensor, dim: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Valid texels whose next / previous neighbour along ``dim`` is valid too."""
    after, before = _shifted(valid.to(dtype), dim)
    return (after > 0) & valid, (before > 0) & valid


def _masked_difference(values: torch.Tensor, valid: torch.Tensor, dim: int) -> torch.Tensor:
    """Central/one-sided difference along ``dim`` (-1 or -2) of ``values[..., H, W]`` towards +index."""
    centre = values
    after, before = _shifted(values, dim)
    valid_after, valid_before = _neighbours_valid(valid, dim, values.dtype)
    zero = torch.zeros((), dtype=values.dtype, device=values.device)
    return torch.where(
        valid_after & valid_before,
        0.5 * (after - before),
        torch.where(valid_after, after - centre, torch.where(valid_before, centre - before, zero)),
    )


@array_api("height")
def height_gradients(
    height: torch.Tensor, mask: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Finite differences ``(dH/du, dH/dv)`` of a height map, mm per texel step.

    Args:
        height: ``(..., H, W)`` displacement in mm on the atlas (v up: row 0 is the top).
        mask: ``(H, W)`` bool valid texels (default all); invalid neighbours are not used.

    Returns:
        Two ``(..., H, W)`` tensors: the change of H per texel step towards +u (right) and +v (up).
    """
    if height.ndim < 2:
        raise ValueError(f"argument 'height' must have shape (..., H, W); got {tuple(height.shape)}")
    valid = _grid_mask(mask, height)
    dh_du = _masked_difference(height, valid, -1)
    dh_dv = -_masked_difference(height, valid, -2)  # rows grow downwards, +v is up
    return dh_du, dh_dv


@array_api("dh_du", "dh_dv", "tangent_u", "tangent_v", "normal", "texel_size_u", "texel_size_v")
def normals_from_height_gradients(
    dh_du: torch.Tensor,
    dh_dv: torch.Tensor,
    tangent_u: torch.Tensor,
    tangent_v: torch.Tensor,
    normal: torch.Tensor,
    texel_size_u: torch.Tensor,
    texel_size_v: torch.Tensor,
) -> torch.Tensor:
    """Unit normals of the displaced surface from height differences (pointwise, broadcasting).

    Args:
        dh_du, dh_dv: ``(...)`` height change per texel step along +u / +v, mm.
        tangent_u, tangent_v: ``(..., 3)`` unit directions of dP/du, dP/dv of the base mesh (world).
        normal: ``(..., 3)`` unit base normal (world). Unit length is assumed, not checked: the
            raster stores zero vectors at invalid texels, which come back unchanged.
        texel_size_u, texel_size_v: ``(...)`` texel sizes s_u, s_v >= 0, mm per texel step.

    Returns:
        ``(..., 3)`` unit normals in world coordinates (base normal where a texel size is 0).
    """
    for name, tensor in (("tangent_u", tangent_u), ("tangent_v", tangent_v), ("normal", normal)):
        check_last_dim(tensor, name, 3)
    check_range(texel_size_u, "texel_size_u", 0.0)
    check_range(texel_size_v, "texel_size_v", 0.0)
    dh_du, dh_dv, s_u, s_v = broadcast_named(
        ("dh_du", dh_du), ("dh_dv", dh_dv), ("texel_size_u", texel_size_u), ("texel_size_v", texel_size_v)
    )
    broadcast_named(
        ("dh_du", dh_du[..., None]), ("tangent_u", tangent_u), ("tangent_v", tangent_v), ("normal", normal)
    )
    t_u = tangent_u - (tangent_u * normal).sum(-1, keepdim=True) * normal
    t_v = tangent_v - (tangent_v * normal).sum(-1, keepdim=True) * normal
    axis_u = s_u[..., None] * t_u + dh_du[..., None] * normal
    axis_v = s_v[..., None] * t_v + dh_dv[..., None] * normal
    raw = torch.linalg.cross(*torch.broadcast_tensors(axis_u, axis_v), dim=-1)
    base = torch.linalg.cross(*torch.broadcast_tensors(t_u, t_v), dim=-1)
    orientation = torch.where((base * normal).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(raw.dtype)
    raw = raw * orientation
    squared = (raw * raw).sum(-1, keepdim=True)
    tiny = torch.finfo(raw.dtype).tiny
    length = torch.sqrt(squared.clamp(min=tiny))
    degenerate = (s_u <= 0) | (s_v <= 0) | (squared[..., 0] <= tiny)
    result = raw / length
    return torch.where(degenerate[..., None], normal.expand_as(result), result)


@array_api("height", "tangent_u", "tangent_v", "normal", "texel_size_u", "texel_size_v")
def normals_from_heights(
    height: torch.Tensor,
    tangent_u: torch.Tensor,
    tangent_v: torch.Tensor,
    normal: torch.Tensor,
    texel_size_u: torch.Tensor,
    texel_size_v: torch.Tensor,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Unit normals ``(..., H, W, 3)`` of the base surface displaced by ``height`` along its normal.

    Args:
        height: ``(..., H, W)`` displacement H in mm on the atlas.
        tangent_u, tangent_v, normal: ``(H, W, 3)`` unit base frame per texel (e.g. from
            :func:`~polarface.geometry.uv_raster.rasterize_uv`), world coordinates.
        texel_size_u, texel_size_v: ``(H, W)`` mm per texel step.
        mask: ``(H, W)`` bool valid texels; invalid texels return ``normal`` and are not used as
            finite-difference neighbours.
    """
    if height.ndim < 2:
        raise ValueError(f"argument 'height' must have shape (..., H, W); got {tuple(height.shape)}")
    grid = tuple(height.shape[-2:])
    for name, tensor, tail in (
        ("tangent_u", tangent_u, (*grid, 3)),
        ("tangent_v", tangent_v, (*grid, 3)),
        ("normal", normal, (*grid, 3)),
        ("texel_size_u", texel_size_u, grid),
        ("texel_size_v", texel_size_v, grid),
    ):
        if tuple(tensor.shape[-len(tail) :]) != tail:
            raise ValueError(f"argument '{name}' must end with shape {tail}; got {tuple(tensor.shape)}")
    valid = _grid_mask(mask, height)
    dh_du, dh_dv = height_gradients(height, valid)
    normals = normals_from_height_gradients(
        dh_du, dh_dv, tangent_u, tangent_v, normal, texel_size_u, texel_size_v
    )
    return torch.where(valid[..., None], normals, normal.expand_as(normals))


def _difference_weights(valid: torch.Tensor, dim: int, dtype: torch.dtype) -> torch.Tensor:
    """``(3, H, W)`` weights of (next, this, previous) texel along ``dim`` in :func:`_masked_difference`."""
    after, before = _neighbours_valid(valid, dim, dtype)
    both = after & before
    one = torch.ones((), dtype=dtype, device=valid.device)
    zero = torch.zeros((), dtype=dtype, device=valid.device)
    w_next = torch.where(both, 0.5 * one, torch.where(after, one, zero))
    w_prev = torch.where(both, -0.5 * one, torch.where(before & ~after, -one, zero))
    w_this = torch.where(both, zero, torch.where(after, -one, torch.where(before, one, zero)))
    return torch.stack([w_next, w_this, w_prev])


@dataclasses.dataclass(frozen=True, eq=False)
class HeightNormals:
    """:func:`normals_from_heights` of one atlas region with every H-independent term precomputed.

    For an optimiser that evaluates the normals of the same texels at every step: the finite
    differences become fixed 3-tap stencils and the cross product is linear in them,
    ``n~ = s_u s_v (t_u x t_v) + dH/dv s_u (t_u x n) + dH/du s_v (n x t_v)`` (projected tangents,
    orientation folded in), so a call costs a few fused tensor operations. Same result as
    :func:`normals_from_heights` (tests), for ``(H, W)`` maps only. Build with :meth:`build`.
    """

    weights_u: torch.Tensor
    weights_v: torch.Tensor
    constant: torch.Tensor
    per_dh_dv: torch.Tensor
    per_dh_du: torch.Tensor
    normal: torch.Tensor
    keep_base: torch.Tensor

    @classmethod
    def build(
        cls,
        tangent_u: torch.Tensor,
        tangent_v: torch.Tensor,
        normal: torch.Tensor,
        texel_size_u: torch.Tensor,
        texel_size_v: torch.Tensor,
        mask: torch.Tensor,
    ) -> HeightNormals:
        """Arguments as :func:`normals_from_heights` with ``(H, W, 3)`` frames, ``(H, W)`` sizes and mask."""
        for name, tensor in (("tangent_u", tangent_u), ("tangent_v", tangent_v), ("normal", normal)):
            if tensor.ndim != 3 or tensor.shape[-1] != 3:
                raise ValueError(f"argument '{name}' must have shape (H, W, 3); got {tuple(tensor.shape)}")
        shape = tuple(normal.shape[:2])
        for name, tensor in (("texel_size_u", texel_size_u), ("texel_size_v", texel_size_v), ("mask", mask)):
            if tuple(tensor.shape) != shape:
                raise ValueError(f"argument '{name}' must have shape {shape}; got {tuple(tensor.shape)}")
        check_range(texel_size_u, "texel_size_u", 0.0)
        check_range(texel_size_v, "texel_size_v", 0.0)
        valid = _grid_mask(mask, normal[..., 0])
        dtype = normal.dtype
        t_u = tangent_u - (tangent_u * normal).sum(-1, keepdim=True) * normal
        t_v = tangent_v - (tangent_v * normal).sum(-1, keepdim=True) * normal
        base = torch.linalg.cross(t_u, t_v, dim=-1)
        orientation = torch.where((base * normal).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(dtype)
        s_u, s_v = texel_size_u[..., None], texel_size_v[..., None]
        return cls(
            weights_u=_difference_weights(valid, -1, dtype),
            weights_v=-_difference_weights(valid, -2, dtype),  # rows grow downwards, +v is up
            constant=orientation * s_u * s_v * base,
            per_dh_dv=orientation * s_u * torch.linalg.cross(t_u, normal, dim=-1),
            per_dh_du=orientation * s_v * torch.linalg.cross(normal, t_v, dim=-1),
            normal=normal,
            keep_base=(~valid | (texel_size_u <= 0) | (texel_size_v <= 0))[..., None],
        )

    def __call__(self, height: torch.Tensor) -> torch.Tensor:
        """``(H, W, 3)`` unit normals of ``P + H n`` for a ``(H, W)`` height map (mm); differentiable."""
        right, left = _shifted(height, -1)
        down, up = _shifted(height, -2)  # rows grow downwards
        w_u, w_v = self.weights_u, self.weights_v
        dh_du = w_u[0] * right + w_u[1] * height + w_u[2] * left
        dh_dv = w_v[0] * down + w_v[1] * height + w_v[2] * up
        raw = self.constant + dh_dv[..., None] * self.per_dh_dv + dh_du[..., None] * self.per_dh_du
        squared = (raw * raw).sum(-1, keepdim=True)
        tiny = torch.finfo(raw.dtype).tiny
        result = raw / torch.sqrt(squared.clamp(min=tiny))
        return torch.where(self.keep_base | (squared <= tiny), self.normal, result)
