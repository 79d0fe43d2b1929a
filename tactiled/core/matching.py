"""Pairing detected slides with true ones, and detection scores: pure functions over (start, stop) sample positions."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np


def match_slides(detected: Sequence[tuple[int, int]], truth: Sequence[tuple[int, int]]) -> list[int | None]:
    """For each true slide, the index of the detection paired with it, else None.

    One-to-one, greedily by largest overlap (a detection pairs with at most one true slide,
    and only if they overlap): a slide split in two pairs with its larger part, and the
    other part counts against precision.
    """
    pairs = sorted(((min(b, tb) - max(a, ta), -j, -i, i, j) for j, (ta, tb) in enumerate(truth) for i, (a, b) in enumerate(detected)
                    if min(b, tb) > max(a, ta)), reverse=True)
    out: list[int | None] = [None] * len(truth)
    used: set[int] = set()
    for *_, i, j in pairs:
        if out[j] is None and i not in used:
            out[j] = i
            used.add(i)
    return out


def detection_scores(detected: Sequence[tuple[int, int]], truth: Sequence[tuple[int, int]], fs: float) -> dict[str, Any]:
    """Recall, precision and boundary errors (s) of ``detected`` against ``truth`` (see :func:`match_slides`)."""
    pairs = match_slides(detected, truth)
    paired = [(detected[i], truth[j]) for j, i in enumerate(pairs) if i is not None]
    start_err = np.abs([d[0] - t[0] for d, t in paired]) / fs
    end_err = np.abs([d[1] - t[1] for d, t in paired]) / fs

    def stat(a: np.ndarray, q: float) -> float | None:
        return float(np.percentile(a, q)) if len(a) else None

    return {"n_true": len(truth), "n_detected": len(detected), "paired": len(paired),
            "recall": len(paired) / len(truth) if truth else 1.0, "precision": len(paired) / len(detected) if detected else 1.0,
            "start_error_s": {"median": stat(start_err, 50), "p90": stat(start_err, 90)},
            "end_error_s": {"median": stat(end_err, 50), "p90": stat(end_err, 90)}}
