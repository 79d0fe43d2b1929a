"""Raw sample batches for the ``samples/<sensor>`` topic: every index once, lost ones as zero rows.

Pure: the daemon hands in the blocks of one processing batch and the index it expects
next; out come contiguous batches whose rows cover every index from the expected one on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt


@dataclass
class SamplesChunk:
    """Rows ``index .. index + n`` (``samples`` (n, C) int16, lost rows zero), ``lost`` [[position, count], ...]."""

    index: int
    samples: npt.NDArray[np.int16]
    lost: list[list[int]]
    lost_before: int = 0  # samples lost just before ``index`` and not sent as rows (gap > max_fill)


def samples_chunks(blocks: list[tuple[int, npt.NDArray[np.int16]]], expected: int | None, max_fill: int) -> list[SamplesChunk]:
    """Batches covering ``blocks`` ((index, (n, C) int16) in increasing index order) from ``expected`` on.

    A gap of at most ``max_fill`` samples becomes zero rows listed in ``lost``; a longer one
    starts a new batch whose ``lost_before`` counts it. ``expected`` None: start at the first block.
    """
    out: list[SamplesChunk] = []
    rows: list[npt.NDArray[np.int16]] = []
    lost: list[list[int]] = []
    start = nxt = expected
    n = lost_before = 0
    for index, block in blocks:
        if nxt is None:
            start = nxt = index
        gap = index - nxt
        if gap < 0:
            raise ValueError(f"samples_chunks: block at {index} overlaps the previous one (expected {nxt})")
        if gap > max_fill:
            if n:
                assert start is not None
                out.append(SamplesChunk(start, np.concatenate(rows), lost, lost_before))
            start, rows, lost, n, lost_before = index, [], [], 0, gap
        elif gap:
            lost.append([n, gap])
            rows.append(np.zeros((gap, block.shape[1]), dtype=np.int16))
            n += gap
        rows.append(block)
        n += block.shape[0]
        nxt = index + block.shape[0]
    if n:
        assert start is not None
        out.append(SamplesChunk(start, np.concatenate(rows).astype(np.int16, copy=False), lost, lost_before))
    return out
