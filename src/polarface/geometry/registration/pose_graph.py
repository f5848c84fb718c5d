"""The pose graph of :func:`polarface.geometry.registration.register_sequence` (step 3 of the package
docstring): the accepted frames' nodes and their odometry and loop-closure edges, Open3D's
Levenberg-Marquardt global optimisation, and every frame's pose from the optimised ones.

Units: poses ``P`` ``(4, 4)`` float64 model -> world (rigid, mm); frames are capture frame indices.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from polarface.geometry.open3d_library import open3d_module
from polarface.geometry.poses import invert_rigid
from polarface.geometry.registration.config import RegistrationConfig
from polarface.geometry.registration.icp import orthonormalised

__all__ = ["PoseGraph", "all_poses", "optimise"]


@dataclasses.dataclass
class PoseGraph:
    """Pose-graph bookkeeping: node per accepted frame, edges (source, target, T, information, uncertain)."""

    nodes: dict[int, np.ndarray] = dataclasses.field(default_factory=dict)
    edges: list[tuple[int, int, np.ndarray, np.ndarray, bool]] = dataclasses.field(default_factory=list)


def optimise(graph: PoseGraph, reference: int, config: RegistrationConfig) -> dict[int, np.ndarray]:
    """Step 3: Levenberg-Marquardt pose-graph optimisation; returns frame -> optimised pose P."""
    o3d = open3d_module()
    reg = o3d.pipelines.registration

    order = list(graph.nodes)
    if len(order) < 2:
        return dict(graph.nodes)
    node_of = {frame: i for i, frame in enumerate(order)}
    pose_graph = reg.PoseGraph()
    for frame in order:
        pose_graph.nodes.append(reg.PoseGraphNode(invert_rigid(graph.nodes[frame])))  # X = P^-1
    for source, target, transform, information, uncertain in graph.edges:
        pose_graph.edges.append(
            reg.PoseGraphEdge(node_of[source], node_of[target], transform, information, uncertain=uncertain)
        )
    option = reg.GlobalOptimizationOption(
        max_correspondence_distance=config.scales[-1][1],
        edge_prune_threshold=config.edge_prune_threshold,
        preference_loop_closure=config.preference_loop_closure,
        reference_node=node_of[int(reference)],
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(
            pose_graph,
            reg.GlobalOptimizationLevenbergMarquardt(),
            reg.GlobalOptimizationConvergenceCriteria(),
            option,
        )
    to_model_ref = np.asarray(pose_graph.nodes[node_of[int(reference)]].pose)
    return {
        frame: orthonormalised(to_model_ref)
        @ invert_rigid(orthonormalised(np.asarray(pose_graph.nodes[node_of[frame]].pose)))
        for frame in order
    }


def all_poses(frames: list[int], optimised: dict[int, np.ndarray], relative: dict) -> np.ndarray:
    """``(F, 4, 4)`` poses: optimised for accepted frames, anchor-relative estimates for rejected ones."""
    poses = np.empty((len(frames), 4, 4))
    for k, frame in enumerate(frames):
        if frame in optimised:
            poses[k] = optimised[frame]
        else:
            anchor, transform = relative[frame]
            poses[k] = orthonormalised(optimised[anchor] @ transform)
    return poses
