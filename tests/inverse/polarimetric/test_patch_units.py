"""The static fit's patches as executor units (inverse/polarimetric/patch_units.py): the wavefront
schedule runs overlapping patches in row-major order and never two overlapping patches at once; the
fit (local executor) gives the maps and loss curve of the row-major patch loop it replaced, bit for bit;
a unit run twice gives the same result; a worker process keeps one cached store for its units (the same
results as uncached reads, opened again for a store replaced on disk); a run stopped in the middle of a
front, or a checkpoint of the row-major loop, resumes to the same maps.

A synthetic sphere capture with a 48 x 48 atlas and 8-texel patches: a 6 x 6 patch grid (32 patches with
atlas texels), 14 fronts of up to 3 patches.
"""

from __future__ import annotations

import dataclasses
import itertools
import shutil

import numpy as np
import pytest

from polarface.inverse.polarimetric import PolarimetricConfig, fit_polarimetric, patch_units
from polarface.inverse.polarimetric.patch_units import (
    PatchUnit,
    haloed_slices,
    patch_fronts,
    patch_waits,
    run_patch_unit,
)
from polarface.texture import UnwrapStore
from polarimetric_reference import row_major_fit, sphere_unwrap

RES, PATCH = 48, 8
CONFIG = PolarimetricConfig(iterations=8, patch=PATCH)


def _grid(height: int, width: int, side: int, missing=()) -> list[tuple[slice, slice]]:
    """Row-major patches of a ``height x width`` texture, without the grid cells in ``missing``."""
    return [(slice(r, min(r + side, height)), slice(c, min(c + side, width)))
            for r in range(0, height, side) for c in range(0, width, side)
            if (r // side, c // side) not in missing]


def _overlap(a, b, halo: int, resolution) -> bool:
    (ra, ca, _), (rb, cb, _) = haloed_slices(*a, halo, resolution), haloed_slices(*b, halo, resolution)
    return ra.start < rb.stop and rb.start < ra.stop and ca.start < cb.stop and cb.start < ca.stop


@pytest.mark.parametrize("side,halo", [(8, 4), (10, 3), (9, 4), (8, 0)])
def test_fronts_order_overlapping_patches_row_major_and_never_run_two_at_once(side, halo):
    resolution = (53, 70)
    patches = _grid(*resolution, side, missing={(0, 0), (2, 3), (4, 1)})
    fronts = patch_fronts(patches, side, halo)
    front_of = {index: t for t, front in enumerate(fronts) for index in front}
    assert sorted(front_of) == list(range(len(patches))) and all(f == sorted(f) for f in fronts)
    for a, b in itertools.combinations(range(len(patches)), 2):  # a before b in row-major order
        if _overlap(patches[a], patches[b], halo, resolution):
            assert front_of[a] < front_of[b], (patches[a], patches[b])
    assert max(len(front) for front in fronts) >= 3  # there is parallelism to use


@pytest.mark.parametrize("side,halo", [(8, 4), (10, 3), (9, 4), (8, 0)])
def test_a_patch_waits_for_the_earlier_patches_whose_regions_overlap_its_own(side, halo):
    resolution = (53, 70)
    patches = _grid(*resolution, side, missing={(0, 0), (2, 3), (4, 1)})
    waits = patch_waits(patches, side, halo)
    for b in range(len(patches)):
        overlapping = {a for a in range(b) if _overlap(patches[a], patches[b], halo, resolution)}
        assert set(waits[b]) == overlapping, patches[b]


def test_fronts_fall_back_to_row_major_order_when_halos_two_patches_apart_overlap():
    patches = _grid(40, 40, 7, missing={(1, 1)})
    assert patch_fronts(patches, 7, 4) == [[i] for i in range(len(patches))]
    assert patch_waits(patches, 7, 4) == [[]] + [[i] for i in range(len(patches) - 1)]
    with pytest.raises(ValueError, match="not on the 8 grid"):
        patch_fronts([(slice(0, 8), slice(3, 11))], 8, 4)


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    """``(unwrap store, straight fit)`` of the synthetic sphere."""
    unwrap = sphere_unwrap(tmp_path_factory.mktemp("patch_units"), RES, PATCH)
    return unwrap, fit_polarimetric(unwrap, CONFIG, progress=False, threads=1)


def _assert_same_fit(fit, maps, curve) -> None:
    different = [name for name in maps if not np.array_equal(fit.maps[name], maps[name])]
    assert not different, f"{different} differ"
    assert fit.loss_curve == curve


def test_the_wavefront_gives_the_maps_of_the_row_major_loop(sphere):
    unwrap, fit = sphere
    assert fit.patches == 32 and len(fit.fronts) == 14 and len(fit.units) == 32  # 4 corners: no atlas texel
    assert all(unit["seconds"] > 0 and unit["node_id"] is None for unit in fit.units.values())
    _assert_same_fit(fit, *row_major_fit(unwrap, CONFIG))


def _unit(unwrap: UnwrapStore, index: int) -> PatchUnit:
    rows, cols = list(unwrap.patches(PATCH))[index]
    hrows, hcols, _ = haloed_slices(rows, cols, CONFIG.halo, unwrap.resolution)
    from polarface.inverse.polarimetric import initial_raw

    raw = {k: v[hrows, hcols] for k, v in initial_raw(unwrap.resolution, CONFIG).items()}
    fitting = [i for i, v in enumerate(unwrap.views) if not v.held_out]
    return PatchUnit(str(unwrap.path), index, rows, cols, CONFIG, unwrap.mean_i_sss(fitting), "cpu", "auto",
                     1, raw, np.zeros(raw["eta"].shape[:2], bool))


def test_a_unit_run_twice_gives_the_same_result_and_changes_nothing_it_was_given(sphere):
    unwrap, _ = sphere
    unit = _unit(unwrap, 14)
    given = {k: v.copy() for k, v in unit.raw.items()}
    first, second = run_patch_unit(unit), run_patch_unit(unit)
    assert first.samples > 0 and first.started.all() and len(first.curve) > CONFIG.iterations
    for name in first.interior:
        assert np.array_equal(first.interior[name], second.interior[name])
    for name in first.starts:
        assert np.array_equal(first.starts[name], second.starts[name])
    assert first.curve == second.curve
    assert all(np.array_equal(unit.raw[k], given[k]) for k in given)


def test_a_worker_keeps_one_cached_store_and_reopens_a_replaced_one(sphere, tmp_path):
    unwrap, _ = sphere
    path = tmp_path / "unwrap.zarr"
    shutil.copytree(unwrap.path, path)
    unit = dataclasses.replace(_unit(unwrap, 14), unwrap=str(path))
    neighbour = dataclasses.replace(_unit(unwrap, 15), unwrap=str(path))
    uncached = [run_patch_unit(dataclasses.replace(u, config=dataclasses.replace(CONFIG, unwrap_cache_mb=0)))
                for u in (unit, neighbour)]
    patch_units._HELD.clear()
    cached = [run_patch_unit(u) for u in (unit, neighbour)]  # outside shared_unwrap: as in a worker
    held = patch_units._HELD["store"][1]
    counts = held.cache_counts
    assert counts["hits"] > 0 and counts["misses"] > 0  # the neighbour reused chunks the first decoded
    for a, b in zip(uncached, cached, strict=True):
        assert all(np.array_equal(a.interior[k], b.interior[k]) for k in a.interior)
        assert a.curve == b.curve
    run_patch_unit(unit)
    assert patch_units._HELD["store"][1] is held  # same store: kept
    shutil.rmtree(path)
    shutil.copytree(unwrap.path, path)  # written again at the same path
    run_patch_unit(unit)
    assert patch_units._HELD["store"][1] is not held
    patch_units._HELD.clear()


def test_a_run_stopped_mid_front_resumes_to_the_same_maps(sphere, tmp_path):
    unwrap, straight = sphere
    checkpoint = tmp_path / "fit.npz"
    first = fit_polarimetric(unwrap, CONFIG, progress=False, threads=1, checkpoint=checkpoint,
                             stop_after_patches=10)
    assert not first.complete
    with np.load(checkpoint) as saved:
        done, folded = sorted(int(i) for i in saved["done"]), int(saved["curve_folded"])
        pending = [int(i) for i in saved["pending_index"]]
    assert len(done) == 10 and done != list(range(10))  # not a row-major prefix: fronts, one cut in two
    assert pending == [i for i in done if i >= folded] and folded < 10
    resumed = fit_polarimetric(unwrap, CONFIG, progress=False, threads=1, checkpoint=checkpoint)
    assert resumed.complete and sorted(resumed.units, key=int) == [str(i) for i in range(32)]
    assert resumed.sample_count < straight.sample_count  # only the patches fitted after the resume
    _assert_same_fit(resumed, straight.maps, straight.loss_curve)


def test_a_checkpoint_of_the_row_major_loop_resumes_to_the_same_maps(sphere, tmp_path):
    unwrap, straight = sphere
    checkpoint = tmp_path / "fit.npz"
    fit_polarimetric(unwrap, CONFIG, progress=False, threads=1, checkpoint=checkpoint, stop_after_patches=2)
    with np.load(checkpoint) as saved:  # the old format: no per-patch curves, no placements
        old = {k: saved[k] for k in saved.files
               if k not in ("curve_folded", "pending_index", "pending_lengths", "pending_curve", "units")}
    assert list(old["done"]) == [0, 1]
    np.savez(checkpoint, **old)
    resumed = fit_polarimetric(unwrap, CONFIG, progress=False, threads=1, checkpoint=checkpoint)
    _assert_same_fit(resumed, straight.maps, straight.loss_curve)
