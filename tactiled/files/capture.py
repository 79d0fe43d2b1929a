"""Raw captures (``.bin``: the bytes exactly as read from the port) and recordings back into a board's bytes.

``tactiled replay x.bin`` reads a :class:`Capture` in chunks and runs it through the same decoder as the daemon
(as gpsfake feeds gpsd); :func:`recording_bytes` encodes a recording's samples as the board's frames (lost rows
become index gaps).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tactiled.board.frames import encode_frames
from tactiled.files.recording import Recording, lost_rows_budget

MIN_LOST_ROWS = 1 << 20  # zero rows a replayed capture may keep for its gaps whatever its size (4 MiB at 2 channels)


@dataclass(frozen=True)
class Capture:
    """A raw capture at ``path``: the bytes a port gave, decoded with a config's sensor settings (rate, channels, scale)."""

    path: Path

    def lost_rows_budget(self) -> int:
        """Zero rows a replay may keep for the capture's index gaps: one per byte of the file, and at least
        :data:`MIN_LOST_ROWS` (a capture of a few bytes cannot justify hundreds of MB of rows it never held)."""
        return lost_rows_budget(self.path.stat().st_size, MIN_LOST_ROWS)

    def chunks(self, size: int = 1 << 16) -> Iterator[bytes]:
        """The capture's bytes in pieces of ``size``."""
        return read_chunks(self.path, size)


def read_chunks(path: str | Path, size: int = 1 << 16) -> Iterator[bytes]:
    """The bytes of ``path`` in pieces of ``size``."""
    with open(path, "rb") as fh:
        while data := fh.read(size):
            yield data


def recording_bytes(rec: Recording, frame_count: int = 20) -> bytes:
    """``rec`` as the board's frames (``frame_count`` samples each) at its sensor indices; lost rows are not sent."""
    valid = rec.valid_mask()
    out = []
    n = rec.samples.shape[0]
    edges = np.flatnonzero(np.diff(np.concatenate([[False], valid, [False]]).astype(np.int8)))
    for lo, hi in zip(edges[::2], edges[1::2], strict=True):
        if hi > lo:
            out.append(encode_frames(rec.first_index + int(lo), rec.samples[lo:hi], count=frame_count))
    assert n == valid.shape[0]
    return b"".join(out)
