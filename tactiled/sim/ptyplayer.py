"""Byte streams played into ptys at a line rate, as boards would send them, from one thread.

Cheap enough that a load test measures the daemons, not the boards (bench/bench_load.py, bench/latency.py).
"""

from __future__ import annotations

import os
import threading
import time
import tty
from collections.abc import Sequence


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
        """Write each stream into its pty at ``bytes_per_s``, every ``period_s``, until ``stop`` is set; what a full pty refuses is lost (``overruns``)."""
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
        """Close both ends of every pty."""
        for fd in self.masters + self.slaves:
            os.close(fd)
        self.masters, self.slaves = [], []
