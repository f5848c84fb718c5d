"""The unwrap store: per texel geometry and per texel x view samples of an unwrapped capture.

Layout of the zarr group written by :func:`polarface.texture.unwrap.unwrap_capture` (``UNWRAP.zarr``;
zarr v3)::

    texel/position, texel/normal, texel/tangent_u, texel/tangent_v   float32 (Ht, Wt, 3), model frame, mm
    texel/texel_size_u, texel/texel_size_v                            float32 (Ht, Wt), mm per texel step
    texel/mask                                                        bool (Ht, Wt) atlas coverage
    obs     float32 (V, Ht, Wt, 3, 3)  per view: :data:`TEXTURE_OBSERVATION_NAMES` [I_sss = 2 I90,
                                       I_zeta = I135 - I45, I_s = I0 - I90] x the view's 3 channels
                                       (radiance, bilinear samples; 0 where invalid)
    valid   bool (V, Ht, Wt)           texel seen by the view: inside the image, unoccluded (ray cast,
                                       0.5 mm tolerance), n.v > ``cos_view_min``, no saturated neighbour,
                                       every pixel of its sampling footprint sees the texel's own surface
    lit     bool (V, Ht, Wt, K)        each LED module's shadow ray from the texel is free
    attrs:  format "polarface-unwrap", version, resolution, patch, views (list of :class:`ViewSpec` dicts),
            done (view indices written), complete

Chunks are ``(1, patch, patch, ...)``: a texture patch of all views is read without touching the rest,
and each view is written (and resumed) independently. View geometry (camera centre and up, light
positions) is stored in the *model* frame: for rigid poses the texel positions and base frames are
those of the rest mesh and only the per-view vectors move (exact, and H-dependent normals need no
per-view recomputation). Texture layout: :mod:`polarface.geometry.uv_raster` (row 0 = v 1).

Chunk cache (opt-in: ``UnwrapStore.open(path, cache_bytes=N)``, read-only stores): a haloed texture
patch straddles up to 3 x 3 chunks per view, most of which its neighbours read too; with the cache each
decoded chunk (per array, view and chunk position) is kept, least recently used first out, until the
decoded chunks held reach ``N`` bytes, so a region's reads decode only the chunks not yet held. Memory is
bounded by ``N`` whatever the number of views (the hit rate is what falls with many views: the static
fit's wavefront reuses every chunk when the cache holds about four chunk rows of its fitting views,
:mod:`polarface.inverse.polarimetric.patch_units`). Reads through the cache equal uncached reads.
In a local folder the chunks are decoded straight from their files and a view's chunks, and the texel
geometry's when the store is made, are written straight to them
(:class:`polarface.io.zarr_chunks.LocalChunks`, about 4x faster per chunk than zarr's pipeline), with or
without the cache; on a URL zarr reads and writes.

Where: a local path or an fsspec URL (``memory://``, ``s3://bucket/key``;
:func:`polarface.io.storage.storage_path`), opened through zarr's local or fsspec store; each chunk is
written in one piece (a rename locally, one object put on a URL), so a rewritten view never leaves half
a chunk.
"""

from __future__ import annotations

import dataclasses
from collections import OrderedDict
from collections.abc import Iterator, Sequence

import numpy as np

from polarface.capture.observations import OBSERVATION_NAMES
from polarface.geometry.uv_raster import UVRaster
from polarface.io.storage import PathOrUrl, open_zarr_group, storage_path
from polarface.io.zarr_chunks import LocalChunks
from polarface.texture.views import ViewSpec

__all__ = ["TEXTURE_OBSERVATION_NAMES", "TexelGeometry", "UnwrapStore", "texel_geometry"]

#: The observations sampled into texture space (axis -2 of ``obs``): the first three capture
#: observations; DoP and AoLP are not unwrapped.
TEXTURE_OBSERVATION_NAMES = OBSERVATION_NAMES[:3]
_FORMAT = "polarface-unwrap"


@dataclasses.dataclass(frozen=True, eq=False)
class TexelGeometry:
    """Per-texel base geometry of the rest mesh (model frame): numpy float32, see module docstring."""

    position: np.ndarray
    normal: np.ndarray
    tangent_u: np.ndarray
    tangent_v: np.ndarray
    texel_size_u: np.ndarray
    texel_size_v: np.ndarray
    mask: np.ndarray

    @property
    def resolution(self) -> tuple[int, int]:
        return int(self.mask.shape[0]), int(self.mask.shape[1])

    def crop(self, rows: slice, cols: slice) -> TexelGeometry:
        return TexelGeometry(*(getattr(self, f.name)[rows, cols] for f in dataclasses.fields(self)))


def texel_geometry(raster: UVRaster) -> TexelGeometry:
    """The :class:`TexelGeometry` of a rest-pose raster."""
    return TexelGeometry(
        raster.position.astype(np.float32),
        raster.normal.astype(np.float32),
        raster.tangent_u.astype(np.float32),
        raster.tangent_v.astype(np.float32),
        raster.texel_size_u.astype(np.float32),
        raster.texel_size_v.astype(np.float32),
        raster.mask.copy(),
    )


class _ChunkCache:
    """Decoded chunks, key -> array, least recently used evicted first beyond ``max_bytes`` in all."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = int(max_bytes)
        self.bytes = 0
        self.entries: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self.hits = 0
        self.misses = 0

    def get(self, key: tuple) -> np.ndarray | None:
        value = self.entries.get(key)
        if value is None:
            self.misses += 1
            return None
        self.hits += 1
        self.entries.move_to_end(key)
        return value

    def put(self, key: tuple, value: np.ndarray) -> None:
        if value.nbytes > self.max_bytes:
            return
        old = self.entries.pop(key, None)
        self.bytes += value.nbytes - (old.nbytes if old is not None else 0)
        self.entries[key] = value
        while self.bytes > self.max_bytes:
            _, evicted = self.entries.popitem(last=False)
            self.bytes -= evicted.nbytes


def _write_texel_array(array, values: np.ndarray) -> None:
    """Write a whole texel array ``(Ht, Wt, ...)`` (chunked over ``Ht, Wt`` alone) chunk by chunk with
    :class:`LocalChunks` where the store allows it (about 4x faster per chunk), else through zarr."""
    chunks = LocalChunks.for_array(array)
    if chunks is None:
        array[...] = values
        return
    _write_chunk_grid(chunks, array.chunks[:2], values, ())


def _write_chunk_grid(chunks: LocalChunks, chunk_hw: tuple[int, int], values: np.ndarray,
                      leading: tuple[int, ...]) -> None:
    """Write ``values`` ``(Ht, Wt, ...)`` whole, one ``chunk_hw`` texel block per chunk, at chunk-grid
    positions ``(*leading, row, col, 0, ...)`` (``leading``: axes of chunk size 1 before the texels, the
    view index of ``obs``, ``valid`` and ``lit``)."""
    chunk_h, chunk_w = chunk_hw
    inner = (0,) * (values.ndim - 2)
    ones = (1,) * len(leading)
    for i in range(0, values.shape[0], chunk_h):
        for j in range(0, values.shape[1], chunk_w):
            block = values[i : i + chunk_h, j : j + chunk_w]
            chunks.write((*leading, i // chunk_h, j // chunk_w, *inner), block.reshape(ones + block.shape))


class UnwrapStore:
    """Reader/writer of an unwrapped capture (layout in the module docstring); ``cache_bytes > 0``: reads
    go through a chunk cache of that many bytes (read-only stores only; module docstring)."""

    def __init__(self, path: PathOrUrl, root, cache_bytes: int = 0) -> None:
        self.path = storage_path(path)
        self.root = root
        self._cache = _ChunkCache(cache_bytes) if int(cache_bytes) > 0 else None
        self._arrays: dict[str, object] = {}

    # ----------------------------------------------------------------------------- creation
    @classmethod
    def create(
        cls, path: PathOrUrl, geometry: TexelGeometry, views: Sequence[ViewSpec], patch: int
    ) -> UnwrapStore:
        """A new, empty store at ``path`` (a local path or a URL; whatever was there is replaced)."""
        path = storage_path(path)
        root = open_zarr_group(path, "w")
        height, width = geometry.resolution
        chunk = (min(patch, height), min(patch, width))
        for field in dataclasses.fields(geometry):
            value = getattr(geometry, field.name)
            array = root.create_array(
                f"texel/{field.name}", shape=value.shape, dtype=value.dtype, chunks=(*chunk, *value.shape[2:])
            )
            _write_texel_array(array, value)
        count = len(views)
        light_count = len(views[0].light_positions) if views else 0
        root.create_array(
            "obs",
            shape=(count, height, width, 3, 3),
            dtype="float32",
            chunks=(1, *chunk, 3, 3),
            fill_value=0.0,
        )
        root.create_array(
            "valid", shape=(count, height, width), dtype="bool", chunks=(1, *chunk), fill_value=False
        )
        root.create_array(
            "lit",
            shape=(count, height, width, light_count),
            dtype="bool",
            chunks=(1, *chunk, light_count),
            fill_value=False,
        )
        root.update_attributes(  # one metadata write (``attrs.update`` writes once per key)
            {
                "format": _FORMAT,
                "version": 1,
                "resolution": [height, width],
                "patch": int(patch),
                "views": [v.to_dict() for v in views],
                "done": [],
                "complete": False,
            }
        )
        return cls(path, root)

    @classmethod
    def open(cls, path: PathOrUrl, mode: str = "r", cache_bytes: int = 0) -> UnwrapStore:
        """Open an unwrap store at a local path or a URL.

        Args:
            mode: zarr's open mode (``r``: read only). cache_bytes: > 0: reads of :meth:`read` and
                :meth:`geometry` go through a chunk cache holding at most this many bytes of decoded
                chunks (module docstring); only with ``mode="r"``.

        Raises:
            FileNotFoundError: nothing is there. ValueError: it is not an unwrap store, the URL's
                protocol is unknown or its package missing, or a cache on a writable store.
        """
        path = storage_path(path)
        if int(cache_bytes) > 0 and mode != "r":
            raise ValueError(f"argument 'cache_bytes' needs mode 'r' (a read-only store); got mode '{mode}'")
        if not path.exists():
            raise FileNotFoundError(f"unwrap store '{path}' does not exist")
        root = open_zarr_group(path, mode)
        if root.attrs.get("format") != _FORMAT:
            raise ValueError(f"'{path}' is not a polarface unwrap store")
        return cls(path, root, cache_bytes)

    @property
    def cache_counts(self) -> dict[str, int]:
        """Chunk cache ``hits``, ``misses`` (chunks decoded) and ``bytes`` held (zeros without a cache)."""
        cache = self._cache
        return {"hits": cache.hits, "misses": cache.misses, "bytes": cache.bytes} if cache else \
            {"hits": 0, "misses": 0, "bytes": 0}  # fmt: skip

    # ----------------------------------------------------------------------------- metadata
    @property
    def views(self) -> list[ViewSpec]:
        return [ViewSpec.from_dict(v) for v in self.root.attrs["views"]]

    @property
    def resolution(self) -> tuple[int, int]:
        height, width = self.root.attrs["resolution"]
        return int(height), int(width)

    @property
    def patch(self) -> int:
        return int(self.root.attrs["patch"])

    @property
    def complete(self) -> bool:
        return bool(self.root.attrs.get("complete", False))

    def done(self) -> set[int]:
        return {int(v) for v in self.root.attrs.get("done", [])}

    def geometry(self, rows: slice = slice(None), cols: slice = slice(None)) -> TexelGeometry:
        names = [f.name for f in dataclasses.fields(TexelGeometry)]
        return TexelGeometry(*(self._read_region(f"texel/{n}", rows, cols, None) for n in names))

    # ----------------------------------------------------------------------------- data
    def write_view(self, index: int, obs: np.ndarray, valid: np.ndarray, lit: np.ndarray) -> None:
        """Write view ``index``'s ``obs (Ht, Wt, 3, 3)``, ``valid (Ht, Wt)`` and ``lit (Ht, Wt, K)``, each
        chunk in one piece, and record the view as done.

        Raises:
            ValueError: an array of another shape (naming it).
        """
        arrays = {"obs": np.asarray(obs), "valid": np.asarray(valid), "lit": np.asarray(lit)}
        for name, values in arrays.items():  # every shape checked before anything is written
            expected = tuple(self._array(name)[0].shape[1:])
            if values.shape != expected:
                raise ValueError(f"argument '{name}' must have shape {expected}; got {values.shape}")
        for name, values in arrays.items():
            array, chunks = self._array(name)
            if chunks is None:
                array[index] = values
                continue
            _write_chunk_grid(chunks, array.chunks[1:3], values, (index,))
        stats = dict(self.root.attrs.get("stats", {}))
        stats[str(int(index))] = [float(obs[..., 0, :][valid].sum()), int(valid.sum()) * 3]
        # one write of the group's metadata for both (``attrs[key] = ...`` writes it once per key)
        self.root.update_attributes({
            "stats": dict(sorted(stats.items(), key=lambda item: int(item[0]))),  # any order
            "done": sorted(self.done() | {int(index)}),
        })

    def mark_complete(self) -> None:
        self.root.attrs["complete"] = True

    def read(self, rows: slice, cols: slice, views: Sequence[int] | None = None) -> tuple[np.ndarray, ...]:
        """``obs (V', h, w, 3, 3)``, ``valid (V', h, w)``, ``lit (V', h, w, K)`` of a texture region."""
        selection = slice(None) if views is None else np.asarray(list(views), dtype=np.int64)
        if views is not None and len(selection) == 0:
            height = len(range(*rows.indices(self.resolution[0])))
            width = len(range(*cols.indices(self.resolution[1])))
            light_count = self.root["lit"].shape[-1]
            return (
                np.zeros((0, height, width, 3, 3), np.float32),
                np.zeros((0, height, width), bool),
                np.zeros((0, height, width, light_count), bool),
            )
        chosen = np.arange(len(self.views)) if views is None else selection
        return tuple(self._read_region(name, rows, cols, chosen) for name in ("obs", "valid", "lit"))

    def _read_region(self, name: str, rows: slice, cols: slice, views: np.ndarray | None) -> np.ndarray:
        """``array[views, rows, cols]`` (``views`` None: an array without a view axis): assembled from
        whole chunks where :meth:`_assembled`, else read through zarr in one call."""
        if self._assembled(name):
            return self._region(name, rows, cols, views)
        array = self._array(name)[0]
        if views is None:
            return np.asarray(array[rows, cols])
        return np.asarray(array.get_orthogonal_selection((np.asarray(views, np.int64), rows, cols)))

    def _array(self, name: str):
        """The zarr array ``name`` and its :class:`LocalChunks` (None: read and written through zarr; so
        are arrays whose chunks hold more than one view), opened once per store object."""
        if name not in self._arrays:
            array = self.root[name]
            one_view = name.startswith("texel/") or array.chunks[0] == 1
            self._arrays[name] = (array, LocalChunks.for_array(array) if one_view else None)
        return self._arrays[name]

    def _assembled(self, name: str) -> bool:
        """Whether regions of ``name`` are assembled from whole chunks (:meth:`_region`): through the
        chunk cache, or decoded directly from a local store's chunk files (module docstring)."""
        return self._cache is not None or self._array(name)[1] is not None

    def _region(self, name: str, rows: slice, cols: slice, views: np.ndarray | None) -> np.ndarray:
        """``array[views, rows, cols]`` (``views`` None: an array without a view axis) assembled from
        decoded chunks (cached ones where the store has a cache); the chunks not held are decoded
        directly or read through zarr, per chunk position, in one call."""
        array = self._array(name)[0]
        height, width = self.resolution
        r0, r1, _ = rows.indices(height)
        c0, c1, _ = cols.indices(width)
        offset = 0 if views is None else 1
        chunk_h, chunk_w = array.chunks[offset], array.chunks[offset + 1]
        lead = () if views is None else (len(views),)
        out = np.empty((*lead, max(r1 - r0, 0), max(c1 - c0, 0), *array.shape[offset + 2 :]), array.dtype)
        ids = [None] if views is None else [int(v) for v in views]
        for i in range(r0 // chunk_h, (r1 - 1) // chunk_h + 1 if r1 > r0 else 0):
            for j in range(c0 // chunk_w, (c1 - 1) // chunk_w + 1 if c1 > c0 else 0):
                blocks = self._chunk_blocks(array, name, ids, i, j)
                br = slice(max(r0, i * chunk_h) - i * chunk_h, min(r1, (i + 1) * chunk_h) - i * chunk_h)
                bc = slice(max(c0, j * chunk_w) - j * chunk_w, min(c1, (j + 1) * chunk_w) - j * chunk_w)
                orow = slice(i * chunk_h + br.start - r0, i * chunk_h + br.stop - r0)
                ocol = slice(j * chunk_w + bc.start - c0, j * chunk_w + bc.stop - c0)
                if views is None:
                    out[orow, ocol] = blocks[0][br, bc]
                else:
                    for index, block in enumerate(blocks):
                        out[index, orow, ocol] = block[br, bc]
        return out

    def _chunk_blocks(self, array, name: str, ids: list, i: int, j: int) -> list[np.ndarray]:
        """The decoded chunk ``(i, j)`` of ``array`` for each view of ``ids`` (``[None]``: no view axis),
        clipped to the array: from the cache (if any), the missing ones decoded directly or read through
        zarr in one call, and cached."""
        cache, reader = self._cache, self._array(name)[1]
        keys = [(name, v, i, j) for v in ids]
        blocks = [cache.get(key) for key in keys] if cache is not None else [None] * len(keys)
        missing = [index for index, block in enumerate(blocks) if block is None]
        if missing:
            lead = 0 if ids[0] is None else 1
            height, width = array.shape[lead : lead + 2]
            chunk_h, chunk_w = array.chunks[lead : lead + 2]
            window = (slice(i * chunk_h, min((i + 1) * chunk_h, height)),
                      slice(j * chunk_w, min((j + 1) * chunk_w, width)))  # fmt: skip
            if reader is not None:
                inner = (0,) * (array.ndim - lead - 2)
                clip = tuple(slice(0, part.stop - part.start) for part in window)
                read = [reader.read((i, j, *inner))[clip] if ids[index] is None
                        else reader.read((ids[index], i, j, *inner))[0][clip] for index in missing]
            elif ids[0] is None:
                read = [np.asarray(array[window])]
            else:
                selection = (np.array([ids[index] for index in missing], dtype=np.int64), *window)
                read = list(np.asarray(array.get_orthogonal_selection(selection)))
            for index, block in zip(missing, read, strict=True):
                block = np.ascontiguousarray(block)
                block.flags.writeable = False
                blocks[index] = block
                if cache is not None:
                    cache.put(keys[index], block)
        return blocks

    def patches(self, patch: int | None = None) -> Iterator[tuple[slice, slice]]:
        """Row/column slices of the texture patches that contain atlas texels (row-major order)."""
        size = patch or self.patch
        height, width = self.resolution
        mask = np.asarray(self.root["texel/mask"][...])
        for r in range(0, height, size):
            for c in range(0, width, size):
                if mask[r : r + size, c : c + size].any():
                    yield slice(r, min(r + size, height)), slice(c, min(c + size, width))

    def mean_i_sss(self, views: Sequence[int] | None = None) -> float:
        """Mean observed ``I_sss`` over the valid samples of ``views`` (default all); 0 if none."""
        stats = self.root.attrs.get("stats", {})
        keys = [str(v) for v in (range(len(self.views)) if views is None else views)]
        total = sum(stats[k][0] for k in keys if k in stats)
        count = sum(stats[k][1] for k in keys if k in stats)
        return total / count if count else 0.0

    def visible_count(self) -> np.ndarray:
        """``(Ht, Wt)`` number of fitting (not held-out) views that see each texel."""
        fitting = [i for i, v in enumerate(self.views) if not v.held_out]
        total = np.zeros(self.resolution, np.int32)
        whole = slice(None)
        for i in fitting:
            total += self._read_region("valid", whole, whole, np.array([i]))[0]
        return total
