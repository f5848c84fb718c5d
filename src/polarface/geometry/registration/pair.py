"""Rigid registration of one cloud onto another (:func:`register_pair`, from one or several starts:
:func:`register_pair_starts`) with the ICP levels and robust kernel of
:func:`polarface.geometry.registration.register_sequence`; e.g. a reference mesh's vertices onto another
capture's first frame.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from polarface.geometry.open3d_library import serial_open3d
from polarface.geometry.point_cloud import PointCloud
from polarface.geometry.poses import check_rigid, invert_rigid
from polarface.geometry.registration.config import RegistrationConfig
from polarface.geometry.registration.icp import icp, registration_levels

__all__ = ["PairRegistration", "register_pair", "register_pair_starts"]


@dataclasses.dataclass(frozen=True)
class PairRegistration:
    """Result of :func:`register_pair`.

    Attributes:
        transform: ``(4, 4)`` float64 rigid source -> target (mm).
        fitness: fraction of the source's points within the finest correspondence distance of the target.
        rmse_mm: inlier point-to-point RMSE at that distance, mm.
        target_fitness: fraction of the target's points within that distance of the moved source (how
            much of the target the source explains: ~1 for a whole head onto one view of it).
    """

    transform: np.ndarray
    fitness: float
    rmse_mm: float
    target_fitness: float


def register_pair(
    source: PointCloud,
    target: PointCloud,
    init: np.ndarray | None = None,
    config: RegistrationConfig = RegistrationConfig(),  # noqa: B008 - frozen dataclass
) -> PairRegistration:
    """Rigid multi-scale point-to-plane ICP of ``source`` onto ``target`` (both with normals, mm) from
    ``init`` (``(4, 4)`` source -> target, default identity), the levels and robust kernel of
    :func:`register_sequence`; e.g. a reference mesh's vertices onto another capture's first frame.

    Raises:
        ValueError: a cloud with fewer than 16 confident points (naming it), or a non-rigid ``init``.
    """
    init = np.eye(4) if init is None else check_rigid(np.asarray(init, dtype=np.float64), "init")
    return register_pair_starts(source, target, [init], config)[0]


def register_pair_starts(
    source: PointCloud,
    target: PointCloud,
    starts: Sequence[np.ndarray],
    config: RegistrationConfig = RegistrationConfig(),  # noqa: B008 - frozen dataclass
    threads: int = 2,
) -> list[PairRegistration]:
    """:func:`register_pair` of ``source`` onto ``target`` from each of ``starts`` (``(4, 4)`` source ->
    target), in their order: the two clouds' ICP levels are built once, and the starts' ICPs run in
    ``threads`` threads (Open3D's ICP releases Python's lock), each ICP on its own thread
    (:func:`~polarface.geometry.open3d_library.serial_open3d`): the same transforms as
    :func:`register_pair` per start, bit for bit, on every run. The dynamic stage's alignment tries 13
    starts: on the demo, 7.7-10.1 s with :func:`register_pair` per start, 7.0-7.6 s with the levels built
    once, 5.6-6.2 s in 2 threads (2-core VM, docs/performance.md; measured when Open3D's own threads ran
    each ICP too).

    Raises:
        ValueError: as :func:`register_pair`; a non-rigid start names its index (``starts[k]``); ``threads``
            < 1.
    """
    if int(threads) < 1:
        raise ValueError(f"argument 'threads' must be >= 1; got {threads}")
    inits = [check_rigid(np.asarray(start, dtype=np.float64), f"starts[{k}]")
             for k, start in enumerate(starts)]
    source_levels, centre = registration_levels(source, None, config)
    if source_levels is None:
        raise ValueError("argument 'source' has fewer than 16 confident points to register")
    target_levels, _ = registration_levels(target, centre, config)
    if target_levels is None:
        raise ValueError("argument 'target' has fewer than 16 confident points to register")
    from open3d.pipelines import registration as reg

    shift = np.eye(4)
    shift[:3, 3] = centre

    def from_start(init: np.ndarray) -> PairRegistration:
        local_init = invert_rigid(shift) @ init @ shift
        local, fitness, rmse, _ = icp(source_levels, target_levels, local_init, config)
        reverse = reg.evaluate_registration(target_levels[-1], source_levels[-1], config.scales[-1][1],
                                            invert_rigid(local))
        return PairRegistration(shift @ local @ invert_rigid(shift), fitness, rmse, float(reverse.fitness))

    with serial_open3d():  # the same transforms on every run (polarface.geometry.open3d_library)
        if len(inits) <= 1 or int(threads) == 1:
            return [from_start(init) for init in inits]
        with ThreadPoolExecutor(max_workers=min(int(threads), len(inits)), thread_name_prefix="icp") as pool:
            return list(pool.map(from_start, inits))
