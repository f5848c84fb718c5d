"""The chunks of a capture store's derived arrays that a read touches: which one is damaged or missing.

zarr reads a chunk that is not there as the fill value (NaN for the float stacks, 0 for the masks) and
reports a chunk that does not decode with its codec's error, which names no file (blosc:
``RuntimeError: error during blosc decompression: -1``). :class:`polarface.capture.store.CaptureStore`
reads every derived array through its ``_read_derived``, which asks this module for a one-line error
naming the chunk file, the array and the frame:

* a read that raises: each chunk the read touches is read alone; the first that fails is named;
* a float read holding NaN (a stack is finite wherever it was written): the chunk files the read touches
  are looked up; a missing one is named (masks cannot tell a missing chunk from one of zeros, which zarr
  never writes, so they are not checked).

The advice in the messages: remove the frame's completion marker and rerun the command that wrote the
store (``ingest`` or ``simulate``), which rewrites every frame without a marker.
"""

from __future__ import annotations

import itertools

from polarface.io.storage import PathOrUrl, storage_path

__all__ = ["damaged_chunk_message", "missing_chunk_message", "touched_chunks"]


def touched_chunks(shape: tuple[int, ...], chunks: tuple[int, ...],
                   selection: tuple) -> list[tuple[int, ...]]:
    """Chunk-grid positions that ``array[selection]`` reads (``selection``: ints and step-1 slices over the
    leading axes; the axes after it are read whole)."""
    ranges = []
    for axis, (size, chunk) in enumerate(zip(shape, chunks, strict=True)):
        item = selection[axis] if axis < len(selection) else slice(None)
        if isinstance(item, slice):
            start, stop, _ = item.indices(size)
            if stop <= start:
                return []
            ranges.append(range(start // chunk, (stop - 1) // chunk + 1))
        else:
            index = int(item) % size if size else 0
            ranges.append(range(index // chunk, index // chunk + 1))
    return list(itertools.product(*ranges))


def _chunk_region(shape: tuple[int, ...], chunks: tuple[int, ...], coords: tuple[int, ...]) -> tuple:
    axes = zip(coords, chunks, shape, strict=True)
    return tuple(slice(c * n, min((c + 1) * n, size)) for c, n, size in axes)


def _chunk_file(array, name: str, coords: tuple[int, ...]) -> str:
    return f"derived.zarr/{name}/{array.metadata.encode_chunk_key(tuple(int(c) for c in coords))}"


def _advice(frame_index: int) -> str:
    return (f"remove 'frames/{frame_index:06d}.json' and rerun the ingest (or simulate) that wrote the store "
            "to rewrite the frame")


def damaged_chunk_message(root: PathOrUrl, array, name: str, frame_index: int, selection: tuple,
                          error: BaseException) -> str:
    """The one-line error of a read of derived array ``name`` that raised ``error``: the first chunk of the
    read that fails alone (or, when none does, the read's array and frame)."""
    root = storage_path(root)
    shape, chunks = tuple(array.shape), tuple(array.chunks)
    for coords in touched_chunks(shape, chunks, selection):
        try:
            array[_chunk_region(shape, chunks, coords)]
        except Exception as exc:
            return (f"capture store '{root}': chunk '{_chunk_file(array, name, coords)}' of derived array "
                    f"'{name}' (frame {frame_index}) cannot be decoded ({_reason(exc)}); "
                    f"{_advice(frame_index)}")
    return (f"capture store '{root}': derived array '{name}' (frame {frame_index}) cannot be read "
            f"({_reason(error)}); {_advice(frame_index)}")


def missing_chunk_message(root: PathOrUrl, array, name: str, frame_index: int,
                          selection: tuple) -> str | None:
    """The one-line error naming the first chunk file of the read that is missing, or None when every chunk
    is there (the NaN values were written)."""
    root = storage_path(root)
    for coords in touched_chunks(tuple(array.shape), tuple(array.chunks), selection):
        relative = _chunk_file(array, name, coords)
        if not (root / relative).exists():
            return (f"capture store '{root}': chunk '{relative}' of derived array '{name}' (frame "
                    f"{frame_index}) is missing (deleted?); {_advice(frame_index)}")
    return None


def _reason(exc: BaseException) -> str:
    return " ".join((str(exc) or type(exc).__name__).split())
