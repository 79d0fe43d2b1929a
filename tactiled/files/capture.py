"""Raw captures (``.bin``: the bytes exactly as read from the port) and recordings back into a board's bytes.

``tactiled replay x.bin`` reads a :class:`Capture` in chunks and runs it through the same decoder as the daemon
(as gpsfake feeds gpsd); :func:`recording_bytes` encodes a recording's samples as the board's frames (lost rows
become index gaps).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

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


class CaptureWriter:
    """A raw capture being written (``run --raw``): every byte read from the port, as read, appended to ``path``.

    A write the machine refuses (a full disk, a file-size limit, an I/O error) ends the capture, never the reading: the
    bytes already on disk stay, :attr:`error` says in one line what happened and where, and ``said`` is called with it
    once (from the reader thread). Before, the error reached the serial reader, which took it for an unplug and reopened
    the port some 80 times a second, losing nearly every sample.
    """

    def __init__(self, path: str | Path, said: Callable[[str], None] = lambda line: None) -> None:
        self.path = Path(path)
        self.error: str | None = None
        self._said = said
        self._fh: BinaryIO | None = open(self.path, "wb")  # noqa: SIM115 - closed by close()

    def write(self, data: bytes) -> None:
        """Append ``data`` (nothing once the capture has ended)."""
        if self._fh is not None:
            try:
                self._fh.write(data)
            except OSError as exc:
                self._end(exc)

    def flush(self) -> None:
        """What is buffered, to the file."""
        if self._fh is not None:
            try:
                self._fh.flush()
            except OSError as exc:
                self._end(exc)

    def close(self) -> None:
        """Flush and close (a failing flush is :attr:`error`, not raised)."""
        self.flush()
        self._end(None)

    def _end(self, exc: OSError | None) -> None:
        fh, self._fh = self._fh, None
        if fh is not None:
            with contextlib.suppress(OSError):  # the buffer's last flush fails again on a full disk; the descriptor closes all the same
                fh.close()
        if exc is not None and self.error is None:
            size = self.path.stat().st_size if self.path.is_file() else 0
            self.error = f"{self.path}: {exc.strerror or exc}: raw capture stopped at byte {size} (what is on disk is kept; reading goes on)"
            self._said(self.error)


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
