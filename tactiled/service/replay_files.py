"""``tactiled replay``: recordings and raw captures through the daemon's pipeline, one after the other, and what
``--publish`` sends while they play.

:func:`replay_files` opens each file by its name (:func:`tactiled.files.formats.open_recording`), chooses its model
(:class:`tactiled.learn.choose.ModelChoice`), paces it (:class:`tactiled.run.pacer.Pacer`), replays it
(:func:`tactiled.run.replay.replay_recording`, :func:`~tactiled.run.replay.replay_capture`) and yields one
:class:`Replayed` per file; a file that cannot be read or analysed is one line and the others go on. With a
publisher, :class:`tactiled.service.replay_feed.ReplayFeed` sends what the daemon sends, so a subscriber or a bridge
on a replay works as on a live sensor.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from tactiled.config import Config
from tactiled.core.events import SlideResult
from tactiled.errors import RecordingError, WindowError
from tactiled.files.capture import Capture
from tactiled.files.formats import open_recording
from tactiled.files.recording import Recording
from tactiled.learn.choose import ModelChoice
from tactiled.run.heap import keep_freed_memory
from tactiled.run.pacer import Pacer
from tactiled.run.pool import map_files, workers
from tactiled.run.replay import BLOCK, replay_capture, replay_recording

if TYPE_CHECKING:
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
    publisher = None
    if publish:
        from tactiled.service.publish import BURST_SEND_HWM, Publisher  # ZeroMQ and asyncio only when publishing (start-up)

        publisher = Publisher(config.override({"publish.endpoint": publish}).publish, see_subscribers=True, send_hwm=BURST_SEND_HWM)
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
    keep_freed_memory()  # in this process or a worker's: before the recording and the pipeline's temporaries are made
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
        from tactiled.service.replay_feed import ReplayFeed

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
