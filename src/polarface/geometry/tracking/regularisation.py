"""The regulariser of :func:`polarface.geometry.tracking.track_mesh` (step 5 of the package docstring):
the reference mesh's edge graph with UV seams welded, the harmonic fill of the untracked vertices'
displacements and the neighbour smoothing.

Units: positions in mm in the rig world.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.raycast import closest_surface_points
from polarface.geometry.tracking.config import TrackingConfig

__all__ = ["MeshGraph", "regularise", "tracking_support"]


class MeshGraph:
    """Edge graph of the reference mesh with UV-seam duplicates welded (one node per position)."""

    def __init__(self, reference: TriangleMesh):
        _, node = np.unique(np.round(reference.vertices, 6), axis=0, return_inverse=True)
        self.node = node.reshape(-1)
        self.count = int(self.node.max()) + 1
        faces = self.node[reference.faces]
        rows = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2], faces[:, 1], faces[:, 2], faces[:, 0]])
        cols = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0], faces[:, 0], faces[:, 1], faces[:, 2]])
        off_diagonal = rows != cols
        adjacency = scipy.sparse.coo_matrix(
            (np.ones(int(off_diagonal.sum())), (rows[off_diagonal], cols[off_diagonal])),
            shape=(self.count, self.count)).tocsr()
        adjacency.data[:] = 1.0
        self.adjacency = adjacency
        self.degree = np.asarray(adjacency.sum(axis=1)).reshape(-1)
        multiplicity = np.bincount(self.node, minlength=self.count).astype(np.float64)
        self._gather = scipy.sparse.csr_matrix(
            (1.0 / multiplicity[self.node], (self.node, np.arange(len(self.node)))),
            shape=(self.count, len(self.node)))

    def to_nodes(self, values: np.ndarray) -> np.ndarray:
        """Per-vertex ``(N, k)`` -> per-node mean ``(M, k)``."""
        return self._gather @ values

    def fill(self, values: np.ndarray, known: np.ndarray, screening: float = 0.0) -> np.ndarray:
        """Harmonic interpolation of node values ``(M, k)`` from the ``known`` ``(M,)`` nodes; nodes of
        components without a known node get 0. ``screening`` > 0 adds ``screening * x`` to the graph
        Laplacian's equations (screened interpolation): the filled values decay towards 0 over about
        ``1 / sqrt(screening)`` edges from the known nodes instead of carrying their border's values
        across every unknown region."""
        unknown = ~known
        if not unknown.any() or not known.any():
            return np.where(known[:, None], values, 0.0)
        laplacian = scipy.sparse.diags(self.degree) - self.adjacency
        diagonal = scipy.sparse.identity(int(unknown.sum())) * (1e-9 + screening)
        block = laplacian[unknown][:, unknown] + diagonal
        rhs = self.adjacency[unknown][:, known] @ values[known]
        solved = scipy.sparse.linalg.spsolve(block.tocsc(), rhs)
        out = values.copy()
        out[unknown] = np.asarray(solved).reshape(-1, values.shape[1])
        return out

    def smooth(self, values: np.ndarray, iterations: int) -> np.ndarray:
        """``iterations`` passes of ``v <- (v + mean of neighbours) / 2``."""
        safe_degree = np.maximum(self.degree, 1.0)[:, None]
        for _ in range(iterations):
            values = 0.5 * values + 0.5 * (self.adjacency @ values) / safe_degree
        return values


def regularise(estimate: np.ndarray, tracked: np.ndarray, rest: np.ndarray, graph: MeshGraph,
                surface: TriangleMesh, config: TrackingConfig) -> np.ndarray:
    """Tracked vertices snapped to the surface, the displacement from ``rest`` harmonically filled
    over the untracked vertices, then smoothed (averages out the surface's noise): ``(N, 3)`` mm."""
    snapped = np.nan_to_num(estimate)
    if config.snap_to_surface:
        snapped[tracked] = closest_surface_points(surface.vertices, surface.faces, snapped[tracked]).point
    displacement = np.where(tracked[:, None], snapped - rest, 0.0)
    node_weight = graph.to_nodes(tracked.astype(np.float64)[:, None])[:, 0]
    node_values = graph.to_nodes(displacement) / np.maximum(node_weight, 1e-12)[:, None]
    node_known = node_weight > 0.5
    if config.fill_screening > 0 and node_known.sum() >= 3:
        rest_nodes = graph.to_nodes(rest)
        rigid = _rigid_motion(rest_nodes[node_known], node_values[node_known])
        moved_rigidly = rest_nodes @ rigid[:3, :3].T + rigid[:3, 3] - rest_nodes
        residual = np.where(node_known[:, None], node_values - moved_rigidly, 0.0)
        node_values = moved_rigidly + graph.fill(residual, node_known, config.fill_screening)
    else:
        node_values = graph.fill(np.where(node_known[:, None], node_values, 0.0), node_known)
    node_values = graph.smooth(node_values, config.smoothing_iterations)
    return rest + node_values[graph.node]


def _rigid_motion(points: np.ndarray, displacement: np.ndarray, rounds: int = 3) -> np.ndarray:
    """``(4, 4)`` rigid transform that best moves ``points`` ``(M, 3)`` by ``displacement`` ``(M, 3)`` (mm):
    least squares (scipy's ``Rotation.align_vectors`` about the centroids), refitted ``rounds`` times on
    the points whose residual is at most twice the median's (at least 0.5 mm), so that an expression's
    motion (brows, jaw) does not tilt the head's rigid motion."""
    from scipy.spatial.transform import Rotation

    targets = points + displacement
    kept = np.ones(len(points), bool)
    transform = np.eye(4)
    for _ in range(rounds):
        source, target = points[kept], targets[kept]
        source_mean, target_mean = source.mean(axis=0), target.mean(axis=0)
        rotation, _ = Rotation.align_vectors(target - target_mean, source - source_mean)
        transform[:3, :3] = rotation.as_matrix()
        transform[:3, 3] = target_mean - transform[:3, :3] @ source_mean
        residual = np.linalg.norm(points @ transform[:3, :3].T + transform[:3, 3] - targets, axis=1)
        limit = max(2.0 * float(np.median(residual)), 0.5)
        if (residual <= limit).sum() < 3:
            break
        kept = residual <= limit
    return transform


def tracking_support(reference: TriangleMesh, confidence: np.ndarray, rings: int) -> np.ndarray:
    """``(N,)`` float64 the tracking confidence ``(N,)`` of ``reference``'s vertices averaged over their
    neighbourhoods (``rings`` passes of neighbour averaging over the seam-welded mesh graph, about that many
    rings of edges): high where the vertex or most of its neighbours were tracked, 0 inside an untracked
    region wider than ``rings`` edges, whose positions the regulariser only guessed (step 5: the head's
    rigid motion plus a decaying fill)."""
    values = np.asarray(confidence, dtype=np.float64).reshape(-1)
    if values.shape != (len(reference.vertices),):
        raise ValueError(f"argument 'confidence' must be ({len(reference.vertices)},); got {values.shape}")
    graph = MeshGraph(reference)
    return graph.smooth(graph.to_nodes(values[:, None]), int(rings))[:, 0][graph.node]
