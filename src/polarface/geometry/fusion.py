"""Fusion of stereo clouds and screened Poisson meshing (issue 14, items 2-3), trimmed to the data.

:func:`fuse_registered` merges the registered frames' clouds in the model frame on a voxel grid;
:func:`poisson_mesh` meshes a cloud:

The per-frame fused stereo cloud (:class:`~polarface.geometry.point_cloud.PointCloud`, mm) becomes a
watertight-free, data-bounded :class:`~polarface.geometry.mesh.TriangleMesh` by Open3D's screened
Poisson reconstruction (Kazhdan and Hoppe 2013, the paper's "Poisson surface reconstruction"), followed by
three trims, because Poisson closes and extrapolates the surface wherever the data stop:

1. **density**: vertices whose Poisson density (the number of samples supporting the octree node) is
   below a low quantile are removed (the thin membranes Poisson stretches over holes);
2. **distance to the data**: vertices farther than ``max_distance_cells`` octree cells (or point
   spacings, whichever is larger) from the nearest input point are removed — the extrapolated cap of an
   open surface has a high density near its rim, so the density alone does not remove it;
3. **small components**: connected pieces with fewer triangles than ``min_component_fraction`` of the
   largest are removed (isolated outlier clusters).

Everything stays in the cloud's frame and units (mm). Faces are counter-clockwise seen from outside,
i.e. their right-hand normals agree with the cloud's outward normals.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.open3d_library import open3d_module
from polarface.geometry.point_cloud import PointCloud, VoxelAccumulator
from polarface.geometry.poses import invert_rigid

if TYPE_CHECKING:
    from polarface.geometry.registration import SequenceRegistration

__all__ = ["PoissonConfig", "confident_points", "fuse_registered", "poisson_mesh"]

_MIN_POINTS = 16


@dataclasses.dataclass(frozen=True)
class PoissonConfig:
    """Settings of :func:`poisson_mesh` (defaults are the documented choice for a head at 1 m).

    Attributes:
        resolution_mm: upper bound on the width of the finest octree cell, mm. The octree depth derives
            from the cloud's extent, ``depth = ceil(log2(scale * extent / resolution_mm))`` (clamped to
            ``[min_depth, max_depth]``), so clouds of different sizes get the same sampling in mm rather
            than the same number of cells. 1.5 mm gives depth 8 (~1.1 mm cells) for a head-sized cloud
            (~250 mm): measured on 200k points sampled from the bundled head with 0.3 mm noise, the
            surface lies 0.05 mm (median) / 0.16 mm (p95) from the truth in 3.1 s on 2 cores, while
            depth 9 (1.0 mm) takes 13 s and is no more accurate at stereo noise levels.
        min_depth, max_depth: bounds of the derived octree depth.
        scale: ratio of the reconstruction cube to the cloud's bounding cube (Open3D's ``scale``).
        point_weight: screening weight (interpolation of the points vs smoothness; Open3D's default 2).
            4 follows the noise more (p95 error 0.20 vs 0.16 mm in the measurement above).
        samples_per_node: minimum samples per octree node (Open3D's default 1.5 for clean data; higher
            values smooth noisy data).
        linear_fit: place iso-vertices by linear interpolation (more accurate surface positions).
        min_confidence: points with confidence below this are dropped before meshing.
        density_quantile: vertices with Poisson density below this quantile of all vertices are removed
            (0 disables).
        max_distance_cells: vertices farther than this many cells (``max(cell width, median point
            spacing)``) from the nearest input point are removed (Poisson's extrapolation); 0 disables.
        min_component_fraction: connected components with fewer triangles than this fraction of the
            largest component are removed (0 keeps all).
        threads: Open3D worker threads (-1: all cores). 1 by default: Open3D's multi-threaded Poisson
            solver crashes the process at random (a segmentation fault inside
            ``CreateFromPointCloudPoisson``, Open3D issue 6828, PoissonRecon issue 298; seen once in this
            project's CI), and on 2 cores it was no faster (demo frame, 175k points: 2.1 s either way).
            One thread also gives the same mesh on every run.
    """

    resolution_mm: float = 1.5
    min_depth: int = 5
    max_depth: int = 10
    scale: float = 1.1
    point_weight: float = 2.0
    samples_per_node: float = 1.5
    linear_fit: bool = True
    min_confidence: float = 0.1
    density_quantile: float = 0.01
    max_distance_cells: float = 1.5
    min_component_fraction: float = 0.05
    threads: int = 1

    def __post_init__(self) -> None:
        checks = {
            "resolution_mm": self.resolution_mm > 0,
            "min_depth": 1 <= self.min_depth <= self.max_depth,
            "max_depth": self.max_depth <= 12,
            "scale": self.scale >= 1.0,
            "point_weight": self.point_weight >= 0,
            "samples_per_node": self.samples_per_node >= 1.0,
            "min_confidence": 0.0 <= self.min_confidence <= 1.0,
            "density_quantile": 0.0 <= self.density_quantile < 1.0,
            "max_distance_cells": self.max_distance_cells >= 0,
            "min_component_fraction": 0.0 <= self.min_component_fraction <= 1.0,
            "threads": self.threads == -1 or self.threads >= 1,
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"PoissonConfig.{name} is out of range: {getattr(self, name)}")

    def octree_depth(self, extent_mm: float) -> int:
        """Octree depth for a cloud whose largest bounding-box side is ``extent_mm``."""
        cells = max(self.scale * float(extent_mm) / self.resolution_mm, 1.0)
        return int(np.clip(math.ceil(math.log2(cells)), self.min_depth, self.max_depth))


def poisson_mesh(cloud: PointCloud, config: PoissonConfig = PoissonConfig()) -> TriangleMesh:
    """Screened Poisson surface of ``cloud``, trimmed to its data (see the module docstring).

    Args:
        cloud: oriented points in mm (any frame); normals point outwards. Points below
            ``config.min_confidence`` are ignored.
        config: :class:`PoissonConfig`.

    Returns:
        A :class:`TriangleMesh` in the cloud's frame, mm, faces counter-clockwise from outside (along
        the cloud's normals), UVs all zero (no atlas yet).

    Raises:
        ValueError: naming ``cloud`` when it is not a PointCloud, has fewer than 16 confident points,
            non-finite values or no valid normals, or when the trims leave nothing.
    """
    cloud = confident_points(cloud, config)
    o3d = open3d_module()

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    extent = float(np.ptp(cloud.points, axis=0).max())
    depth = config.octree_depth(extent)
    cell_mm = config.scale * extent / 2**depth
    mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        cloud.to_open3d(),
        depth=depth,
        scale=config.scale,
        linear_fit=config.linear_fit,
        n_threads=config.threads,
        samples_per_node=config.samples_per_node,
        point_weight=config.point_weight,
    )
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.triangles, dtype=np.int64)
    if not len(faces):
        raise ValueError("argument 'cloud': Poisson reconstruction produced no surface")
    keep = _trim_vertices(vertices, np.asarray(densities), cloud, cell_mm, config)
    vertices, faces = _keep_vertices(vertices, faces, keep)
    vertices, faces = _drop_small_components(vertices, faces, config.min_component_fraction)
    if not len(faces):
        raise ValueError("argument 'cloud': nothing is left of the Poisson surface after trimming")
    faces = _orient_along_normals(vertices, faces, cloud)
    return TriangleMesh.from_arrays(vertices, faces, np.zeros((len(vertices), 2)), source="poisson_mesh")


def confident_points(cloud: PointCloud, config: PoissonConfig = PoissonConfig()) -> PointCloud:
    """The points of ``cloud`` that :func:`poisson_mesh` meshes: confidence at least
    ``config.min_confidence`` and a normal.

    Raises:
        ValueError: naming ``cloud`` when it is not a PointCloud, has non-finite values, or fewer than 16
            such points.
    """
    if not isinstance(cloud, PointCloud):
        raise ValueError(f"argument 'cloud' must be a PointCloud; got {type(cloud).__name__}")
    if not (np.isfinite(cloud.points).all() and np.isfinite(cloud.normals).all()):
        raise ValueError("argument 'cloud' contains NaN or infinite points or normals")
    usable = (cloud.confidence >= config.min_confidence) & (np.linalg.norm(cloud.normals, axis=1) > 0.5)
    if int(usable.sum()) < _MIN_POINTS:
        raise ValueError(
            f"argument 'cloud' has {int(usable.sum())} points with confidence >= {config.min_confidence} "
            f"and a normal (of {len(cloud)}); at least {_MIN_POINTS} are needed"
        )
    return cloud.select(usable)


def _trim_vertices(
    vertices: np.ndarray, densities: np.ndarray, cloud: PointCloud, cell_mm: float, config: PoissonConfig
) -> np.ndarray:
    """``(V,)`` bool: vertices kept by the density and distance-to-data trims."""
    from scipy.spatial import cKDTree

    keep = np.ones(len(vertices), dtype=bool)
    if config.density_quantile > 0:
        keep &= densities >= np.quantile(densities, config.density_quantile)
    if config.max_distance_cells > 0:
        tree = cKDTree(cloud.points)
        spacing = _median_spacing(tree, cloud.points)
        limit = config.max_distance_cells * max(cell_mm, spacing)
        distance, _ = tree.query(vertices, k=1, distance_upper_bound=limit, workers=-1)
        keep &= np.isfinite(distance)
    return keep


def _median_spacing(tree, points: np.ndarray, sample: int = 4096) -> float:
    """Median distance from a point to its nearest neighbour (on a fixed subsample), mm."""
    step = max(len(points) // sample, 1)
    distance, _ = tree.query(points[::step], k=2, workers=-1)
    return float(np.median(distance[:, 1]))


def _keep_vertices(
    vertices: np.ndarray, faces: np.ndarray, keep: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Remove the vertices not in ``keep`` and every face touching one; re-index compactly."""
    faces = faces[keep[faces].all(axis=1)]
    used = np.zeros(len(vertices), dtype=bool)
    used[faces.reshape(-1)] = True
    index = np.cumsum(used) - 1
    return vertices[used], index[faces]


def _drop_small_components(
    vertices: np.ndarray, faces: np.ndarray, min_fraction: float
) -> tuple[np.ndarray, np.ndarray]:
    """Remove face-connected components (sharing vertices) smaller than ``min_fraction`` of the largest,
    counted in triangles."""
    if not len(faces) or min_fraction <= 0:
        return vertices, faces
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(len(vertices),) * 2)
    _, label = connected_components(graph, directed=False)
    face_label = label[faces[:, 0]]
    sizes = np.bincount(face_label)
    big = sizes >= min_fraction * sizes.max()
    return _keep_vertices(vertices, faces, big[label])


def _orient_along_normals(vertices: np.ndarray, faces: np.ndarray, cloud: PointCloud) -> np.ndarray:
    """Faces wound so that their normals agree with the nearest input normals (flipped if not)."""
    from scipy.spatial import cKDTree

    step = max(len(faces) // 20000, 1)
    sample = faces[::step]
    corners = vertices[sample]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    _, nearest = cKDTree(cloud.points).query(corners.mean(axis=1), k=1, workers=-1)
    agreement = np.einsum("fc,fc->f", cross, cloud.normals[nearest])
    return faces if np.sum(np.sign(agreement)) >= 0 else faces[:, ::-1].copy()


def fuse_registered(
    frame_indices: Sequence[int],
    load_cloud: Callable[[int], PointCloud],
    registration: SequenceRegistration,
    voxel_mm: float,
) -> PointCloud:
    """All accepted frames' clouds in the model frame, merged on a ``voxel_mm`` grid.

    Each frame is loaded, brought into the model frame (``P_k^-1``), downsampled on the grid and added to
    running per-voxel sums (confidence-weighted position, normal and colour sums, total weight, maximum
    confidence), so every frame's points weigh the same whatever the order, and memory is bounded by the
    occupied voxels, not by the frame count. The result equals ``PointCloud.voxel_downsample`` of all
    frames' voxel means at once.

    Args:
        frame_indices: frames to fuse (rejected frames and frames not in ``registration`` are skipped).
        load_cloud: ``frame index -> PointCloud`` in the rig world frame, mm.
        registration: :class:`polarface.geometry.registration.SequenceRegistration` from
            :func:`polarface.geometry.registration.register_sequence`.
        voxel_mm: grid size, mm.

    Returns:
        The fused :class:`PointCloud` in the model frame (mm); empty when nothing was accepted.

    Raises:
        ValueError: naming ``voxel_mm`` when it is not > 0.
    """
    accepted = {
        int(f): pose
        for f, pose, ok in zip(
            registration.frame_indices, registration.poses, registration.accepted, strict=True
        )
        if ok
    }
    grid = VoxelAccumulator(voxel_mm)
    for frame in frame_indices:
        if int(frame) in accepted:
            cloud = load_cloud(int(frame)).voxel_downsample(voxel_mm)
            grid.add(cloud.transformed(invert_rigid(accepted[int(frame)])))
    return grid.cloud()
