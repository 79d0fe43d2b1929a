"""Hostile files (issue 22, items 4 and 6/7): recordings, captures and journals that claim more than they hold, or hold
numbers at the edge of float64, are bounded by their size and refused in one line, never a traceback.

Every test builds real files in ``tmp_path`` and states the bound it checks.
"""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np

from tactiled.board.frames import encode_frame
from tactiled.config import Config
from tactiled.files.capture import Capture
from tactiled.run.replay import replay_capture, summary_line

MB = 1 << 20


def test_a_capture_whose_index_jumps_keeps_zero_rows_bounded_by_its_size_and_counts_every_gap(tmp_path: Path) -> None:
    """Bound: 100 one-sample frames (1.6 kB), each 399 000 samples after the last (under the ring's 400 000, so each
    gap is lost samples), peak Python allocation < 50 MB (it was ~160 MB: 1.6 MB of zero rows per gap); every gap still
    counted: 99 x 398 999 samples lost, in the meta and the summary line."""
    path = tmp_path / "gaps.bin"
    path.write_bytes(b"".join(encode_frame(i * 399_000, np.array([[i, -i]], dtype=np.int16)) for i in range(100)))
    tracemalloc.start()
    try:
        _, rec = replay_capture(Capture(path), Config(), None)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 50 * MB, f"peak {peak / MB:.0f} MB for a {path.stat().st_size} byte capture"
    assert rec.meta["samples_lost"] == 99 * 398_999 and rec.meta["samples"] == 100
    assert rec.samples.shape[0] <= Capture(path).lost_rows_budget() + 100 and "truncated_at" in rec.meta
    assert summary_line([], rec).endswith(f", {99 * 398_999} samples lost")
