"""Whole chunks of a local zarr v3 array, read and decoded directly.

zarr v3 reads every chunk through its asynchronous codec pipeline. For the small chunks of the unwrap
store (``(1, 64, 64, 3, 3)`` float32, 147 kB decoded) that costs about 0.6 ms per chunk on a 2-core
laptop-class CPU, of which zstd's decoding is 0.14 ms (docs/performance.md, "Removed waste"). A haloed
texture patch reads hundreds of such chunks. :class:`LocalChunkReader` reads a chunk's file and decodes
it itself, for the one layout where that is exactly what zarr does: a local folder (zarr's
``LocalStore``), a regular chunk grid, no sharding, and the codecs ``bytes`` (little-endian or none)
then ``zstd``. Everything else (object storage, other codecs) is refused by :meth:`for_array`, and the
caller reads through zarr. A chunk that was never written (zarr leaves out chunks that hold only the fill
value) is the fill value, as in zarr. The decoded values equal zarr's (tests/io/test_zarr_chunks.py).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

__all__ = ["LocalChunkReader"]


class LocalChunkReader:
    """Reads whole chunks of one eligible array (module docstring); build it with :meth:`for_array`."""

    def __init__(self, folder: Path, metadata, chunk_shape: tuple[int, ...], dtype: np.dtype) -> None:
        import numcodecs

        self.folder = folder
        self.metadata = metadata
        self.chunk_shape = chunk_shape
        self.dtype = dtype
        self._zstd = numcodecs.Zstd()

    @classmethod
    def for_array(cls, array) -> LocalChunkReader | None:
        """The reader of the zarr array ``array``, or None when its store, chunk grid or codecs are not
        the layout this reader decodes (read it through zarr then)."""
        import zarr
        from zarr.codecs import BytesCodec, ZstdCodec
        from zarr.core.chunk_grids import RegularChunkGrid

        metadata = getattr(array, "metadata", None)
        store = getattr(array, "store", None)
        if getattr(metadata, "zarr_format", None) != 3 or not isinstance(store, zarr.storage.LocalStore):
            return None
        codecs = tuple(metadata.codecs)
        if (len(codecs) != 2 or not isinstance(codecs[0], BytesCodec) or not isinstance(codecs[1], ZstdCodec)
                or not isinstance(metadata.chunk_grid, RegularChunkGrid)):
            return None
        dtype = np.dtype(array.dtype)
        endian = getattr(codecs[0].endian, "value", codecs[0].endian)
        if dtype.itemsize > 1 and (endian != "little" or sys.byteorder != "little"):
            return None
        return cls(Path(store.root) / array.path, metadata, tuple(metadata.chunk_grid.chunk_shape), dtype)

    def read(self, coords: tuple[int, ...]) -> np.ndarray:
        """The decoded chunk at chunk-grid position ``coords`` (read-only, of the full chunk shape: an
        edge chunk holds the fill value beyond the array, as stored)."""
        path = self.folder / self.metadata.encode_chunk_key(tuple(int(c) for c in coords))
        try:
            encoded = path.read_bytes()
        except FileNotFoundError:
            chunk = np.full(self.chunk_shape, self.metadata.fill_value, self.dtype)
        else:
            chunk = np.frombuffer(self._zstd.decode(encoded), self.dtype).reshape(self.chunk_shape)
        chunk.flags.writeable = False
        return chunk
