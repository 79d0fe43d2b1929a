"""Ground truth beside the labels: which true slide a labelled span overlaps most (for replays, the monitor and demos)."""

from __future__ import annotations

from collections.abc import Iterable

__all__ = ["overlapping"]


def overlapping(truth: Iterable[tuple[int, int, str | None]], start: int, stop: int) -> str | None:
    """The surface of the true slide (start, stop, surface; sample indices, stop exclusive) that overlaps [start, stop) most.

    None when none overlaps; ties go to the earlier slide.
    """
    best, most = None, 0
    for a, b, surface in truth:
        overlap = min(b, stop) - max(a, start)
        if overlap > most:
            best, most = surface, overlap
    return best
