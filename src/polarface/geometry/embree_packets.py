"""Shadow-ray occlusion in coherent packets of 8 rays, through the Embree 4 library that embreex ships.

embreex (the Embree binding :mod:`polarface.geometry.raycast` uses) answers one ray per call
(``rtcOccluded1``). A renderer's shadow rays come in runs that leave neighbouring pixels for one light,
and Embree traces such runs faster as packets flagged coherent (``rtcOccluded8`` with
``RTC_RAY_QUERY_FLAG_COHERENT``): a demo frame's 15.5 M shadow rays took 1.5-1.6 s instead of 2.2-2.4 s
(docs/geometry.md, "Shadow rays in packets"), with the same answer for every ray. The scene is robust
(``RTC_SCENE_FLAG_ROBUST``: Embree without its optimisations that reduce arithmetic accuracy): without
it, packets let rays through at edges and vertices where embreex's single rays are blocked (the sphere
test of ``tests/geometry/test_raycast.py``: 24 rays).

:class:`PacketScene` builds an Embree scene of the float32 triangles that embreex was given (the same
vertices, shifted and scaled as trimesh's wrapper does) in the same library (the one embreex loaded,
found next to its package) and answers occlusion queries with one compiled loop that fills each packet's
structure (``RTCRay8``: origins, ``tnear = 0``, directions, ``time = 0``, ``tfar``, ``mask = ~0``,
``id = flags = 0``; Embree sets ``tfar`` to ``-inf`` where the ray is blocked). Where the library cannot be
found or loaded, :func:`packet_scene` returns None and the caller keeps embreex's one-ray queries, which
give the same booleans (test).

The compiled loop takes Embree's function's address as an argument (:func:`_call_occluded8`), so numba
caches it on disk like the package's other kernels.
"""

from __future__ import annotations

import ctypes
import functools
import glob
import os
import weakref

import numba
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

__all__ = ["PacketScene", "packet_scene"]

_RTC_GEOMETRY_TYPE_TRIANGLE = 0
_RTC_BUFFER_TYPE_INDEX, _RTC_BUFFER_TYPE_VERTEX = 0, 1
_RTC_FORMAT_UINT3, _RTC_FORMAT_FLOAT3 = 0x5003, 0x9003
_RTC_RAY_QUERY_FLAG_COHERENT = 1
_RTC_SCENE_FLAG_ROBUST = 4
_RTC_FEATURE_FLAG_ALL = -1  # 0xffffffff as a C int


class _OccludedArguments(ctypes.Structure):
    """Embree 4's ``RTCOccludedArguments`` (``rtcore_ray.h``): what ``rtcInitOccludedArguments`` sets, with
    the coherent flag."""

    _fields_ = [
        ("flags", ctypes.c_int),
        ("feature_mask", ctypes.c_int),
        ("context", ctypes.c_void_p),
        ("filter", ctypes.c_void_p),
        ("occluded", ctypes.c_void_p),
        ("min_width_distance_factor", ctypes.c_float),
    ]


def _library_paths() -> list[str]:
    """Candidate files of the Embree 4 library that embreex loaded: auditwheel's ``embreex.libs``
    (Linux), delocate's ``embreex/.dylibs`` (macOS), the package folder (Windows)."""
    try:
        import embreex
    except ImportError:
        return []
    package = os.path.dirname(embreex.__file__)
    folders = (os.path.join(package, os.pardir, "embreex.libs"), os.path.join(package, ".dylibs"), package)
    patterns = ("libembree4*.so*", "libembree4*.dylib", "embree4*.dll")
    return sorted({path for folder in folders for pattern in patterns
                   for path in glob.glob(os.path.join(folder, pattern))})


@functools.lru_cache(maxsize=1)
def _embree() -> tuple[ctypes.CDLL, int] | None:
    """The Embree library with the functions' signatures set and one device of this process; None where it
    is not found or does not load."""
    for path in _library_paths():
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        handle = ctypes.c_size_t  # pointers as integers: the compiled loop passes array addresses
        lib.rtcNewDevice.restype, lib.rtcNewDevice.argtypes = handle, [ctypes.c_char_p]
        lib.rtcGetDeviceError.restype, lib.rtcGetDeviceError.argtypes = ctypes.c_int, [handle]
        lib.rtcNewScene.restype, lib.rtcNewScene.argtypes = handle, [handle]
        lib.rtcNewGeometry.restype, lib.rtcNewGeometry.argtypes = handle, [handle, ctypes.c_int]
        lib.rtcSetNewGeometryBuffer.restype = handle
        lib.rtcSetNewGeometryBuffer.argtypes = [handle, ctypes.c_int, ctypes.c_uint, ctypes.c_int,
                                                ctypes.c_size_t, ctypes.c_size_t]
        lib.rtcCommitGeometry.restype, lib.rtcCommitGeometry.argtypes = None, [handle]
        lib.rtcAttachGeometry.restype, lib.rtcAttachGeometry.argtypes = ctypes.c_uint, [handle, handle]
        lib.rtcReleaseGeometry.restype, lib.rtcReleaseGeometry.argtypes = None, [handle]
        lib.rtcCommitScene.restype, lib.rtcCommitScene.argtypes = None, [handle]
        lib.rtcReleaseScene.restype, lib.rtcReleaseScene.argtypes = None, [handle]
        lib.rtcSetSceneFlags.restype, lib.rtcSetSceneFlags.argtypes = None, [handle, ctypes.c_int]
        lib.rtcOccluded8.restype, lib.rtcOccluded8.argtypes = None, [handle, handle, handle, handle]
        device = lib.rtcNewDevice(None)
        if device:
            return lib, device
    return None


@intrinsic
def _call_occluded8(typingctx, function, valid, scene, ray, arguments):
    """Call ``rtcOccluded8(valid, scene, ray, arguments)`` through its address ``function``; every argument
    an address as an integer (the same registers as pointers in the C calling conventions of x86-64 and
    arm64). The address is an argument, not a constant, so the loop that calls this caches on disk."""
    signature = types.void(types.uintp, types.uintp, types.uintp, types.uintp, types.uintp)

    def codegen(context, builder, sig, args):
        word = context.get_value_type(types.uintp)
        function_type = ir.FunctionType(ir.VoidType(), [word] * 4)
        builder.call(builder.inttoptr(args[0], function_type.as_pointer()), args[1:])
        return context.get_dummy_value()

    return signature, codegen


@numba.njit(cache=True, nogil=True)
def _occluded(function, scene, arguments, origins32, directions32, lengths32, blocked):  # pragma: no cover
    """Fill ``blocked`` ``(R,)`` from ``rtcOccluded8`` (at address ``function``) of the rays, 8 at a time."""
    # one buffer holds the valid mask (8 int32) and the RTCRay8 (12 x 8 words), both 32-byte aligned
    buffer = np.zeros(8 + 96 + 8, np.float32)
    skip = (-(buffer.ctypes.data // 4)) % 8
    valid = buffer[skip : skip + 8].view(np.int32)
    ray = buffer[skip + 8 : skip + 104]
    words = ray.view(np.uint32)
    for k in range(8):  # the fields every ray shares (Embree writes only tfar)
        ray[24 + k], ray[56 + k] = 0.0, 0.0  # tnear, time
        words[72 + k], words[80 + k], words[88 + k] = 0xFFFFFFFF, 0, 0  # mask, id, flags
    count = origins32.shape[0]
    for start in range(0, count, 8):
        size = min(8, count - start)
        for k in range(8):
            if k < size:
                r = start + k
                ray[k], ray[8 + k], ray[16 + k] = origins32[r, 0], origins32[r, 1], origins32[r, 2]
                ray[32 + k], ray[40 + k] = directions32[r, 0], directions32[r, 1]
                ray[48 + k] = directions32[r, 2]
                ray[64 + k] = lengths32[r]
                valid[k] = -1
            else:
                ray[64 + k] = 0.0
                valid[k] = 0
        _call_occluded8(function, valid.ctypes.data, scene, ray.ctypes.data, arguments)
        for k in range(size):
            blocked[start + k] = ray[64 + k] == -np.inf


class PacketScene:
    """An Embree scene of float32 triangles answering occlusion queries in coherent packets of 8 rays.

    Args:
        vertices32: ``(V, 3)`` float32 vertices, in the frame of the rays (embreex's shifted, scaled one).
        faces: ``(F, 3)`` integer vertex indices.

    Raises:
        RuntimeError: Embree reports an error building the scene (the message gives its code).
    """

    def __init__(self, vertices32: np.ndarray, faces: np.ndarray) -> None:
        lib, device = _embree()  # type: ignore[misc]
        vertices32 = np.ascontiguousarray(vertices32, np.float32)
        faces32 = np.ascontiguousarray(faces, np.uint32)
        scene = lib.rtcNewScene(device)
        lib.rtcSetSceneFlags(scene, _RTC_SCENE_FLAG_ROBUST)
        geometry = lib.rtcNewGeometry(device, _RTC_GEOMETRY_TYPE_TRIANGLE)
        for kind, fmt, array in ((_RTC_BUFFER_TYPE_VERTEX, _RTC_FORMAT_FLOAT3, vertices32),
                                 (_RTC_BUFFER_TYPE_INDEX, _RTC_FORMAT_UINT3, faces32)):
            target = lib.rtcSetNewGeometryBuffer(geometry, kind, 0, fmt, 12, len(array))
            if target:  # else Embree's error is reported below
                ctypes.memmove(target, array.ctypes.data, array.nbytes)
        lib.rtcCommitGeometry(geometry)
        lib.rtcAttachGeometry(scene, geometry)
        lib.rtcReleaseGeometry(geometry)
        lib.rtcCommitScene(scene)
        error = lib.rtcGetDeviceError(device)
        self._finalizer = weakref.finalize(self, lib.rtcReleaseScene, scene)
        if error:
            self._finalizer()
            raise RuntimeError(f"Embree could not build the shadow-ray scene (RTCError {error})")
        self._scene = scene
        self._function = ctypes.cast(lib.rtcOccluded8, ctypes.c_void_p).value
        self._arguments = _OccludedArguments(_RTC_RAY_QUERY_FLAG_COHERENT, _RTC_FEATURE_FLAG_ALL)

    def occluded(self, origins32: np.ndarray, directions32: np.ndarray, lengths32: np.ndarray) -> np.ndarray:
        """``(R,)`` bool: True where the ray ``origin + t direction`` meets a triangle for ``0 <= t <=
        length`` (``(R, 3)`` float32 origins and directions, ``(R,)`` float32 lengths; Embree's
        ``rtcOccluded`` semantics, as embreex's ``query='OCCLUDED'``). Consecutive rays should be
        neighbours (one light, neighbouring pixels): they share a packet."""
        origins32 = np.ascontiguousarray(origins32, np.float32)
        directions32 = np.ascontiguousarray(directions32, np.float32)
        lengths32 = np.ascontiguousarray(lengths32, np.float32)
        if origins32.ndim != 2 or origins32.shape[1] != 3 or directions32.shape != origins32.shape:
            raise ValueError(f"arguments 'origins32' and 'directions32' must both be (R, 3); got "
                             f"{origins32.shape}, {directions32.shape}")
        if lengths32.shape != origins32.shape[:1]:
            raise ValueError(f"argument 'lengths32' must be ({origins32.shape[0]},); got {lengths32.shape}")
        blocked = np.zeros(origins32.shape[0], bool)
        _occluded(self._function, self._scene, ctypes.addressof(self._arguments), origins32, directions32,
                  lengths32, blocked)
        return blocked


def packet_scene(vertices32: np.ndarray, faces: np.ndarray) -> PacketScene | None:
    """A :class:`PacketScene` of the triangles, or None where the Embree library is not available (or the
    environment variable ``POLARFACE_EMBREE_PACKETS`` is ``0``): the caller then asks embreex one ray at a
    time, for the same answers."""
    if os.environ.get("POLARFACE_EMBREE_PACKETS", "1") == "0" or _embree() is None:
        return None
    return PacketScene(vertices32, faces)
