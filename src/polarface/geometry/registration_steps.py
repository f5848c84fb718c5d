"""The passes of :func:`polarface.geometry.registration.register_sequence` (its module docstring describes
the algorithm): the walks outwards from the reference with chained odometry, rejections and loop closures
into a pose graph (steps 1-2), the pose-graph optimisation (step 3), and the residuals of every frame
against the voxel model of the accepted frames nearer the reference (step 4). The ICP primitives are in
:mod:`polarface.geometry.registration_icp`.

Units: positions in mm; poses ``P`` ``(4, 4)`` float64 model -> world (rigid); frames are capture frame
indices.
"""

from __future__ import annotations

import collections
import dataclasses
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING

import numpy as np

from polarface.geometry.open3d_library import open3d_module
from polarface.geometry.point_cloud import PointCloud
from polarface.geometry.poses import check_rigid, invert_rigid
from polarface.geometry.registration_icp import (
    global_retry,
    icp,
    model_cloud,
    orthonormalised,
    point_to_plane,
    registration_levels,
    rejection_reason,
    rotation_deg,
    scaled_motion,
)

if TYPE_CHECKING:
    from polarface.geometry.registration import RegistrationConfig

__all__ = ["all_poses", "chain_and_close", "optimise", "residuals_against_model"]


@dataclasses.dataclass
class _Frame:
    """One accepted frame in the sliding window: its clouds per ICP level and its chained pose."""

    index: int
    levels: list  # open3d PointClouds, coarse -> fine
    pose: np.ndarray  # model -> world


@dataclasses.dataclass
class _Graph:
    """Pose-graph bookkeeping: node per accepted frame, edges (source, target, T, information, uncertain)."""

    nodes: dict[int, np.ndarray] = dataclasses.field(default_factory=dict)
    edges: list[tuple[int, int, np.ndarray, np.ndarray, bool]] = dataclasses.field(default_factory=list)


def _walks(frames: list[int], reference: int) -> list[list[int]]:
    """The two walks outwards from the reference (each starting with the frame next to it)."""
    at = frames.index(int(reference))
    return [frames[at + 1 :], frames[:at][::-1]]


def chain_and_close(frames, load_cloud, reference, config, bar):
    """Step 1-2: chained odometry, loop closures, rejections, in a local frame: the world shifted by
    ``-centre`` (the reference cloud's centroid), so that poses have small translations and the pose graph
    is well conditioned (about the rig origin, 1 m away, Levenberg-Marquardt stalls on its first step).

    The two walks share nothing but the reference frame, so they run in two threads (Open3D's ICP and
    numpy's voxel reductions release the GIL); their nodes and edges are merged in walk order, as one
    walk after the other would have added them.

    Returns ``(graph, relative, reasons, centre)``: ``relative[frame] = (anchor, T)`` with the rejected
    frame's local pose ``= P_anchor_optimised @ T``.
    """
    ref_levels, centre = registration_levels(load_cloud(int(reference)), None, config)
    if ref_levels is None:
        raise ValueError(f"argument 'load_cloud': the reference frame {reference} has fewer than 16 points")
    ref = _Frame(int(reference), ref_levels, np.eye(4))
    bar.update(1)
    position = {f: i for i, f in enumerate(frames)}

    def walk_graph(walk: list[int]) -> tuple[_Graph, dict, dict]:
        graph, relative, reasons = _Graph(), {}, {}
        window: collections.deque[_Frame] = collections.deque([ref], maxlen=config.window + 1)
        for frame in walk:
            levels, _ = registration_levels(load_cloud(frame), centre, config)
            _register_one(frame, levels, window, ref, position, graph, relative, reasons, config)
            bar.update(1)
        return graph, relative, reasons

    graph, relative, reasons = _Graph(nodes={ref.index: np.eye(4)}), {}, {}
    for part, part_relative, part_reasons in _both_walks(walk_graph, frames, reference):
        graph.nodes.update(part.nodes)
        graph.edges.extend(part.edges)
        relative.update(part_relative)
        reasons.update(part_reasons)
    return graph, relative, reasons, centre


def _both_walks(run_walk, frames: list[int], reference: int) -> list:
    """``[run_walk(walk) for walk in _walks(frames, reference)]``, the two walks in two threads."""
    with ThreadPoolExecutor(max_workers=2, thread_name_prefix="registration-walk") as pool:
        return list(pool.map(run_walk, _walks(frames, reference)))


def _predict(window, frame: int, position: dict[int, int]) -> np.ndarray:
    """Constant-velocity prediction of ``frame``'s pose from the last two accepted frames of the walk."""
    anchor = window[-1]
    if len(window) < 2:
        return anchor.pose
    before = window[-2]
    motion = anchor.pose @ invert_rigid(before.pose)
    steps = abs(position[frame] - position[anchor.index]) / max(
        abs(position[anchor.index] - position[before.index]), 1
    )
    return scaled_motion(motion, steps) @ anchor.pose


def _register_one(frame, levels, window, ref, position, graph, relative, reasons, config) -> None:
    """Register ``frame`` (its ICP levels) to the window's last frame, check it, add its node and edges."""
    anchor = window[-1]
    predicted = _predict(window, frame, position)
    if levels is None:
        reasons[frame] = "fewer than 16 confident points"
        relative[frame] = (anchor.index, invert_rigid(anchor.pose) @ predicted)
        return
    init = anchor.pose @ invert_rigid(predicted)  # world-k -> world-anchor
    transform, fitness, rmse, information = icp(levels, anchor.levels, init, config)
    pose = invert_rigid(check_rigid(orthonormalised(transform))) @ anchor.pose
    jump = rotation_deg(pose @ invert_rigid(predicted))
    reason = rejection_reason(fitness, rmse, jump, config)
    if reason and config.global_voxel_mm > 0:
        retry = global_retry(levels, anchor.levels, config)
        if retry is not None:
            transform, fitness, rmse, information = retry
            pose = invert_rigid(check_rigid(orthonormalised(transform))) @ anchor.pose
            jump, reason = rotation_deg(pose @ invert_rigid(predicted)), ""
    if reason:
        reasons[frame] = reason
        best = pose if jump <= config.max_rotation_jump_deg else predicted
        relative[frame] = (anchor.index, invert_rigid(anchor.pose) @ best)
        return
    graph.nodes[frame] = pose
    graph.edges.append((frame, anchor.index, transform, information, False))
    current = _Frame(frame, levels, pose)
    targets = [window[-o] for o in config.loop_offsets if o <= len(window)]
    if config.reference_edges and ref not in targets and ref is not anchor:
        targets.append(ref)
    for target in targets:
        init = target.pose @ invert_rigid(pose)
        loop, loop_fitness, loop_rmse, loop_info = icp(
            levels, target.levels, init, config, config.loop_first_level
        )
        if loop_fitness >= config.min_fitness and loop_rmse <= config.max_rmse_mm:
            graph.edges.append((frame, target.index, loop, loop_info, True))
    window.append(current)


def optimise(graph: _Graph, reference: int, config: RegistrationConfig) -> dict[int, np.ndarray]:
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


def residuals_against_model(frames, load_cloud, reference, poses, reasons, config, bar):
    """Step 4: fitness and point-to-plane RMSE of each frame against the voxel model of the accepted frames
    nearer the reference (the reference is the model: fitness 1, RMSE 0); the two walks in two threads."""
    pose_of = dict(zip(frames, poses, strict=True))
    fitness = np.zeros(len(frames))
    rmse = np.full(len(frames), np.nan)
    row = {f: i for i, f in enumerate(frames)}
    reference_model = model_cloud(load_cloud(int(reference)), np.eye(4), config)
    fitness[row[int(reference)]], rmse[row[int(reference)]] = 1.0, 0.0

    def walk_residuals(walk: list[int]) -> None:  # each walk writes its own rows
        model = reference_model
        for frame in walk:
            cloud = model_cloud(load_cloud(frame), pose_of[frame], config)
            bar.update(1)
            if len(cloud) < 16:
                continue
            fitness[row[frame]], rmse[row[frame]] = point_to_plane(cloud, model, config.final_distance_mm)
            if frame not in reasons:
                model = PointCloud.concatenate([model, cloud]).voxel_downsample(config.voxel_mm)

    _both_walks(walk_residuals, frames, reference)
    return fitness, rmse
