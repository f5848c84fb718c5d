"""Whole chunks of a local zarr v3 array, read and written directly.

zarr v3 reads and writes every chunk through its asynchronous codec pipeline. For the small chunks of the
unwrap store (``(1, 64, 64, 3, 3)`` float32, 147 kB decoded) that costs about 0.6 ms per chunk read on a
2-core laptop-class CPU, of which zstd's decoding is 0.14 ms, and about 0.7 ms per chunk written
(docs/performance.md, "Removed waste"). A haloed texture patch reads hundreds of such chunks, and every
unwrapped view writes 192. :class:`LocalChunks` reads a chunk's file and decodes it, or encodes it and
writes its file, itself, for the one layout where that is exactly what zarr does: a local folder (zarr's
``LocalStore``), a regular chunk grid, no sharding, and the codecs ``bytes`` (little-endian or none) then
``zstd``. Everything else (object storage, other codecs) is refused by :meth:`LocalChunks.for_array`, and
the caller goes through zarr.

As in zarr: a chunk that was never written (zarr leaves out chunks that hold only the fill value) reads
as the fill value; a chunk of fill values only is not written (its file is removed) unless the array's
``write_empty_chunks`` is set; edge chunks are stored at the full chunk shape, padded with the fill
value; a file is written under a temporary name and renamed. Chunks written here read back through zarr
unchanged, and chunks read here equal zarr's reads (tests/io/test_zarr_chunks.py).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from polarface.io.atomic import atomic_path

__all__ = ["LocalChunks"]


class LocalChunks:
    """Reads and writes whole chunks of one eligible array (module docstring); build it with
    :meth:`for_array`."""

    def __init__(self, folder: Path, metadata, dtype: np.dtype, write_empty: bool) -> None:
        import numcodecs

        zstd = metadata.codecs[1]
        self.folder = folder
        self.metadata = metadata
        self.chunk_shape = tuple(metadata.chunk_grid.chunk_shape)
        self.dtype = dtype
        self.write_empty = write_empty
        self._zstd = numcodecs.Zstd(level=int(zstd.level), checksum=bool(zstd.checksum))

    @classmethod
    def for_array(cls, array) -> LocalChunks | None:
        """The chunks of the zarr array ``array``, or None when its store, chunk grid or codecs are not
        the layout handled here (go through zarr then)."""
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
        write_empty = bool(array.config.write_empty_chunks)
        return cls(Path(store.root) / array.path, metadata, dtype, write_empty)

    def _path(self, coords: tuple[int, ...]) -> Path:
        return self.folder / self.metadata.encode_chunk_key(tuple(int(c) for c in coords))

    def read(self, coords: tuple[int, ...]) -> np.ndarray:
        """The decoded chunk at chunk-grid position ``coords`` (read-only, of the full chunk shape: an
        edge chunk holds the fill value beyond the array, as stored)."""
        try:
            encoded = self._path(coords).read_bytes()
        except FileNotFoundError:
            chunk = np.full(self.chunk_shape, self.metadata.fill_value, self.dtype)
        else:
            chunk = np.frombuffer(self._zstd.decode(encoded), self.dtype).reshape(self.chunk_shape)
        chunk.flags.writeable = False
        return chunk

    def write(self, coords: tuple[int, ...], values: np.ndarray) -> None:
        """Store ``values`` as the chunk at ``coords``: the full chunk shape, or less at the array's edge
        (padded with the fill value); cast to the array's dtype.

        Raises:
            ValueError: ``values`` larger than a chunk or of another number of dimensions.
        """
        values = np.asarray(values)
        if values.ndim != len(self.chunk_shape) or any(
                n > c for n, c in zip(values.shape, self.chunk_shape, strict=True)):
            raise ValueError(f"argument 'values' must fit a chunk {self.chunk_shape}; got {values.shape}")
        fill = self.metadata.fill_value
        chunk = np.full(self.chunk_shape, fill, self.dtype)
        chunk[tuple(slice(0, n) for n in values.shape)] = values
        path = self._path(coords)
        if not self.write_empty and _only_fill(chunk, fill):
            path.unlink(missing_ok=True)
            return
        encoded = self._zstd.encode(chunk)
        with atomic_path(path) as tmp:
            Path(tmp).write_bytes(encoded)


def _only_fill(chunk: np.ndarray, fill) -> bool:
    """Whether every value of ``chunk`` is the fill value (NaN equal to a NaN fill; ``-0.0`` equal to
    ``0.0``), as ``np.array_equal(chunk, full_like(chunk, fill), equal_nan=...)`` without the copy."""
    if chunk.dtype.kind in "fc" and np.isnan(fill):
        return bool(np.isnan(chunk).all())
    if fill == 0:
        return not chunk.any()
    return bool((chunk == fill).all())
