"""The walks outwards from the reference of :func:`polarface.geometry.registration.register_sequence`
(steps 1-2 of the package docstring): chained odometry with its constant-velocity prediction, rejections
(with the global retry) and loop closures, into a
:class:`~polarface.geometry.registration.pose_graph.PoseGraph`. The two walks run in two threads
(:func:`both_walks`, also used by the residuals of step 4).

Units: positions in mm; poses ``P`` ``(4, 4)`` float64 model -> world (rigid); frames are capture frame
indices.
"""

from __future__ import annotations

import collections
import dataclasses
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from polarface.geometry.poses import check_rigid, invert_rigid
from polarface.geometry.registration.global_registration import global_retry
from polarface.geometry.registration.icp import (
    icp,
    orthonormalised,
    registration_levels,
    rejection_reason,
    rotation_deg,
    scaled_motion,
)
from polarface.geometry.registration.pose_graph import PoseGraph

__all__ = ["both_walks", "chain_and_close", "outward_walks"]


@dataclasses.dataclass
class _Frame:
    """One accepted frame in the sliding window: its clouds per ICP level and its chained pose."""

    index: int
    levels: list  # open3d PointClouds, coarse -> fine
    pose: np.ndarray  # model -> world


def outward_walks(frames: list[int], reference: int) -> list[list[int]]:
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

    def walk_graph(walk: list[int]) -> tuple[PoseGraph, dict, dict]:
        graph, relative, reasons = PoseGraph(), {}, {}
        window: collections.deque[_Frame] = collections.deque([ref], maxlen=config.window + 1)
        for frame in walk:
            levels, _ = registration_levels(load_cloud(frame), centre, config)
            _register_one(frame, levels, window, ref, position, graph, relative, reasons, config)
            bar.update(1)
        return graph, relative, reasons

    graph, relative, reasons = PoseGraph(nodes={ref.index: np.eye(4)}), {}, {}
    for part, part_relative, part_reasons in both_walks(walk_graph, frames, reference):
        graph.nodes.update(part.nodes)
        graph.edges.extend(part.edges)
        relative.update(part_relative)
        reasons.update(part_reasons)
    return graph, relative, reasons, centre


def both_walks(run_walk, frames: list[int], reference: int) -> list:
    """``[run_walk(walk) for walk in outward_walks(frames, reference)]``, the two walks in two threads."""
    with ThreadPoolExecutor(max_workers=2, thread_name_prefix="registration-walk") as pool:
        return list(pool.map(run_walk, outward_walks(frames, reference)))


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
