"""Direct chunk reads and writes of local zarr v3 arrays (io/zarr_chunks.py): every chunk read equals
zarr's own read of it (chunks straddling the array's edge, chunks never written, float and bool arrays),
chunks written read back through zarr (edge chunks, chunks of fill values only left out as zarr leaves
them out, unless the array writes empty chunks), bad chunks are refused, and arrays whose store or codecs
are another layout are refused (read and written through zarr)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import zarr
from zarr.codecs import BloscCodec, BytesCodec, GzipCodec, ZstdCodec

from polarface.io.zarr_chunks import LocalChunks


def _chunks_equal_zarrs(array, reader: LocalChunks) -> None:
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
    reader = LocalChunks.for_array(array)
    assert reader is not None
    _chunks_equal_zarrs(array, reader)


def test_bool_chunks_equal_zarr_reads(tmp_path):
    array = zarr.create_array(tmp_path / "b.zarr", shape=(9, 9), chunks=(4, 4), dtype="bool",
                              fill_value=False)
    array[...] = np.random.default_rng(1).random(array.shape) > 0.5
    array[:4, 4:8] = False
    reader = LocalChunks.for_array(array)
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
    assert LocalChunks.for_array(array) is None
    assert LocalChunks.for_array(np.zeros(3)) is None  # not a zarr array


@pytest.mark.parametrize("dtype", ["float32", "bool"])
def test_written_chunks_read_back_through_zarr(tmp_path, dtype):
    rng = np.random.default_rng(2)
    expected = rng.normal(size=(2, 9, 7)).astype(np.float32)
    expected = (expected > 0) if dtype == "bool" else expected
    written = zarr.create_array(tmp_path / "w.zarr", shape=expected.shape, chunks=(1, 4, 4), dtype=dtype,
                                fill_value=0)
    chunks = LocalChunks.for_array(written)
    for v, i, j in itertools.product(range(2), range(3), range(2)):
        chunks.write((v, i, j), expected[v : v + 1, 4 * i : 4 * i + 4, 4 * j : 4 * j + 4])  # edges: less
    assert np.array_equal(np.asarray(written[...]), expected)
    reference = zarr.create_array(tmp_path / "r.zarr", shape=expected.shape, chunks=(1, 4, 4), dtype=dtype,
                                  fill_value=0)
    reference[...] = expected  # zarr's own chunks: the same files exist, the same values decode

    def files(name: str) -> set:
        folder = tmp_path / name / "c"
        return {path.relative_to(folder) for path in folder.rglob("*") if path.is_file()}

    assert files("w.zarr") == files("r.zarr")  # the same chunks written (none of fill values only, no temp)


def test_a_chunk_of_fill_values_is_removed_unless_empty_chunks_are_written(tmp_path):
    for write_empty in (False, True):
        array = zarr.create_array(tmp_path / f"e{write_empty}.zarr", shape=(4, 4), chunks=(2, 2),
                                  dtype="float32", fill_value=1.5, config={"write_empty_chunks": write_empty})
        chunks = LocalChunks.for_array(array)
        path = tmp_path / f"e{write_empty}.zarr" / "c" / "1" / "0"
        chunks.write((1, 0), np.zeros((2, 2)))
        assert path.exists()
        chunks.write((1, 0), np.full((2, 2), 1.5))
        assert path.exists() == write_empty
        assert np.array_equal(np.asarray(array[2:, :2]), np.full((2, 2), 1.5, np.float32))


def test_a_chunk_that_does_not_fit_is_refused(tmp_path):
    array = zarr.create_array(tmp_path / "b.zarr", shape=(4, 4), chunks=(2, 2), dtype="float32")
    chunks = LocalChunks.for_array(array)
    for values in (np.zeros((3, 2)), np.zeros((2, 2, 1)), np.zeros(2)):
        with pytest.raises(ValueError, match="argument 'values' must fit a chunk"):
            chunks.write((0, 0), values)


@pytest.mark.parametrize(("dtype", "fill"), [("float32", 0.0), ("float32", np.nan), ("float32", 1.5),
                                             ("bool", False), ("bool", True), ("int16", 0), ("int16", -3)])
def test_chunks_of_fill_values_are_told_as_numpy_compares_them(tmp_path, dtype, fill):
    """The test for a chunk of fill values only answers as ``np.array_equal(chunk, full_like(chunk, fill),
    equal_nan=...)`` (the file is removed exactly then): ``-0.0`` counts as a fill of ``0.0``, NaN as a
    fill of NaN, a value that rounds to the fill in the array's dtype counts as fill (tested after the
    cast), an edge chunk's padding is fill."""
    array = zarr.create_array(tmp_path / "f.zarr", shape=(3, 3), chunks=(2, 2), dtype=dtype, fill_value=fill)
    chunks = LocalChunks.for_array(array)
    fill_value = np.asarray(fill, dtype)
    cases = [np.full((2, 2), fill_value), np.full((1, 1), fill_value)]  # a whole chunk, an edge chunk
    if dtype == "float32":
        cases += [np.where(np.eye(2, dtype=bool), -fill_value, fill_value), np.full((2, 2), fill) + 1e-50,
                  np.full((2, 2), np.nan), np.array([[fill, 2.0], [fill, fill]])]
    else:
        cases += [np.array([[fill_value, ~fill_value if dtype == "bool" else fill_value + 1]] * 2)]
    for values in cases:
        chunk = np.full((2, 2), fill_value)
        chunk[: values.shape[0], : values.shape[1]] = values
        expected_empty = np.array_equal(chunk, np.full_like(chunk, fill_value), equal_nan=dtype == "float32")
        chunks.write((0, 0), values)
        assert (tmp_path / "f.zarr" / "c" / "0" / "0").exists() != expected_empty, values
        assert np.array_equal(np.asarray(array[:2, :2]), chunk, equal_nan=dtype == "float32")
