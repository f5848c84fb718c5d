"""Rigid registration of the revolving-chair sequence (issue 14, item 3); the registered frames are fused
into the model frame by :func:`polarface.geometry.fusion.fuse_registered`.

Each capture frame ``k`` has a fused stereo cloud in the rig world frame. The head moves rigidly between
frames; :func:`register_sequence` finds the pose ``P_k`` (model -> world, 4x4, mm) of every frame, where
the model frame is the world frame at the reference frame (``P_reference = I``), so that
``world cloud of frame k ~= P_k applied to model points`` and the reference cloud *is* the model.

Algorithm (Open3D, multi-scale point-to-plane ICP + pose graph):

1. Walk outwards from the reference in both directions. Frame ``k`` is registered to its neighbour
   ``j`` nearer the reference (the last accepted one), initialised by a constant-velocity prediction
   of the chain. The ICP result ``T_kj`` (world-k -> world-j, ``= P_j P_k^-1``) is checked: fitness,
   inlier RMSE and its rotation jump from the prediction; a failing frame is rejected with a reason and
   left out of the graph (it keeps its best estimate relative to its anchor, flagged).
2. Loop closures: the frame is also registered to the accepted frames ``loop_offsets`` steps back along
   the walk and to the reference; each edge with enough fitness enters the graph as an uncertain edge.
3. ``open3d.pipelines.registration.global_optimization`` (Levenberg-Marquardt, line process pruning of
   wrong loop closures) over all accepted frames. Open3D's node pose is ``X_k = P_k^-1`` (frame -> model).
4. A second pass walks outwards again with the optimised poses, growing a voxel model of the accepted
   frames, and reports each frame's fitness and RMSE against the model built from the frames nearer the
   reference; frames that no longer fit are rejected.

The two walks outwards from the reference (steps 1 and 4) share nothing but the reference frame and run
in two threads; the pose graph adds their nodes and edges in walk order, as one walk after the other would.

Memory: ``load_cloud`` is called once per frame per pass; only a bounded window of downsampled clouds
per walk (the last ``max(loop_offsets)`` accepted frames of its side and the reference) and a voxel
model per walk bounded by the head's surface area are held, whatever the number of frames.

Measured (partial views of the bundled head, independent samples per frame, 0.3 mm noise, 2 cores):
24 frames at 5 deg (+-60 deg, ~126k points each): rotation error median 0.008 deg, max 0.015 deg,
translation 0.005 mm median, ~1.2 s per frame for both passes (before ``icp_tolerance`` stopped the ICP
levels early); 200 frames at 0.6 deg (~38k points):
median 0.011 deg, max 0.022 deg, 0.011 mm; peak memory flat in the frame count (80 frames: 468 -> 481 MB).

Modules, by concept (in the manner of Open3D's ``pipelines/registration``), bottom up:

- :mod:`~polarface.geometry.registration.config`: :class:`RegistrationConfig`, the settings;
- :mod:`~polarface.geometry.registration.icp`: the clouds per ICP level, the multi-scale point-to-plane
  ICP, its information matrix, the acceptance test and the rigid-motion helpers;
- :mod:`~polarface.geometry.registration.global_registration`: the FPFH + RANSAC retry of a rejected frame;
- :mod:`~polarface.geometry.registration.pose_graph`: the pose graph and its optimisation (step 3);
- :mod:`~polarface.geometry.registration.odometry`: the walks outwards from the reference, chained
  odometry, rejections and loop closures (steps 1-2);
- :mod:`~polarface.geometry.registration.residuals`: the residuals against the model (step 4);
- :mod:`~polarface.geometry.registration.sequence`: :func:`register_sequence` and its result;
- :mod:`~polarface.geometry.registration.pair`: :func:`register_pair`, :func:`register_pair_starts`.

This package's face re-exports the public names.
"""

from polarface.geometry.registration.config import RegistrationConfig
from polarface.geometry.registration.pair import PairRegistration, register_pair, register_pair_starts
from polarface.geometry.registration.sequence import SequenceRegistration, register_sequence

__all__ = [
    "PairRegistration", "RegistrationConfig", "SequenceRegistration", "register_pair", "register_pair_starts",
    "register_sequence",
]
