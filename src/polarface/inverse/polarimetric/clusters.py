"""Clusters of the diffuse albedo and the values a map takes per cluster: the ``hwang2022`` model variant
(:data:`polarface.inverse.polarimetric.MODEL_VARIANTS`; ``PolarimetricConfig.clustered``).

Hwang et al. 2022 (Sparse Ellipsometry, ACM TOG 41(4)) share the specular parameters over clusters of
the surface and fit them by alternating optimisation; the paper compares it (Sec. 6) and blames its
specular errors on that "alternative and cluster-based optimization scheme". Here the clusters are
k-means clusters of the six-channel diffuse albedo ``rho_sss_bar`` of a free fit, and a map's value in a
cluster is its median over the cluster's texels in the result mask.
"""

from __future__ import annotations

import numpy as np
from scipy.cluster.vq import kmeans2, vq

__all__ = ["albedo_clusters", "cluster_values"]

#: Largest number of texels k-means sees (a random subset beyond it; every texel is then labelled).
KMEANS_SAMPLE = 200_000


def albedo_clusters(rho_sss_bar: np.ndarray, mask: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """``(Ht, Wt)`` int32 cluster of every texel: k-means (k-means++ starts, ``seed``) of the ``(Ht, Wt,
    C)`` diffuse albedo over the ``(Ht, Wt)`` bool ``mask``, each texel labelled with its nearest centre.

    Raises:
        ValueError: shapes that do not match, ``count`` < 1, or fewer masked texels than ``count``.
    """
    albedo = np.asarray(rho_sss_bar, dtype=np.float64)
    mask = np.asarray(mask, dtype=bool)
    if albedo.ndim != 3 or albedo.shape[:2] != mask.shape:
        raise ValueError(f"argument 'rho_sss_bar' must be (Ht, Wt, C) over 'mask' {mask.shape}; "
                         f"got {albedo.shape}")
    if int(count) < 1 or int(mask.sum()) < int(count):
        raise ValueError(f"argument 'count' must be in [1, masked texels {int(mask.sum())}]; got {count}")
    rng = np.random.default_rng(seed)
    inside = albedo[mask]
    if len(inside) > KMEANS_SAMPLE:
        inside = inside[rng.choice(len(inside), KMEANS_SAMPLE, replace=False)]
    centres, _ = kmeans2(inside, int(count), minit="++", seed=rng)
    labels, _ = vq(albedo.reshape(-1, albedo.shape[-1]), centres)
    return labels.reshape(mask.shape).astype(np.int32)


def cluster_values(values: np.ndarray, labels: np.ndarray, mask: np.ndarray, count: int) -> np.ndarray:
    """``(count,)`` float64 median of the ``(Ht, Wt)`` map ``values`` over each cluster's texels in
    ``mask`` (a cluster without any: the median over the whole mask).

    Raises:
        ValueError: shapes that do not match, or an empty ``mask``.
    """
    values = np.asarray(values, dtype=np.float64)
    if values.shape != labels.shape or labels.shape != mask.shape:
        raise ValueError(f"arguments 'values' {values.shape}, 'labels' {labels.shape} and 'mask' "
                         f"{mask.shape} must have one shape")
    if not mask.any():
        raise ValueError("argument 'mask' has no texel")
    overall = float(np.median(values[mask]))
    medians = np.full(int(count), overall)
    for k in range(int(count)):
        members = values[mask & (labels == k)]
        if members.size:
            medians[k] = float(np.median(members))
    return medians
