"""What ``tactiled replay --publish`` sends while a file plays: the daemon's messages (:class:`ReplayFeed`).

Kept apart from :mod:`tactiled.service.replay_files` so that a replay that publishes nothing imports neither the
publisher nor ZeroMQ and asyncio with it (start-up).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import numpy.typing as npt
from tactiled_client import schema

from tactiled import __version__
from tactiled.config import Config
from tactiled.core.events import PipelineEvent, SlideEnded, SlideResult, SlideResumed, SlideStarted
from tactiled.core.features import film_levels
from tactiled.core.pipeline import FinalCounts
from tactiled.run.ingest import Batch
from tactiled.run.pacer import Pacer
from tactiled.service.publish import Publisher


class ReplayFeed:
    """What ``replay --publish`` sends for one file: the daemon's messages, so a bridge on a replay works as on a live sensor.

    Slide and roughness messages (:meth:`event`); with ``samples`` the raw samples on ``samples/<id>`` in messages of
    ``fs / 25`` rows, lost rows zero and listed (:meth:`block`, or :meth:`batch` for a capture's decoded batches); and a
    status message every ``config.publish.status_interval_s`` of sensor time, counters and film levels as the daemon's
    (state idle or sliding; :meth:`finish` sends the last, ``stopping``). Host times come from ``pacer``: when the
    replay reached each sample if paced, nil as fast as possible. ``integer``: samples are int16 counts (False: volts).
    """

    def __init__(self, publisher: Publisher, config: Config, model: str, pacer: Pacer, *, fs: float, channels: int,
                 volts_per_count: float, integer: bool = True, samples: bool = False) -> None:
        self.publisher, self.config, self.model, self.pacer, self.samples = publisher, config, model, pacer, samples
        self.fs, self.channels, self.volts_per_count, self.integer = fs, channels, volts_per_count, integer
        self.sensor = config.sensor.id
        self.t0 = time.monotonic()
        self.chunk = max(1, round(fs / 25))
        self.sliding = False
        self.counts = FinalCounts()
        self._last_final: SlideResult | None = None
        self.count = self.lost = 0
        self.index: int | None = None  # the next sensor index expected
        self._sumsq = np.zeros(channels)
        self._sums = np.zeros(channels)
        self._window = 0
        self._next_status: int | None = None

    @property
    def _fs_clock(self) -> float:
        return self.fs * self.pacer.speed if self.pacer.speed else self.fs

    def event(self, ev: PipelineEvent) -> None:
        """One pipeline event: published as the daemon does, and counted for the status."""
        if isinstance(ev, SlideStarted):
            self.sliding = True
        elif isinstance(ev, SlideEnded):
            self.sliding = False
        elif isinstance(ev, SlideResult) and ev.final:
            self._last_final = ev
            self.counts.add(ev)
        elif isinstance(ev, SlideResumed) and self._last_final is not None:  # that end and label are withdrawn: the slide goes on
            self.sliding = True
            self.counts.withdraw(self._last_final)
            self._last_final = None
        model = ev.model if isinstance(ev, SlideResult) and ev.model else self.model
        self.publisher.publish_event(self.sensor, ev, self.fs, model, time.perf_counter(), self.pacer.to_host)

    def batch(self, b: Batch) -> None:
        """One decoded batch of a capture (its gap from the previous one counted as lost samples)."""
        self.block(b.index, b.samples, np.ones(b.samples.shape[0], dtype=bool))

    def block(self, index: int, samples: npt.NDArray[Any], valid: npt.NDArray[np.bool_]) -> None:
        """One block of the replay (sensor index of row 0, (n, C) samples, (n,) valid), before the pipeline sees it."""
        if self.index is None:
            self.index = self._next_status = index
        lost_before = max(0, index - self.index)  # an index gap between blocks (a capture's lost frames): not sent as rows
        self.lost += lost_before
        for lo in range(0, samples.shape[0], self.chunk):
            rows, ok = samples[lo:lo + self.chunk], valid[lo:lo + self.chunk]
            first = index + lo
            n = rows.shape[0]
            edges = np.flatnonzero(np.diff(np.concatenate([[0], (~ok).astype(np.int8), [0]])))
            lost = [[int(a), int(b - a)] for a, b in zip(edges[::2], edges[1::2], strict=True)]
            if self.samples:
                counts = rows if self.integer else np.clip(np.rint(rows / self.volts_per_count), -32768, 32767)
                data = np.where(ok[:, None], counts, 0).astype("<i2").tobytes()
                self.publisher.publish(schema.samples(self.sensor, first, data, n, self.channels, fs=self.fs,
                                                      volts_per_count=self.volts_per_count, lost=lost, lost_before=lost_before if lo == 0 else 0,
                                                      to_host=self.pacer.to_host, fs_clock=self._fs_clock))
            good = rows[ok].astype(np.float64)
            self._sumsq += np.einsum("ij,ij->j", good, good)
            self._sums += good.sum(axis=0)
            self._window += len(good)
            self.count += int(ok.sum())
            self.lost += n - int(ok.sum())
            self.index = first + n
            assert self._next_status is not None
            if self.index >= self._next_status:
                self._status()
                self._next_status = self.index + max(1, round(self.config.publish.status_interval_s * self.fs))

    def _status(self, state: str | None = None) -> None:
        scale = self.volts_per_count if self.integer else 1.0
        level = film_levels(self._sums, self._sumsq, self._window, scale)
        clock: dict[str, Any] = {}
        if self.pacer.paced and self.index is not None:
            mono, unix = self.pacer.host(self.index)
            clock = {"clock_index": self.index, "clock_mono": round(mono, 6), "clock_unix": round(unix, 6), "fs_clock": self._fs_clock}
        self.publisher.publish(schema.status(
            self.sensor, state=state or (schema.STATE_SLIDING if self.sliding else schema.STATE_IDLE), samples=self.count,
            samples_lost=self.lost, slides=self.counts.slides, labels=self.counts.labels, unknown=self.counts.unknown, fs_nominal=self.fs, model=self.model,
            uptime_s=round(time.monotonic() - self.t0, 3), index=self.index or 0, level=level, version=__version__,
            dropped_messages=self.publisher.dropped, **clock))
        self._sumsq[:] = 0.0
        self._sums[:] = 0.0
        self._window = 0

    def finish(self, last: bool = False) -> None:
        """After the file: a status with the final counters (``last``: state ``stopping``, as the daemon's last)."""
        self._status(schema.STATE_STOPPING if last else None)
