"""polarface.geometry.open3d_library: the one import of Open3D and the system libraries it needs."""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from polarface.geometry.open3d_library import DEBIAN_PACKAGES, SYSTEM_LIBRARIES, open3d_module

# The C and C++ runtime: on every Linux that runs a Python wheel.
RUNTIME = {"libc.so.6", "libm.so.6", "libstdc++.so.6", "libgcc_s.so.1", "ld-linux-x86-64.so.2",
           "libpthread.so.0", "libdl.so.2", "librt.so.1"}


def _needed(path: Path) -> set[str]:
    """The DT_NEEDED entries of a shared object (``readelf -d``)."""
    out = subprocess.run(["readelf", "-d", str(path)], check=True, capture_output=True, text=True).stdout
    return {line.split("[", 1)[1].split("]", 1)[0] for line in out.splitlines() if "(NEEDED)" in line}


def test_the_module_is_open3d_with_the_pipelines_the_geometry_stage_uses():
    o3d = open3d_module()
    assert o3d.__name__ == "open3d"
    assert hasattr(o3d.pipelines.registration, "registration_icp")
    assert hasattr(o3d.t.geometry, "RaycastingScene")


def test_a_missing_library_is_reported_with_the_packages_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "open3d", None)  # the import machinery then raises ImportError
    with pytest.raises(ImportError, match=r"Open3D .* could not be loaded: .*apt-get install libusb-1.0-0"):
        open3d_module()


@pytest.mark.skipif(sys.platform != "linux", reason="ELF shared objects: Linux wheels only")
def test_every_system_library_open3d_links_is_named():
    """Oracle: the wheel's own shared objects. A new Open3D release that links another system library
    fails here, not on a user's bare machine."""
    if shutil.which("readelf") is None:
        if os.environ.get("CI"):
            pytest.fail("readelf (binutils) is not installed")
        pytest.skip("readelf (binutils) is not installed")
    package = Path(importlib.util.find_spec("open3d").origin).parent
    objects = [p for p in package.rglob("*.so*") if p.is_file() and "_ops" not in p.name]
    bundled = {p.name for p in objects}
    needed = set().union(*(_needed(p) for p in objects if p.name.startswith(("pybind", "libOpen3D"))))
    system = needed - bundled - RUNTIME
    assert system, "readelf found no system library at all: the parsing is broken"
    assert system <= set(SYSTEM_LIBRARIES), sorted(system - set(SYSTEM_LIBRARIES))
    assert set(DEBIAN_PACKAGES) == set(SYSTEM_LIBRARIES.values())


@pytest.mark.skipif(shutil.which("dpkg") is None, reason="the package names are Debian's: checked with dpkg")
def test_each_library_comes_from_the_package_named():
    """Oracle: dpkg's own record of which installed package owns each library file."""
    for soname, package in SYSTEM_LIBRARIES.items():
        owners = subprocess.run(["dpkg", "-S", f"*/{soname}"], capture_output=True, text=True).stdout
        assert owners, f"{soname}: no installed package owns it"
        assert {line.split(":", 1)[0] for line in owners.splitlines()} == {package}, owners
