"""Pacing a replay: sensor indices at ``speed`` times real time, and the host times that follow from it.

One :class:`Pacer` serves ``--speed`` everywhere (a recording, a raw capture, the messages ``replay --publish``
sends): it waits until the host clock reaches a sample's time, and maps a sample index to the host time at which
the replay reached it (what a live daemon's clock map gives). The first index it sees is its origin, so a capture
whose first index is known only after decoding needs nothing up front. Without a speed, nothing waits and there are
no host times.
"""

from __future__ import annotations

import time
from collections.abc import Callable


class Pacer:
    """Replay pacing at ``speed`` × real time (None or 0: as fast as possible) for a stream of ``fs`` samples/s.

    ``clock`` (monotonic seconds) and ``sleep`` can be replaced in tests.
    """

    def __init__(self, fs: float, speed: float | None, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.fs = fs
        self.speed = speed or None
        self._clock = clock
        self._sleep = sleep
        self.first: int | None = None  # the origin: the first index seen
        self.t0 = 0.0  # monotonic time of the origin

    @property
    def paced(self) -> bool:
        """True if the replay runs at a set speed (then :meth:`host` gives host times)."""
        return self.speed is not None

    def _origin(self, index: int) -> int:
        if self.first is None:
            self.first, self.t0 = index, self._clock()
        return self.first

    def wait(self, index: int) -> None:
        """Return when the host clock has reached sample ``index``'s time (at once if not paced, or if late)."""
        if self.speed is None:
            return
        ahead = self.mono(index) - self._clock()
        if ahead > 0:
            self._sleep(ahead)  # pacing the replay at --speed, not synchronisation

    def mono(self, index: int) -> float:
        """Monotonic host time (s) at which the replay reaches sample ``index`` (paced only)."""
        if self.speed is None:
            raise ValueError("an unpaced replay has no host times")
        return self.t0 + (index - self._origin(index)) / self.fs / self.speed

    def host(self, index: int) -> tuple[float, float]:
        """(monotonic, Unix) host times (s) of sample ``index``, as a live daemon's clock map gives them (paced only)."""
        mono = self.mono(index)
        return mono, mono + (time.time() - time.monotonic())

    @property
    def to_host(self) -> Callable[[int], tuple[float, float]] | None:
        """:meth:`host` when paced, else None (messages then carry no host times)."""
        return self.host if self.speed is not None else None
