"""Sensor sample index → host time, from when the samples arrived.

A sample is taken before it arrives: every (index, arrival time) pair is an upper bound on
the time the sample was taken. :class:`ClockMap` keeps the lower envelope of those bounds:
the rate is the slope between the earliest arrivals (relative to the nominal rate) in the
older and the newer half of the last ``span_s`` seconds, and the offset puts the line
through the earliest arrival of all. So mapped times never lie after an arrival, and they
track the board's crystal (its true rate) rather than the nominal one. What stays is the
smallest transport delay (USB + read interval), a constant of a few ms.

A host stall (a busy machine) only delays arrivals, which the envelope ignores. The line is
dropped and measured again only when arrivals stay more than ``reset_s`` after their mapped
time for ``persist_s`` on end (a board restart that continues the timeline); an arrival before
its mapped time (a forward jump, or a board faster than nominal) moves the line down at once.

Driven by the host clock by nature (it measures it); the pipeline never uses it.
"""

from __future__ import annotations

import time
from collections import deque

BUCKET_S = 0.1  # one envelope point per this much host time
MIN_SPAN_S = 2.0  # the rate is the nominal one until arrivals span this long


class ClockMap:
    """Feed :meth:`observe` with (index one past the newest sample received, host monotonic time)."""

    def __init__(self, fs_nominal: float, span_s: float = 30.0, reset_s: float = 0.5, persist_s: float = 1.0) -> None:
        self.fs_nominal = fs_nominal
        self.fs = fs_nominal
        self.span_s = span_s
        self.reset_s = reset_s
        self.persist_s = persist_s
        self._late_since: float | None = None  # host time of the first of a run of arrivals later than reset_s
        self._points: deque[tuple[int, float]] = deque()  # (index, t) earliest arrival per bucket
        self._bucket: tuple[int, float] | None = None
        self._bucket_t0 = 0.0
        self._offset: float | None = None  # host mono time of index 0
        self.resets = 0

    @property
    def ready(self) -> bool:
        return self._offset is not None

    def observe(self, end_index: int, t_mono: float) -> None:
        """Samples up to ``end_index`` (exclusive) had arrived by ``t_mono``."""
        if self._offset is not None:
            if t_mono - self.mono(end_index) <= self.reset_s:
                self._late_since = None
            else:
                self._late_since = t_mono if self._late_since is None else self._late_since
                if t_mono - self._late_since < self.persist_s:
                    return  # a stall so far: a late arrival says nothing new about the line
                self._reset()
        if self._bucket is None:
            self._bucket, self._bucket_t0 = (end_index, t_mono), t_mono
        elif self._delay(end_index, t_mono) < self._delay(*self._bucket):
            self._bucket = (end_index, t_mono)
        if t_mono - self._bucket_t0 >= BUCKET_S or not self._points:
            self._points.append(self._bucket)
            self._bucket, self._bucket_t0 = None, t_mono
            while len(self._points) > 2 and self._points[-1][1] - self._points[0][1] > self.span_s:
                self._points.popleft()
            self._fit()
        elif self._offset is not None:
            self._offset = min(self._offset, t_mono - end_index / self.fs)

    def _reset(self) -> None:
        self._points.clear()
        self._bucket = None
        self._offset = None
        self._late_since = None
        self.fs = self.fs_nominal
        self.resets += 1

    def _delay(self, index: int, t: float) -> float:
        return t - index / self.fs_nominal

    def _fit(self) -> None:
        pts = list(self._points)
        if pts[-1][1] - pts[0][1] >= MIN_SPAN_S:
            half = len(pts) // 2
            a = min(pts[:half], key=lambda p: self._delay(*p))
            b = min(pts[half:], key=lambda p: self._delay(*p))
            if b[1] > a[1] and b[0] > a[0]:
                self.fs = (b[0] - a[0]) / (b[1] - a[1])
        self._offset = min(t - i / self.fs for i, t in pts)

    def mono(self, index: int) -> float:
        """Host monotonic time at which sample ``index`` was taken (estimate), s."""
        if self._offset is None:
            raise ValueError("ClockMap: no samples observed yet")
        return self._offset + index / self.fs

    def host(self, index: int) -> tuple[float, float]:
        """(monotonic, unix) host time of sample ``index``, s."""
        mono = self.mono(index)
        return mono, mono + (time.time() - time.monotonic())
