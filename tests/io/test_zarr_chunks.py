"""Direct chunk reads of local zarr v3 arrays (io/zarr_chunks.py): every chunk equals zarr's own read of
it (chunks straddling the array's edge, chunks never written, float and bool arrays), and arrays whose
store or codecs are another layout are refused (read through zarr)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import zarr
from zarr.codecs import BloscCodec, BytesCodec, GzipCodec, ZstdCodec

from polarface.io.zarr_chunks import LocalChunkReader


def _chunks_equal_zarrs(array, reader: LocalChunkReader) -> None:
    grid = [range(-(-size // chunk)) for size, chunk in zip(array.shape, array.chunks, strict=True)]
    for coords in itertools.product(*grid):
        window = tuple(slice(c * n, min((c + 1) * n, size))
                       for c, n, size in zip(coords, array.chunks, array.shape, strict=True))
        chunk = reader.read(coords)
        assert chunk.shape == tuple(array.chunks) and chunk.dtype == array.dtype
        assert not chunk.flags.writeable
        inside = tuple(slice(0, w.stop - w.start) for w in window)
        assert np.array_equal(chunk[inside], np.asarray(array[window])), coords
        beyond = np.ones(chunk.shape, bool)
        beyond[inside] = False
        assert (chunk[beyond] == array.metadata.fill_value).all()  # the edge chunk's padding


@pytest.mark.parametrize("level", [0, 3])
def test_float_chunks_equal_zarr_reads(tmp_path, level):
    rng = np.random.default_rng(0)
    array = zarr.create_array(tmp_path / "a.zarr", shape=(3, 10, 7, 2), chunks=(1, 4, 4, 2), dtype="float32",
                              fill_value=0.5, compressors=ZstdCodec(level=level))
    values = rng.normal(size=array.shape).astype(np.float32)
    values[1, :4, :4] = 0.5  # a chunk of fill values only: zarr does not write it
    array[...] = values
    assert not (tmp_path / "a.zarr" / "c" / "1" / "0" / "0" / "0").exists()
    reader = LocalChunkReader.for_array(array)
    assert reader is not None
    _chunks_equal_zarrs(array, reader)


def test_bool_chunks_equal_zarr_reads(tmp_path):
    array = zarr.create_array(tmp_path / "b.zarr", shape=(9, 9), chunks=(4, 4), dtype="bool",
                              fill_value=False)
    array[...] = np.random.default_rng(1).random(array.shape) > 0.5
    array[:4, 4:8] = False
    reader = LocalChunkReader.for_array(array)
    assert reader is not None
    _chunks_equal_zarrs(array, reader)


@pytest.mark.parametrize("layout", ["memory", "gzip", "blosc", "sharded", "big-endian"])
def test_other_layouts_are_read_through_zarr(tmp_path, layout):
    options = {"shape": (8, 8), "chunks": (4, 4), "dtype": "float32"}
    if layout == "memory":
        array = zarr.create_array(zarr.storage.MemoryStore(), **options)
    elif layout == "gzip":
        array = zarr.create_array(tmp_path / "g.zarr", compressors=GzipCodec(), **options)
    elif layout == "blosc":
        array = zarr.create_array(tmp_path / "c.zarr", compressors=BloscCodec(), **options)
    elif layout == "sharded":
        array = zarr.create_array(tmp_path / "s.zarr", shape=(8, 8), chunks=(2, 2), shards=(4, 4),
                                  dtype="float32")
    else:
        array = zarr.create_array(tmp_path / "e.zarr", serializer=BytesCodec(endian="big"), **options)
    assert LocalChunkReader.for_array(array) is None
    assert LocalChunkReader.for_array(np.zeros(3)) is None  # not a zarr array
