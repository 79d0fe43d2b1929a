"""``tactiled replay``: recordings and raw captures through the daemon's pipeline, one after the other, and what
``--publish`` sends while they play.

:func:`replay_files` opens each file by its name (:func:`tactiled.files.formats.open_recording`), chooses its model
(:class:`tactiled.learn.choose.ModelChoice`), paces it (:class:`tactiled.run.pacer.Pacer`), replays it
(:func:`tactiled.run.replay.replay_recording`, :func:`~tactiled.run.replay.replay_capture`) and yields one
:class:`Replayed` per file; a file that cannot be read or analysed is one line and the others go on. With a
publisher, :class:`ReplayFeed` sends what the daemon sends, so a subscriber or a bridge on a replay works as on a
live sensor.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from tactiled_client import schema

from tactiled import __version__
from tactiled.config import Config
from tactiled.core.events import PipelineEvent, SlideEnded, SlideResult, SlideResumed, SlideStarted
from tactiled.core.pipeline import FinalCounts
from tactiled.errors import RecordingError, WindowError
from tactiled.files.capture import Capture
from tactiled.files.formats import open_recording
from tactiled.files.recording import Recording
from tactiled.learn.choose import ModelChoice
from tactiled.run.ingest import Batch
from tactiled.run.pacer import Pacer
from tactiled.run.pool import map_files, workers
from tactiled.run.replay import BLOCK, replay_capture, replay_recording
from tactiled.service.publish import Publisher


@dataclass
class Replayed:
    """One file of a replay: its ``path``, the recording replayed (a capture's decoded samples; None if unreadable),
    every slide result in positions of the file, the fingerprint of the ``model`` used ("" for none), and the one-line
    ``error`` that stopped it (None if it played)."""

    path: str
    rec: Recording | None
    results: list[SlideResult]
    model: str = ""
    error: str | None = None


def replay_files(paths: Sequence[str], config: Config, choice: ModelChoice, *, block: int = BLOCK, speed: float | None = None,
                 publish: str | None = None, wait_subscriber_s: float = 0.0, samples: bool = False, jobs: int | None = 1,
                 done: Callable[[int, int], None] | None = None) -> Iterator[Replayed]:
    """Replay ``paths`` in order (see the module docstring). ``block``: samples per block of a recording; ``speed``: times
    real time (None: as fast as possible); ``publish``: an endpoint to send the daemon's messages on (after waiting up to
    ``wait_subscriber_s`` for a first subscriber), with the raw samples if ``samples``. ``jobs``: worker processes over the
    files when neither paced nor published (None or 0: every core, :func:`tactiled.run.pool.map_files`; results still in
    order); ``done(finished, total)`` after each file."""
    if publish is None and speed is None:
        signal_s = sum(_size(p) for p in paths) / BYTES_PER_S  # about: int16 counts of the default sensor
        if workers(jobs, len(paths), signal_s) > 1:
            _choose_once(paths[0], config, choice)  # its notes and checks here, once, not in every worker
        yield from map_files(_replay_one, [(path, config, choice, block) for path in paths], jobs, done, signal_s=signal_s)
        return
    publisher = Publisher(config.override({"publish.endpoint": publish}).publish, see_subscribers=True) if publish else None
    if publisher is not None:
        publisher.wait_subscriber(wait_subscriber_s)
    try:
        for k, path in enumerate(paths):
            yield _replay_path(path, config, choice, block, speed, publisher, samples, last=k == len(paths) - 1)
            if done is not None:
                done(k + 1, len(paths))
    finally:
        if publisher is not None:
            publisher.close()


BYTES_PER_S = 80_000.0  # a 2-channel 20 kHz int16 stream, to guess the seconds of signal in a file from its size


def _size(path: str) -> int:
    try:
        return os.stat(path).st_size
    except OSError:
        return 0


def _stream_of(source: Recording | Capture, config: Config) -> tuple[float, int]:
    """(fs, channels) of a recording, or of a raw capture (the config's sensor: a capture states neither)."""
    s = config.sensor
    return (s.fs, s.channels) if isinstance(source, Capture) else (source.fs, source.channels)


def _choose_once(path: str, config: Config, choice: ModelChoice) -> None:
    """Resolve the model for ``path``'s stream in this process (its one-line notes, its cost check), if it can be read."""
    try:
        source = open_recording(path)
    except RecordingError:
        return
    choice.for_stream(*_stream_of(source, config), path)


def _replay_one(task: tuple[str, Config, ModelChoice, int]) -> Replayed:
    """One file as fast as possible, unpublished (a worker process's task)."""
    path, config, choice, block = task
    return _replay_path(path, config, choice, block, None, None, False, last=True)


def _replay_path(path: str, config: Config, choice: ModelChoice, block: int, speed: float | None, publisher: Publisher | None,
                 samples: bool, last: bool) -> Replayed:
    """One file: opened by its name, its model chosen, paced at ``speed``, published on ``publisher`` (``last``: the
    final status says ``stopping``); a file that cannot be read or analysed is its one-line error."""
    try:
        source = open_recording(path)
    except RecordingError as exc:
        return Replayed(path, None, [], error=str(exc))
    s = config.sensor
    fs, channels = _stream_of(source, config)
    model = choice.for_stream(fs, channels, path)
    fingerprint = getattr(model, "fingerprint", "")
    pacer = Pacer(fs, speed)
    feed = None
    if publisher is not None:
        if isinstance(source, Capture):
            feed = ReplayFeed(publisher, config, fingerprint, pacer, fs=fs, channels=channels, volts_per_count=s.volts_per_count,
                              samples=samples)
        else:
            feed = ReplayFeed(publisher, config, fingerprint, pacer, fs=fs, channels=channels, volts_per_count=source.volts_per_count,
                              integer=source.is_integer, samples=samples)
    try:
        if isinstance(source, Capture):
            results, rec = replay_capture(source, config, model, pacer=pacer, on_event=feed.event if feed else None,
                                          on_batch=feed.batch if feed else None)
        else:
            rec = source
            results = replay_recording(rec, config, model, block=block, pacer=pacer, on_event=feed.event if feed else None,
                                       on_block=feed.block if feed else None)
    except (WindowError, RecordingError) as exc:  # this file's rate or windows cannot be analysed: say which, go on
        return Replayed(path, None, [], fingerprint, f"{path}: {exc}" if path not in str(exc) else str(exc))
    if feed is not None:
        feed.finish(last=last)
    return Replayed(path, rec, results, fingerprint)


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
        level = [round(float(np.sqrt(v / self._window)) * scale, 6) for v in self._sumsq] if self._window else []
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
        self._window = 0

    def finish(self, last: bool = False) -> None:
        """After the file: a status with the final counters (``last``: state ``stopping``, as the daemon's last)."""
        self._status(schema.STATE_STOPPING if last else None)
