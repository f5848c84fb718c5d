"""Sequence registration (polarface.geometry.registration): known rigid motions of partial, noisy views of
the bundled head are recovered; a frame with no overlap is rejected with a reason; clouds are loaded
lazily; registered frames fuse into the model frame."""

from __future__ import annotations

import math
import threading
import weakref

import numpy as np
import pytest
from scipy.spatial import cKDTree

from polarface.geometry import load_head_asset
from polarface.geometry.fusion import fuse_registered
from polarface.geometry.point_cloud import PointCloud
from polarface.geometry.poses import invert_rigid, rigid_transform
from polarface.geometry.registration import (
    RegistrationConfig,
    SequenceRegistration,
    register_pair,
    register_pair_starts,
    register_sequence,
)

# model (+y up, face +z) -> rig world (y down, z away from the camera at the origin), face 1 m away
RIG_FROM_HEAD = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 1000.0], [0, 0, 0, 1]])
FRAMES = 10
REFERENCE = 4


@pytest.fixture(scope="module")
def head_surface():
    """``(points (M, 3), normals (M, 3))`` sampled area-weighted on the bundled head above the neck."""
    mesh = load_head_asset(texture_resolution=64).mesh
    rng = np.random.default_rng(0)
    areas = mesh.face_areas()
    faces = rng.choice(len(areas), size=400_000, p=areas / areas.sum())
    weights = rng.dirichlet(np.ones(3), size=len(faces))
    points = np.einsum("fk,fkc->fc", weights, mesh.vertices[mesh.faces[faces]])
    normals = mesh.face_normals()[faces]
    keep = points[:, 1] > -120.0
    return points[keep], normals[keep]


def true_poses(count: int = FRAMES, step_deg: float = 5.0) -> np.ndarray:
    """Yaw sweep of ``step_deg`` per frame about the neck, a small pitch nod and sub-mm translations."""
    pivot = load_head_asset(texture_resolution=64).neck_pivot
    poses = []
    for k in range(count):
        yaw = math.radians(step_deg * (k - REFERENCE))
        pitch = math.radians(2.0 * math.sin(k))
        shift = (0.5 * math.sin(k), 0.3 * math.cos(k), 0.2 * k)
        poses.append(RIG_FROM_HEAD @ rigid_transform(yaw, pitch, 0.0, shift, pivot))
    return np.stack(poses)


def partial_view(surface, pose: np.ndarray, seed: int, count: int = 25_000, noise_mm: float = 0.1):
    """The part of the head seen from the rig origin in pose ``pose``: an independent subsample of the
    surface points whose normal faces the camera, with ``noise_mm`` noise along the normal."""
    points, normals = surface
    rng = np.random.default_rng(seed)
    world = points @ pose[:3, :3].T + pose[:3, 3]
    world_normals = normals @ pose[:3, :3].T
    to_camera = -world / np.linalg.norm(world, axis=1, keepdims=True)
    visible = np.flatnonzero(np.einsum("ij,ij->i", world_normals, to_camera) > 0.1)
    chosen = rng.choice(visible, size=min(count, len(visible)), replace=False)
    noisy = world[chosen] + world_normals[chosen] * rng.normal(0.0, noise_mm, (len(chosen), 1))
    return PointCloud.from_arrays(noisy, world_normals[chosen])


def unrelated_cloud(seed: int) -> PointCloud:
    """A small sphere 400 mm to the side of the head: no overlap with any frame."""
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(5000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return PointCloud.from_arrays((400.0, 0.0, 900.0) + 30.0 * directions, directions)


class LazyLoader:
    """``load_cloud`` that counts calls and how many of the clouds it returned are still alive."""

    def __init__(self, make) -> None:
        self.make = make
        self.calls: list[int] = []
        self.returned: list[weakref.ref] = []
        self.max_alive = 0

    def __call__(self, frame: int) -> PointCloud:
        alive = sum(ref() is not None for ref in self.returned)
        self.max_alive = max(self.max_alive, alive)
        self.calls.append(frame)
        cloud = self.make(frame)
        self.returned.append(weakref.ref(cloud))
        return cloud


def pose_errors(estimated: np.ndarray, truth: np.ndarray, reference: int):
    """Rotation error (deg) and translation error at the head (mm) of each estimated model -> world pose
    against the true motion relative to the reference frame."""
    relative = truth @ invert_rigid(truth[reference])
    head_centre = truth[:, :3, 3]  # where the model origin (head centre) lies in each frame
    rotation, translation = [], []
    for k in range(len(truth)):
        error = estimated[k] @ invert_rigid(relative[k])
        cosine = (np.trace(error[:3, :3]) - 1.0) / 2.0
        rotation.append(math.degrees(math.acos(np.clip(cosine, -1.0, 1.0))))
        moved = error[:3, :3] @ head_centre[k] + error[:3, 3]
        translation.append(float(np.linalg.norm(moved - head_centre[k])))
    return np.array(rotation), np.array(translation)


@pytest.fixture(scope="module")
def sweep(head_surface):
    truth = true_poses()
    loader = LazyLoader(lambda k: partial_view(head_surface, truth[k], seed=k))
    result = register_sequence(range(FRAMES), loader, REFERENCE)
    return truth, loader, result


def test_register_sequence_recovers_known_motions(sweep):
    truth, _, result = sweep
    assert isinstance(result, SequenceRegistration)
    assert result.accepted.all() and not result.rejected
    np.testing.assert_array_equal(result.frame_indices, np.arange(FRAMES))
    np.testing.assert_allclose(result.poses[REFERENCE], np.eye(4), atol=1e-9)
    rotation, translation = pose_errors(result.poses, truth, REFERENCE)
    # measured: rotation <= 0.02 deg, translation <= 0.015 mm (0.1 mm noise, 25k points per view)
    assert rotation.max() < 0.05, rotation
    assert translation.max() < 0.1, translation
    # residuals against the model: a little above the noise (the model is a voxel average)
    others = np.arange(FRAMES) != REFERENCE
    assert np.all(result.rmse_mm[others] < 0.3) and np.all(result.fitness[others] > 0.8)


def test_the_same_sequence_twice_gives_the_same_poses_bit_for_bit(head_surface):
    """Open3D's multi-threaded reductions made the poses of two registrations of the same clouds differ by
    ~1e-12 mm (issue 47), enough to change the unwrapped observations and the maps; under serial_open3d
    they are the same bits, and Open3D's thread limit is put back afterwards."""
    from polarface.geometry.open3d_library import open3d_module

    truth = true_poses(count=4)
    clouds = [partial_view(head_surface, truth[k], seed=k, count=15_000) for k in range(4)]
    limit = open3d_module().utility.get_max_threads()
    runs = [register_sequence(range(4), clouds.__getitem__, 2) for _ in range(3)]
    assert open3d_module().utility.get_max_threads() == limit
    for run in runs[1:]:
        np.testing.assert_array_equal(run.poses, runs[0].poses)
        np.testing.assert_array_equal(run.fitness, runs[0].fitness)
        np.testing.assert_array_equal(run.rmse_mm, runs[0].rmse_mm)


def test_serial_open3d_is_counted_over_threads_and_restores_the_limit():
    from polarface.geometry.open3d_library import open3d_module, serial_open3d

    utility = open3d_module().utility
    assert hasattr(utility, "set_max_threads"), "pyproject.toml requires Open3D >= 0.20, which has it"
    before = utility.get_max_threads()
    inside, leave = threading.Event(), threading.Event()
    seen = []

    def hold() -> None:
        with serial_open3d():
            inside.set()
            leave.wait(10)

    holder = threading.Thread(target=hold)
    holder.start()
    assert inside.wait(10)
    with serial_open3d() as o3d:
        seen.append(o3d.utility.get_max_threads())
    seen.append(utility.get_max_threads())  # the other thread still holds it
    leave.set()
    holder.join(10)
    assert seen == [1, 1] and utility.get_max_threads() == before


def test_world_cloud_is_the_pose_applied_to_the_model(sweep, head_surface):
    truth, _, result = sweep
    model = partial_view(head_surface, truth[REFERENCE], seed=99, noise_mm=0.0)
    frame = 7
    moved = model.transformed(result.poses[frame]).points
    expected = model.transformed(truth[frame] @ invert_rigid(truth[REFERENCE])).points
    assert np.abs(moved - expected).max() < 0.2


def test_clouds_are_loaded_lazily(sweep):
    _, loader, _ = sweep
    counts = np.bincount(loader.calls, minlength=FRAMES)
    assert counts.max() <= 2  # one registration pass, one residual pass
    # the loader's clouds are released (only downsampled copies are held): at most one per walk (the two
    # walks run in two threads) and one not yet released
    assert loader.max_alive <= 3


def test_walks_run_in_threads_and_enter_the_graph_in_walk_order(head_surface):
    from tqdm import tqdm

    from polarface.geometry.registration.odometry import chain_and_close

    truth = true_poses(count=8)
    threads = set()

    def load(frame: int) -> PointCloud:
        threads.add(threading.current_thread().name)
        return partial_view(head_surface, truth[frame], seed=frame)

    graph, _, reasons, _ = chain_and_close(list(range(8)), load, REFERENCE, RegistrationConfig(),
                                           tqdm(disable=True))
    assert not reasons and any(name.startswith("registration-walk") for name in threads)
    assert list(graph.nodes) == [REFERENCE, 5, 6, 7, 3, 2, 1, 0]
    odometry = [(source, target) for source, target, *_, uncertain in graph.edges if not uncertain]
    assert odometry == [(5, 4), (6, 5), (7, 6), (3, 4), (2, 3), (1, 2), (0, 1)]
    # each frame's loop closures follow its odometry edge, as one walk after the other adds them
    sources = [source for source, *_ in graph.edges]
    assert sources == sorted(sources[: sources.index(3)]) + sorted(sources[sources.index(3):], reverse=True)


def test_frame_without_overlap_is_rejected_and_the_others_stay_right(head_surface):
    truth = true_poses(count=8)
    bad = 6
    loader = LazyLoader(
        lambda k: unrelated_cloud(k) if k == bad else partial_view(head_surface, truth[k], seed=k)
    )
    result = register_sequence(range(8), loader, REFERENCE, RegistrationConfig(loop_offsets=(2,)))
    assert set(result.rejected) == {bad}
    assert "fitness" in result.rejected[bad] and "no overlap" in result.rejected[bad]
    assert not result.accepted[bad] and result.accepted.sum() == 7
    rotation, translation = pose_errors(result.poses, truth, REFERENCE)
    good = np.arange(8) != bad
    assert rotation[good].max() < 0.05, rotation
    assert translation[good].max() < 0.1, translation
    summary = result.to_json()
    assert summary["rejected"] == {str(bad): result.rejected[bad]} and summary["accepted_count"] == 7


def test_fuse_registered_merges_accepted_frames_in_the_model_frame(sweep, head_surface):
    truth, _, result = sweep
    frames = [2, REFERENCE, 6]
    fused = fuse_registered(frames, lambda k: partial_view(head_surface, truth[k], seed=k), result, 1.0)
    # the model frame is the rig world at the reference: the true surface there is truth[REFERENCE] applied
    # to the head; every fused point lies on it
    surface = PointCloud.from_arrays(*head_surface).transformed(truth[REFERENCE])
    distance, _ = cKDTree(surface.points).query(fused.points)
    assert np.median(distance) < 0.5
    # the fused cloud covers more than the reference view alone (the sides seen by frames 2 and 6)
    alone = fuse_registered([REFERENCE], lambda k: partial_view(head_surface, truth[k], seed=k), result, 1.0)
    assert len(fused) > 1.1 * len(alone)
    with pytest.raises(ValueError, match="'voxel_mm'"):
        fuse_registered(frames, lambda k: partial_view(head_surface, truth[k], seed=k), result, 0.0)


def test_bad_arguments_name_the_argument():
    def never(_):  # pragma: no cover - must not be called
        raise AssertionError("load_cloud called on bad input")

    with pytest.raises(ValueError, match="'frame_indices'"):
        register_sequence([], never, 0)
    with pytest.raises(ValueError, match="'frame_indices'"):
        register_sequence([1, 1, 2], never, 1)
    with pytest.raises(ValueError, match="'reference'"):
        register_sequence([1, 2, 3], never, 7)
    with pytest.raises(ValueError, match="'load_cloud'"):
        register_sequence([0, 1], lambda _: PointCloud.empty(), 0)
    with pytest.raises(ValueError, match="min_fitness"):
        RegistrationConfig(min_fitness=2.0)
    with pytest.raises(ValueError, match="icp_tolerance"):
        RegistrationConfig(icp_tolerance=0.0)


def test_edges_do_not_keep_open3d_results_alive(head_surface):
    """Regression: ``np.asarray(result.transformation)`` is a view whose base keeps Open3D's whole
    registration result (its correspondence set) alive in the pose graph: memory grew ~1 MB per frame."""
    from polarface.geometry.registration.icp import icp, registration_levels

    config = RegistrationConfig()
    truth = true_poses(count=2)
    source, centre = registration_levels(partial_view(head_surface, truth[1], seed=1), None, config)
    target, _ = registration_levels(partial_view(head_surface, truth[0], seed=0), centre, config)
    transform, _, _, information = icp(source, target, np.eye(4), config)
    assert transform.base is None and information.base is None


def test_register_pair_recovers_a_known_motion_of_the_whole_head_onto_a_partial_view(head_surface):
    """The dynamic stage's alignment: the whole reference head onto one frame's front view."""
    points, normals = head_surface
    whole = PointCloud.from_arrays(points[::8] @ RIG_FROM_HEAD[:3, :3].T + RIG_FROM_HEAD[:3, 3],
                                   normals[::8] @ RIG_FROM_HEAD[:3, :3].T)
    truth = rigid_transform(math.radians(3.0), math.radians(-2.0), 0.0, (4.0, -3.0, 2.0))
    truth = RIG_FROM_HEAD @ truth @ invert_rigid(RIG_FROM_HEAD)  # a motion about the rig origin
    view = partial_view(head_surface, truth @ RIG_FROM_HEAD, seed=7)
    result = register_pair(whole, view)
    error = result.transform @ invert_rigid(truth)
    angle = math.degrees(math.acos(np.clip((np.trace(error[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
    assert angle < 0.05, angle
    centre = RIG_FROM_HEAD[:3, 3]
    assert np.linalg.norm(error[:3, :3] @ centre + error[:3, 3] - centre) < 0.05
    assert 0.2 < result.fitness < 0.8  # the whole head vs its front: about half has a partner
    assert result.target_fitness > 0.6  # the whole head explains the view (sparse source: every 8th sample)
    assert 0.0 < result.rmse_mm < 1.5  # point-to-point within the finest distance (sparse samples)


def test_register_pair_names_a_cloud_without_points(head_surface):
    points, normals = head_surface
    cloud = PointCloud.from_arrays(points[:1000], normals[:1000])
    with pytest.raises(ValueError, match="'source'"):
        register_pair(PointCloud.empty(), cloud)
    with pytest.raises(ValueError, match="'target'"):
        register_pair(cloud, PointCloud.empty())
    with pytest.raises(ValueError, match="'init'"):
        register_pair(cloud, cloud, np.full((4, 4), np.nan))


def test_register_pair_starts_is_register_pair_from_each_start(head_surface):
    """The levels built once and the starts' ICPs in threads: each start's result is register_pair's, bit
    for bit (every ICP on its own thread: serial_open3d), in the starts' order."""
    points, normals = head_surface
    whole = PointCloud.from_arrays(points[::16], normals[::16])
    view = partial_view(head_surface, rigid_transform(math.radians(2.0), 0.0, 0.0, (3.0, -2.0, 1.0)), seed=3)
    starts = [np.eye(4), rigid_transform(0.0, math.radians(4.0), 0.0, (0.0, 5.0, 0.0)),
              rigid_transform(0.0, math.radians(50.0), 0.0, (0.0, 0.0, 0.0))]  # far: another minimum
    expected = [register_pair(whole, view, start) for start in starts]
    for threads in (1, 2, 3):
        results = register_pair_starts(whole, view, starts, threads=threads)
        assert len(results) == len(starts)
        for got, want in zip(results, expected, strict=True):
            np.testing.assert_array_equal(got.transform, want.transform)
            assert (got.fitness, got.target_fitness, got.rmse_mm) == (want.fitness, want.target_fitness,
                                                                      want.rmse_mm)
    assert np.abs(expected[2].transform - expected[0].transform).max() > 1e-3  # the order is the starts'
    assert register_pair_starts(whole, view, []) == []
    with pytest.raises(ValueError, match=r"'starts\[1\]'"):
        register_pair_starts(whole, view, [np.eye(4), np.full((4, 4), np.nan)])
    with pytest.raises(ValueError, match="'threads' must be >= 1"):
        register_pair_starts(whole, view, starts, threads=0)


def test_icp_scores_and_information_are_those_of_its_transform(head_surface):
    """``icp`` takes fitness, RMSE and the information matrix from its last iterate instead of searching the
    neighbours again: they equal Open3D's ``evaluate_registration`` and
    ``get_information_matrix_from_point_clouds`` at the returned transform (independent reference)."""
    from open3d.pipelines import registration as reg

    from polarface.geometry.registration.icp import icp, registration_levels

    config = RegistrationConfig()
    truth = true_poses(count=2)
    source, centre = registration_levels(partial_view(head_surface, truth[1], seed=1), None, config)
    target, _ = registration_levels(partial_view(head_surface, truth[0], seed=0), centre, config)
    transform, fitness, rmse, information = icp(source, target, np.eye(4), config)
    distance = config.scales[-1][1]
    scored = reg.evaluate_registration(source[-1], target[-1], distance, transform)
    assert fitness == pytest.approx(scored.fitness, abs=1e-9) and fitness > 0.5
    assert rmse == pytest.approx(scored.inlier_rmse, rel=1e-9)
    expected = np.asarray(reg.get_information_matrix_from_point_clouds(source[-1], target[-1], distance,
                                                                       transform))
    assert np.allclose(information, expected, rtol=1e-9, atol=1e-6 * np.abs(expected).max())


def test_information_matrix_is_the_sum_of_point_jacobians():
    """Closed form against the explicit sum of ``G^T G``, ``G = [-[t]x | I]``; points on one line leave the
    rotation about that line unconstrained (rank 5); bad shapes name the argument."""
    from polarface.geometry.registration.icp import information_matrix

    points = np.random.default_rng(3).normal(0.0, 50.0, (40, 3))
    explicit = np.zeros((6, 6))
    for x, y, z in points:
        jacobian = np.array([[0, z, -y, 1, 0, 0], [-z, 0, x, 0, 1, 0], [y, -x, 0, 0, 0, 1]], float)
        explicit += jacobian.T @ jacobian
    assert np.allclose(information_matrix(points), explicit, rtol=1e-12, atol=1e-9)
    assert np.linalg.matrix_rank(information_matrix(points)) == 6
    line = np.outer(np.linspace(-50.0, 50.0, 20), [1.0, 2.0, -0.5])
    assert np.linalg.matrix_rank(information_matrix(line), tol=1e-6 * 20 * 50.0**2) == 5
    assert np.array_equal(information_matrix(np.zeros((0, 3))), np.zeros((6, 6)))
    with pytest.raises(ValueError, match="'target_points'"):
        information_matrix(np.zeros((4, 2)))
