"""Pairing detected slides with true ones (temporary; replaced by the detector branch)."""

from __future__ import annotations

from collections.abc import Sequence


def match_slides(detected: Sequence[tuple[int, int]], truth: Sequence[tuple[int, int]]) -> list[int | None]:
    """For each true slide, the index of the detection paired with it (greedy by overlap), else None."""
    pairs = sorted(((min(b, tb) - max(a, ta), i, j) for j, (ta, tb) in enumerate(truth) for i, (a, b) in enumerate(detected)
                    if min(b, tb) > max(a, ta)), reverse=True)
    out: list[int | None] = [None] * len(truth)
    used: set[int] = set()
    for _, i, j in pairs:
        if out[j] is None and i not in used:
            out[j] = i
            used.add(i)
    return out
