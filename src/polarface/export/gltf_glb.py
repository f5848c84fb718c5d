"""A glTF 2.0 binary (GLB) container written with numpy and struct: one JSON chunk, one BIN chunk.

Layout (glTF 2.0 specification, "GLB File Format Specification"): a 12-byte header (magic ``glTF``,
version 2, total length, little-endian uint32), then chunks of ``(length, type, data)``: the JSON chunk
(type ``JSON``, padded with spaces to 4 bytes) and the binary chunk (type ``BIN\\0``, padded with
zeros). Every buffer view starts on a 4-byte boundary of the BIN chunk, so every accessor's component
type is aligned. Used by :mod:`polarface.export.gltf` (``docs/export.md``, "glTF 2.0").
"""

from __future__ import annotations

import json
import struct
from typing import Any

import numpy as np

__all__ = ["ARRAY_BUFFER", "ELEMENT_ARRAY_BUFFER", "GlbBuilder"]

GLB_MAGIC = 0x46546C67  # "glTF"
GLB_VERSION = 2
CHUNK_JSON = 0x4E4F534A  # "JSON"
CHUNK_BIN = 0x004E4942  # "BIN\0"
#: bufferView targets of vertex attributes and of indices.
ARRAY_BUFFER = 34962
ELEMENT_ARRAY_BUFFER = 34963

_COMPONENT_TYPES = {
    np.dtype(np.int8): 5120,
    np.dtype(np.uint8): 5121,
    np.dtype(np.int16): 5122,
    np.dtype(np.uint16): 5123,
    np.dtype(np.uint32): 5125,
    np.dtype(np.float32): 5126,
}
_ACCESSOR_TYPES = {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4"}


def _padded(data: bytes, fill: bytes) -> bytes:
    return data + fill * (-len(data) % 4)


class GlbBuilder:
    """Collects binary data (buffer views, accessors, images) and encodes a GLB around a glTF document.

    Usage: ``accessor = builder.add_accessor(array, ARRAY_BUFFER)``, ``image = builder.add_image(png,
    "image/png", name)``; put the returned indices into the document's meshes and textures, then
    ``builder.encode(document)`` fills ``buffers``, ``bufferViews``, ``accessors`` and ``images``.
    """

    def __init__(self) -> None:
        self._blob = bytearray()
        self.buffer_views: list[dict[str, Any]] = []
        self.accessors: list[dict[str, Any]] = []
        self.images: list[dict[str, Any]] = []

    def add_view(self, data: bytes, target: int | None = None) -> int:
        """Append ``data`` (starting 4-byte aligned) as a buffer view; returns its index."""
        self._blob.extend(b"\0" * (-len(self._blob) % 4))
        view: dict[str, Any] = {"buffer": 0, "byteOffset": len(self._blob), "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        self._blob.extend(data)
        self.buffer_views.append(view)
        return len(self.buffer_views) - 1

    def add_accessor(self, array: np.ndarray, target: int, *, bounds: bool = False, name: str = "") -> int:
        """An accessor of ``array`` ``(count,)`` or ``(count, k)``, k <= 4, of a glTF component type
        (int8/uint8/int16/uint16/uint32/float32), tightly packed in its own buffer view.

        Args:
            target: :data:`ARRAY_BUFFER` (vertex attributes) or :data:`ELEMENT_ARRAY_BUFFER` (indices).
            bounds: also write ``min`` / ``max`` per component (required for POSITION).
        """
        array = np.ascontiguousarray(array)
        if array.dtype not in _COMPONENT_TYPES:
            raise ValueError(f"accessor '{name}': dtype {array.dtype} is not a glTF component type")
        width = 1 if array.ndim == 1 else array.shape[1]
        if array.ndim not in (1, 2) or width not in _ACCESSOR_TYPES or array.shape[0] == 0:
            raise ValueError(f"accessor '{name}': shape must be (count,) or (count, 1..4); got {array.shape}")
        accessor: dict[str, Any] = {
            "bufferView": self.add_view(array.astype(array.dtype.newbyteorder("<")).tobytes(), target),
            "componentType": _COMPONENT_TYPES[array.dtype],
            "count": int(array.shape[0]),
            "type": _ACCESSOR_TYPES[width],
        }
        if name:
            accessor["name"] = name
        if bounds:
            flat = array.reshape(array.shape[0], width)
            cast = float if array.dtype.kind == "f" else int
            accessor["min"] = [cast(v) for v in flat.min(axis=0)]
            accessor["max"] = [cast(v) for v in flat.max(axis=0)]
        self.accessors.append(accessor)
        return len(self.accessors) - 1

    def add_image(self, data: bytes, mime_type: str, name: str) -> int:
        """An image stored in the BIN chunk (``bufferView`` + ``mimeType``); returns its index."""
        self.images.append({"name": name, "bufferView": self.add_view(data), "mimeType": mime_type})
        return len(self.images) - 1

    def encode(self, document: dict[str, Any]) -> bytes:
        """The GLB bytes of ``document`` with this builder's buffers, views, accessors and images."""
        binary = _padded(bytes(self._blob), b"\0")
        document = {
            **document,
            "buffers": [{"byteLength": len(binary)}],
            "bufferViews": self.buffer_views,
            "accessors": self.accessors,
        }
        if self.images:
            document["images"] = self.images
        text = _padded(json.dumps(document, separators=(",", ":"), allow_nan=False).encode("utf-8"), b" ")
        total = 12 + 8 + len(text) + 8 + len(binary)
        return b"".join(
            [
                struct.pack("<III", GLB_MAGIC, GLB_VERSION, total),
                struct.pack("<II", len(text), CHUNK_JSON),
                text,
                struct.pack("<II", len(binary), CHUNK_BIN),
                binary,
            ]
        )
