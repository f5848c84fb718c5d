"""The frame selection of a sequence (``--frames``): which frames of a capture a stage fits."""

from __future__ import annotations

from collections.abc import Iterable, Sequence

__all__ = ["parse_frame_selection", "selection_note"]


def _ranges(values: Sequence[int]) -> str:
    """``[0, 1, 2, 5]`` as ``'0-2,5'``."""
    parts: list[str] = []
    start = previous = None
    for value in sorted(set(values)):
        if previous is not None and value == previous + 1:
            previous = value
            continue
        if start is not None:
            parts.append(f"{start}-{previous}" if previous != start else f"{start}")
        start = previous = value
    if start is not None:
        parts.append(f"{start}-{previous}" if previous != start else f"{start}")
    return ",".join(parts)


def parse_frame_selection(spec: str | Iterable[int] | None, frames: Iterable[int]) -> list[int]:
    """Frames selected by ``spec`` among the capture's ``frames``, in the sequence's order.

    ``spec`` is ``"0-4,7"`` (frames and ascending ranges, in any order, repeats allowed), a list of
    indices, or None for all. The selection is a set: the frames are always tracked forward through the
    whole sequence and fitted in its order, whatever order ``spec`` lists them in.

    Raises:
        ValueError: a malformed spec, a descending range (``'4-0'``: write ``'0-4'``), an empty selection,
            or frames that are not in the capture (naming ``--frames``).
    """
    frames = [int(f) for f in frames]
    if spec is None:
        return frames
    present = set(frames)
    chosen: set[int] = set()
    unknown: list[str] = []

    def take(low: int, high: int) -> None:
        inside = [f for f in frames if low <= f <= high]
        chosen.update(inside)
        if high - low + 1 > len(inside):  # some are not in the capture: name them, compactly
            if high - low < 100_000:
                unknown.append(_ranges([v for v in range(low, high + 1) if v not in present]))
            else:  # a huge range: its ends that are not in the capture
                while low in present:
                    low += 1
                while high in present:
                    high -= 1
                unknown.append(f"{low}-{high}")

    if isinstance(spec, str):
        for part in (p.strip() for p in spec.split(",")):
            try:
                if "-" in part[1:]:
                    cut = part.index("-", 1)
                    low, high = int(part[:cut]), int(part[cut + 1:])
                else:
                    low = high = int(part)
            except ValueError:
                raise ValueError(
                    f"argument '--frames': {spec!r} is not a list of frames and ranges (e.g. '0-4,7')"
                ) from None
            if min(low, high) < 0:
                raise ValueError(f"argument '--frames': {part!r}: frame indices are >= 0")
            if low > high:
                raise ValueError(
                    f"argument '--frames': {part!r} is a descending range; frames are tracked forward "
                    f"through the whole sequence and fitted in its order: write '{high}-{low}'"
                )
            take(low, high)
    else:
        for value in spec:
            take(int(value), int(value))
    if unknown:
        raise ValueError(
            f"argument '--frames': frame(s) {','.join(unknown)} are not in the dynamic capture (its frames: "
            f"{_ranges(frames) or 'none'})"
        )
    if not chosen:
        raise ValueError(f"argument '--frames': {spec!r} selects no frame")
    return [f for f in frames if f in chosen]


def selection_note(spec: str | Iterable[int] | None, selected: Sequence[int]) -> str | None:
    """What to tell the user about ``--frames spec`` whose frames are fitted as ``selected``
    (:func:`parse_frame_selection`): a note when ``spec`` lists them out of the sequence's order or more
    than once (they are fitted once, in the sequence's order), else None."""
    if spec is None:
        return None
    if isinstance(spec, str):
        firsts = [int(part.strip()[:part.strip().index("-", 1)]) if "-" in part.strip()[1:]
                  else int(part) for part in spec.split(",")]
    else:
        firsts = [int(value) for value in spec]
    if firsts == sorted(set(firsts)):
        return None
    return (f"--frames {spec if isinstance(spec, str) else firsts!r}: the frames are fitted once "
            f"each, in the sequence's order ({_ranges(selected)}); the tracking always runs forward "
            "through the whole sequence")
