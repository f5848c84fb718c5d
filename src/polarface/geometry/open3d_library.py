"""Open3D, the one place it is imported from (Poisson meshing, ICP registration, closest points).

Open3D's Linux wheel links system libraries that a minimal machine may lack (seen: ``libusb-1.0.so.0``
on a bare Debian 12 with Python only). :func:`open3d_module` turns the loader's bare ``ImportError`` into
one that names the Debian packages to install; ``./run.sh`` installs them itself when it runs as root
(it reads :data:`DEBIAN_PACKAGES`).

Repeatable registrations: Open3D's parallel loops run on oneTBB, whose reductions (the ICP's
``J^T J`` and residual sums, the correspondence sets, RANSAC's trials) combine the threads' partial
results in the order the threads finish, so with several threads the same ICP differs from run to run in
the last bits (measured on the tiny preset: poses ~1e-12 mm apart, enough to change the unwrapped
observations and, through the polarimetric fit, the maps). :func:`serial_open3d` limits Open3D to the
calling thread while a registration runs; the registrations get their parallelism from Python threads
instead (two walks, two ICP starts at a time), each of which runs its own ICP serially.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from types import ModuleType

# The system libraries that Open3D's shared objects list as needed (``readelf -d``), beyond the ones its
# wheel bundles and the C/C++ runtime, with the Debian/Ubuntu package of each.
SYSTEM_LIBRARIES: dict[str, str] = {
    "libusb-1.0.so.0": "libusb-1.0-0",
    "libudev.so.1": "libudev1",
    "libEGL.so.1": "libegl1",
    "libGL.so.1": "libgl1",
    "libX11.so.6": "libx11-6",
    "libidn2.so.0": "libidn2-0",
}
DEBIAN_PACKAGES: tuple[str, ...] = tuple(dict.fromkeys(SYSTEM_LIBRARIES.values()))


def open3d_module() -> ModuleType:
    """The ``open3d`` module.

    Raises:
        ImportError: Open3D is not installed, or a system library it links is missing; the message names
            the library the loader reported and the packages that provide it.
    """
    try:
        import open3d
    except ImportError as exc:
        raise ImportError(
            f"Open3D (used by the geometry stage) could not be loaded: {exc}. Its wheel links system "
            f"libraries a minimal machine may lack; on Debian or Ubuntu install them with "
            f"'apt-get install {' '.join(DEBIAN_PACKAGES)}' (./run.sh does this when run as root)"
        ) from exc
    return open3d


_SERIAL_LOCK = threading.Lock()
_serial_holders = 0
_limit_before = 0


@contextlib.contextmanager
def serial_open3d() -> Iterator[ModuleType]:
    """Open3D (the module) with its oneTBB parallelism limited to the calling thread while inside
    (``open3d.utility.set_max_threads(1)``), so that its reductions are summed in one fixed order and
    the same inputs give the same bits on every run (module docstring).

    The limit is process-wide: it is counted over the threads inside (the two walks of a registration
    hold it at once) and the limit found on the first entry is put back when the last one leaves. Open3D
    calls of other threads meanwhile run serially too; several threads inside each run their own calls
    at once. Open3D before 0.20 (OpenMP, no ``set_max_threads``) is left as it is: its registrations are
    not repeatable bit for bit.
    """
    global _serial_holders, _limit_before
    o3d = open3d_module()
    if not hasattr(o3d.utility, "set_max_threads"):  # Open3D < 0.20 (OpenMP): no process-wide limit
        yield o3d
        return
    with _SERIAL_LOCK:
        if _serial_holders == 0:
            _limit_before = int(o3d.utility.get_max_threads())
            o3d.utility.set_max_threads(1)
        _serial_holders += 1
    try:
        yield o3d
    finally:
        with _SERIAL_LOCK:
            _serial_holders -= 1
            if _serial_holders == 0:
                o3d.utility.set_max_threads(_limit_before)
