"""Open3D, the one place it is imported from (Poisson meshing, ICP registration, closest points).

Open3D's Linux wheel links system libraries that a minimal machine may lack (seen: ``libusb-1.0.so.0``
on a bare Debian 12 with Python only). :func:`open3d_module` turns the loader's bare ``ImportError`` into
one that names the Debian packages to install; ``./run.sh`` installs them itself when it runs as root
(it reads :data:`DEBIAN_PACKAGES`).
"""

from __future__ import annotations

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
