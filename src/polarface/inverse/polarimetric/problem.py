"""One patch of the polarimetric fit: its samples and its loss.

:func:`build_patch_samples` gathers the visible samples (texel x view) of a texture region from an
:class:`~polarface.texture.unwrap.UnwrapStore` (as a
:class:`~polarface.inverse.polarimetric.model.SampleBatch` and, for the fused kernel, as
:class:`~polarface.inverse.polarimetric.fused.FusedSamples`); :class:`PatchProblem` evaluates the loss
of Eq. p-inverse-main-loss on such a patch (data terms plus the regularisers) from the raw,
reparameterised variables of :mod:`polarface.inverse.polarimetric.config`.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from polarface.geometry.heights import HeightNormals
from polarface.inverse.polarimetric.config import PolarimetricConfig, maps_from_raw
from polarface.inverse.polarimetric.fused import (
    FusedSamples,
    build_fused_samples,
    fused_data_loss,
    pack_parameters,
)
from polarface.inverse.polarimetric.losses import data_losses, laplacian_penalty, smoothness_penalty
from polarface.inverse.polarimetric.model import SampleBatch, precompute_samples, render_samples
from polarface.texture import TexelGeometry, UnwrapStore, ViewSpec

__all__ = ["PatchProblem", "build_patch_fused_samples", "build_patch_samples"]


def _patch_arrays(unwrap: UnwrapStore, rows: slice, cols: slice, view_indices: list[int]):
    """Geometry and the visible samples ``(v, r, c)`` of a texture region with their obs and lit masks."""
    geometry = unwrap.geometry(rows, cols)
    obs, valid, lit = unwrap.read(rows, cols, view_indices)
    valid = valid & geometry.mask[None]
    v_idx, r_idx, c_idx = np.nonzero(valid)
    return geometry, v_idx, r_idx, c_idx, obs[v_idx, r_idx, c_idx], lit[v_idx, r_idx, c_idx]


_VIEW_FIELDS = (
    "camera_center", "camera_up", "reference_up", "light_positions", "light_intensity", "channels"
)  # fmt: skip


def _view_table(views: list[ViewSpec], attribute: str) -> np.ndarray:
    return np.array([getattr(v, attribute) for v in views])


def _fused_samples(geometry: TexelGeometry, arrays: tuple, view_indices: list[int], views: list[ViewSpec],
                   dtype: torch.dtype) -> FusedSamples:
    """:class:`FusedSamples` of the visible samples of :func:`_patch_arrays` (``arrays``: its last five)."""
    v_idx, r_idx, c_idx, obs, lit = arrays
    chosen = [views[i] for i in view_indices]
    table = {name: _view_table(chosen, name) for name in _VIEW_FIELDS}
    return build_fused_samples(
        geometry.position.reshape(-1, 3),
        r_idx * geometry.mask.shape[1] + c_idx,
        v_idx,
        lit,
        obs,
        table["camera_center"],
        table["camera_up"],
        table["reference_up"],
        table["light_positions"],
        table["light_intensity"],
        table["channels"],
        dtype=np.float64 if dtype == torch.float64 else np.float32,
    )


def build_patch_fused_samples(
    unwrap: UnwrapStore,
    rows: slice,
    cols: slice,
    view_indices: list[int],
    views: list[ViewSpec],
    *,
    dtype: torch.dtype = torch.float32,
    timings: dict[str, float] | None = None,
) -> tuple[FusedSamples | None, TexelGeometry]:
    """The fused kernel's samples of a texture region for the given views (None when nothing is
    visible) and the region's geometry: :func:`build_patch_samples` ``(fused=True)`` without its
    per-sample-and-light :class:`~polarface.inverse.polarimetric.model.SampleBatch`, which the fused
    engine needs only for the lobe refinement (same samples, same order). ``timings``: where given, the
    seconds of reading the store (``read_s``) and of packing the samples (``samples_s``) are added to it."""
    tick = time.perf_counter()
    geometry, *arrays = _patch_arrays(unwrap, rows, cols, view_indices)
    read = time.perf_counter()
    packed = None
    if arrays[0].size:
        packed = _fused_samples(geometry, tuple(arrays), view_indices, views, dtype)
    if timings is not None:
        timings["read_s"] = timings.get("read_s", 0.0) + read - tick
        timings["samples_s"] = timings.get("samples_s", 0.0) + time.perf_counter() - read
    return packed, geometry


def build_patch_samples(
    unwrap: UnwrapStore,
    rows: slice,
    cols: slice,
    view_indices: list[int],
    views: list[ViewSpec],
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
    fused: bool = False,
) -> tuple[SampleBatch | None, TexelGeometry] | tuple[SampleBatch | None, TexelGeometry, FusedSamples | None]:
    """The samples of a texture region for the given views (None when nothing is visible).

    With ``fused=True`` also the compact :class:`~polarface.inverse.polarimetric.fused.FusedSamples`
    of the same samples (third element), for the fused CPU kernel.
    """
    geometry, v_idx, r_idx, c_idx, obs, lit = _patch_arrays(unwrap, rows, cols, view_indices)
    if v_idx.size == 0:
        return (None, geometry, None) if fused else (None, geometry)
    width = geometry.mask.shape[1]
    chosen = [views[i] for i in view_indices]
    table = {name: _view_table(chosen, name) for name in _VIEW_FIELDS}
    batch = precompute_samples(
        geometry.position[r_idx, c_idx],
        r_idx * width + c_idx,
        np.asarray(view_indices)[v_idx],
        table["camera_center"][v_idx],
        table["camera_up"][v_idx],
        table["reference_up"][v_idx],
        table["light_positions"][v_idx],
        table["light_intensity"][v_idx],
        table["channels"][v_idx],
        lit,
        obs,
        dtype=dtype,
        device=device,
    )
    if not fused:
        return batch, geometry
    packed = _fused_samples(geometry, (v_idx, r_idx, c_idx, obs, lit), view_indices, views, dtype)
    return batch, geometry, packed


class PatchProblem:
    """Everything needed to evaluate the loss of one patch (parameters as raw leaf tensors); ``batch`` may
    be None when ``fused`` samples are given (the fused engine evaluates the data loss on them)."""

    def __init__(
        self,
        batch: SampleBatch | None,
        geometry: TexelGeometry,
        config: PolarimetricConfig,
        scale: float,
        dtype: torch.dtype,
        device: torch.device,
        fused: FusedSamples | None = None,
    ) -> None:
        self.batch = batch
        self.fused = fused
        self.config = config
        self.scale = scale
        t = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
        self.frame = (
            t(geometry.tangent_u),
            t(geometry.tangent_v),
            t(geometry.normal),
            t(geometry.texel_size_u),
            t(geometry.texel_size_v),
        )
        self.mask = torch.as_tensor(geometry.mask, device=device)
        self.positions = geometry.position
        self.shape = geometry.mask.shape
        self.texel_count = int(self.mask.sum())
        self._height_normals: HeightNormals | None = None

    def height_normals(self) -> HeightNormals:
        """The patch's normals-from-H operator (H-independent terms, built once)."""
        if self._height_normals is None:
            self._height_normals = HeightNormals.build(*self.frame, self.mask)
        return self._height_normals

    def normals(self, height: torch.Tensor) -> torch.Tensor:
        return self.height_normals()(height).reshape(-1, 3)

    def loss(self, raw: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        maps = maps_from_raw(raw, self.config)
        h, w = self.shape
        flat = {k: v.reshape(h * w, -1) for k, v in maps.items()}
        normal = self.normals(maps["displacement_mm"][..., 0])
        wts = self.config.weights
        if self.fused is not None:
            params = pack_parameters(
                normal, flat["eta"], flat["alpha_s"], flat["alpha_ss"], flat["rho_s"], flat["rho_ss"],
                flat["rho_sss_bar"],
            )  # fmt: skip
            data = fused_data_loss(params, self.fused, wts, self.scale)
        else:
            b = self.batch
            texel = b.texel
            prediction = render_samples(
                b,
                normal[texel],
                flat["eta"][texel, 0],
                flat["alpha_s"][texel, 0],
                flat["alpha_ss"][texel, 0],
                flat["rho_s"][texel, 0],
                flat["rho_ss"][texel, 0],
                torch.gather(flat["rho_sss_bar"][texel], 1, b.channels),
            )
            terms = data_losses(prediction, b.observed, self.scale)
            data = (
                wts.sss * terms["sss"] + wts.s * terms["s"] + wts.phi * terms["phi"] + wts.psi * terms["psi"]
            )
        height = maps["displacement_mm"][..., 0]
        mask = self.mask
        reg = {
            "h_temporal": ((height * height) * mask).sum(),
            "h_laplacian": laplacian_penalty(height, mask),
            "eta_smooth": smoothness_penalty(maps["eta"][..., 0], mask),
            "alpha_s_smooth": smoothness_penalty(maps["alpha_s"][..., 0], mask),
            "alpha_ss_smooth": smoothness_penalty(maps["alpha_ss"][..., 0], mask),
        }
        total = (
            data
            + wts.h_temporal * reg["h_temporal"]
            + wts.h_laplacian * reg["h_laplacian"]
            + wts.eta * reg["eta_smooth"]
            + wts.alpha_s * reg["alpha_s_smooth"]
            + wts.alpha_ss * reg["alpha_ss_smooth"]
        ) / max(self.texel_count, 1)
        return total, {}
