"""Unwrapping a capture read from a URL into an unwrap store at a URL (memory://): the same arrays as the
local run, resumed in place (object storage cannot rename the finished store)."""

from __future__ import annotations

import numpy as np
import pytest

from polarface.capture.store import CaptureStore
from polarface.geometry.mesh import load_mesh
from polarface.geometry.poses import load_poses
from polarface.simulate.sphere_capture import SphereCaptureConfig, make_sphere_capture
from polarface.texture import UnwrapConfig, UnwrapStore, unwrap_capture
from storage_fixtures import memory_keys, upload_tree

CONFIG = UnwrapConfig(texture_resolution=16, patch=8)
WHOLE = (slice(0, 16), slice(0, 16))


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    """``(local capture folder, mesh, poses, the local unwrap store)``."""
    root = tmp_path_factory.mktemp("sphere_url")
    info = make_sphere_capture(root, SphereCaptureConfig(texture_resolution=16, frames=3))
    mesh = load_mesh(info["ground_truth"] / "mesh_rest.obj")
    poses = load_poses(info["ground_truth"] / "static" / "poses.json")
    local = unwrap_capture(CaptureStore.open(info["capture"]), mesh, poses, root / "u.zarr", CONFIG,
                           progress=False)
    return info["capture"], mesh, poses, local


def _assert_same(store: UnwrapStore, reference: UnwrapStore) -> None:
    for got, expected in zip(store.read(*WHOLE), reference.read(*WHOLE), strict=True):
        np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(store.geometry().position, reference.geometry().position)
    assert [v.to_dict() for v in store.views] == [v.to_dict() for v in reference.views]
    assert store.done() == reference.done() and store.mean_i_sss() == reference.mean_i_sss()


def test_unwrap_from_and_to_a_url_matches_the_local_store(sphere, memory_url):
    capture, mesh, poses, local = sphere
    store = CaptureStore.open(str(upload_tree(capture, f"{memory_url}/capture")))
    url = f"{memory_url}/u.zarr"
    unwrap = unwrap_capture(store, mesh, poses, url, CONFIG, progress=False)
    assert unwrap.complete and str(unwrap.path) == url
    _assert_same(UnwrapStore.open(url), local)
    assert not [key for key in memory_keys(memory_url) if ".partial" in key or ".tmp-" in key]
    # an interrupted run (views 2.. lost, not complete) resumes in place at the URL
    writer = UnwrapStore.open(url, mode="a")
    writer.root.attrs["done"] = [0, 1]
    writer.root.attrs["complete"] = False
    writer.root["obs"][3] = 0.0
    resumed = unwrap_capture(store, mesh, poses, url, CONFIG, progress=False)
    assert resumed.complete
    _assert_same(resumed, local)


def test_missing_unwrap_store_at_a_url_is_named(memory_url):
    with pytest.raises(FileNotFoundError, match=f"unwrap store '{memory_url}/none.zarr' does not exist"):
        UnwrapStore.open(f"{memory_url}/none.zarr")
