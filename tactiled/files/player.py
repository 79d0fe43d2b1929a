"""Byte players: a raw capture (``.bin``) or a recording (``.npz``) back into the bytes a board sends.

``tactiled replay x.bin`` reads a capture with :func:`read_chunks` and runs it through the
same decoder as the daemon (as gpsfake feeds gpsd); :func:`recording_bytes` encodes a
recording's samples as the board's frames (lost rows become index gaps), and
:class:`PtyPlayer` plays byte streams into many ptys at line rate from one thread, cheaply
enough that a load test measures the daemons, not the boards.
"""

from __future__ import annotations

import os
import threading
import time
import tty
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from tactiled.board.frames import encode_frames
from tactiled.files.recording import Recording


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


class PtyPlayer:
    """Plays ``streams`` (bytes each) into one new pty per stream at ``bytes_per_s``, looping; :meth:`run` until ``stop``.

    Each stream should hold whole frames; when it loops, its indices jump back (a restart to the
    reader) unless it is long enough for the run. One thread writes every pty once per ``period_s``.
    """

    def __init__(self, streams: Sequence[bytes], bytes_per_s: float, period_s: float = 0.005, links: Sequence[str] | None = None) -> None:
        self.streams = list(streams)
        self.rate = bytes_per_s
        self.period = period_s
        self.masters: list[int] = []
        self.slaves: list[int] = []
        self.paths: list[str] = []
        self.overruns = 0  # bytes a pty would not take (its reader fell behind)
        for k in range(len(self.streams)):
            master, slave = os.openpty()
            tty.setraw(slave)
            os.set_blocking(master, False)
            self.masters.append(master)
            self.slaves.append(slave)
            path = os.ttyname(slave)
            if links:
                tmp = f"{links[k]}.tmp{os.getpid()}"
                os.symlink(path, tmp)
                os.replace(tmp, links[k])
            self.paths.append(path)

    def run(self, stop: threading.Event) -> None:
        sent = [0] * len(self.streams)
        t0 = time.monotonic()
        while not stop.wait(self.period):  # the write period, not synchronisation
            due = int((time.monotonic() - t0) * self.rate)
            for k, (fd, data) in enumerate(zip(self.masters, self.streams, strict=True)):
                while sent[k] < due:
                    pos = sent[k] % len(data)
                    chunk = data[pos:pos + (due - sent[k])]
                    try:
                        written = os.write(fd, chunk)
                    except (BlockingIOError, OSError):
                        written = 0
                    if written < len(chunk):
                        self.overruns += len(chunk) - written
                        sent[k] = due  # the board does not wait: what did not fit is lost
                        break
                    sent[k] += written

    def close(self) -> None:
        for fd in self.masters + self.slaves:
            os.close(fd)
        self.masters, self.slaves = [], []


def capture_recording_stub(path: str | Path, fs: float, channels: int, volts_per_count: float) -> Recording:
    """An empty recording carrying the first sample index of capture ``path`` (found in its first 64 KiB), for pacing host times."""
    from tactiled.board.frames import FrameDecoder

    runs = FrameDecoder(channels=channels).feed_runs(next(read_chunks(path), b""))
    return Recording(np.zeros((0, channels), dtype=np.int16), fs, volts_per_count, first_index=runs[0].index if runs else 0)
