"""``tactiled replay``: recordings and raw captures through the daemon's pipeline, one after the other, and what
``--publish`` sends while they play.

:func:`replay_files` opens each file by its name (:func:`tactiled.files.formats.open_recording`), chooses its model
(:class:`tactiled.learn.choose.ModelChoice`), paces it (:class:`tactiled.run.pacer.Pacer`), replays it
(:func:`tactiled.run.replay.replay_recording`, :func:`~tactiled.run.replay.replay_capture`) and yields one
:class:`Replayed` per file; a file that cannot be read or analysed is one line and the others go on. With a
publisher, :class:`tactiled.service.replay_feed.ReplayFeed` sends what the daemon sends, so a subscriber or a bridge
on a replay works as on a live sensor.

A paced replay (``--speed``: a user watching it as live) hands each slide to ``on_slide`` as soon as its final result
stands (:class:`LiveSlides`), and Ctrl-C there ends it with what was done: the file's :class:`Replayed` says where it
stopped (``interrupted_at``). A ``.bin`` in which no sensor frame is found is a failed file, not a capture of no slides.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from tactiled.config import Config
from tactiled.core.detect import front_end
from tactiled.core.events import PipelineEvent, SlideResult, SlideStarted
from tactiled.errors import ModelError, RecordingError, WindowError
from tactiled.files.capture import Capture
from tactiled.files.formats import open_recording
from tactiled.files.recording import Recording
from tactiled.learn.choose import ModelChoice
from tactiled.run.heap import keep_freed_memory
from tactiled.run.ingest import Batch
from tactiled.run.pacer import Pacer
from tactiled.run.pool import map_files, workers
from tactiled.run.replay import BLOCK, collect, pair_results, replay_capture, replay_recording, right_answers

if TYPE_CHECKING:
    from tactiled.service.publish import Publisher


@dataclass
class Replayed:
    """One file of a replay: its ``path``, the recording replayed (a capture's decoded samples; None if unreadable),
    every slide result in positions of the file, the fingerprint of the ``model`` used ("" for none) and its ``classes``, and the one-line
    ``error`` that stopped it (None if it played). ``interrupted_at``: a paced replay stopped by Ctrl-C in this file, at
    this position (samples of the file fed; ``results`` are those so far); None: the file played to its end."""

    path: str
    rec: Recording | None
    results: list[SlideResult]
    model: str = ""
    error: str | None = None
    interrupted_at: int | None = None
    classes: tuple[str, ...] = ()  # the surfaces the model was taught (none without a model)


OnSlide = Callable[[str, Recording, SlideResult, list[SlideResult], str], None]
"""``on_slide(path, rec, final, provisional, model)``: a slide whose final result stands, in positions of the file, with
the provisional results before it; ``rec`` is the recording (a capture's: its sensor's rate and scale, no samples)."""

LIVE_BLOCK_S = 0.04  # a paced replay's blocks without --block: this much wall time each (the daemon's batch), in fs / 25 rows


def paced_block(fs: float, speed: float) -> int:
    """Samples per block of a replay paced at ``speed``: about :data:`LIVE_BLOCK_S` of wall time (so slides come as they
    would live), a whole number of ``replay --publish``'s samples messages (fs / 25 rows), at most :data:`BLOCK`."""
    rows = max(1, round(fs * LIVE_BLOCK_S))
    return rows * max(1, min(BLOCK // rows, math.ceil(speed)))


class LiveSlides:
    """A paced replay's slides handed to ``on_slide`` as their final results stand, in order, each once.

    A final result can be withdrawn (:class:`~tactiled.core.events.SlideResumed`: the slide went on) until the detector has
    seen ``detector.off_hold_s`` of quiet after its end; so it is handed over once the samples fed reach that far past its
    stop (:meth:`fed`), when the next slide starts, or at the end (:meth:`finish`). What is handed over is exactly what the
    whole replay keeps (:func:`tactiled.run.replay.by_slide`): the final result that stood, with the provisional ones before it.
    """

    def __init__(self, path: str, rec: Recording, model: str, config: Config, on_slide: OnSlide, base: int | None) -> None:
        self.path, self.rec, self.model, self.on_slide = path, rec, model, on_slide
        self.base = base  # the sensor index of the file's first row (a capture's: its first batch's, known once decoded)
        hop = front_end(config.detector, rec.fs).hop  # the detector's hop at this rate
        self.settle = math.ceil(config.detector.off_hold_s * rec.fs) + 2 * hop  # past a final's stop by then, it is no longer withdrawn
        self.results: list[SlideResult] = []  # as the replay collects them (positions of the file)
        self.position = 0  # samples of the file fed to the pipeline so far
        self._shown: set[int] = set()  # id() of the finals handed over
        self._end = 0  # a capture: the end of the batches decoded so far (sensor index)

    def event(self, ev: PipelineEvent) -> None:
        """One pipeline event (sensor indices), as the replay collects it; a new slide means the ones before stand."""
        assert self.base is not None
        collect(self.results, ev, self.base)
        if isinstance(ev, SlideStarted):
            self._release(lambda r: r.slide_id < ev.slide_id)

    def fed(self, index: int) -> None:
        """The pipeline has been fed every sample before sensor index ``index``."""
        if self.base is None:
            return
        self.position = max(self.position, index - self.base)
        self._release(lambda r: r.stop + self.settle <= self.position)

    def block(self, index: int, samples: np.ndarray, valid: np.ndarray) -> None:
        """A recording's block at sensor ``index``, before the pipeline sees it: every block before it was fed."""
        self.fed(index)

    def batch(self, b: Batch) -> None:
        """A capture's decoded batch, before the pipeline sees it (it is fed with the rest of its chunk: :meth:`chunk_done`)."""
        if self.base is None:
            self.base = b.index
        self._end = max(self._end, b.end)

    def chunk_done(self) -> None:
        """A capture's chunk has gone through the pipeline: every batch decoded so far was fed."""
        if self._end:
            self.fed(self._end)

    def finish(self) -> None:
        """The file ended (or was interrupted): every final result left stands as the replay's."""
        self._release(lambda r: True)

    def _release(self, stands: Callable[[SlideResult], bool]) -> None:
        for r in self.results:
            if not r.final or id(r) in self._shown:
                continue
            if not stands(r):
                return  # in order: a later slide waits for this one
            self._shown.add(id(r))
            self.on_slide(self.path, self.rec, r, [p for p in self.results if not p.final and p.slide_id == r.slide_id], self.model)


@dataclass(frozen=True)
class _WatchedCapture(Capture):
    """A capture whose reader calls ``done()`` each time the chunk it gave has been replayed (when the next is asked for)."""

    done: Callable[[], None] = field(default=lambda: None, compare=False)

    def chunks(self, size: int = 1 << 16) -> Iterator[bytes]:
        """The capture's bytes in pieces of ``size``, ``done()`` called after each has been replayed."""
        for data in super().chunks(size):
            yield data
            self.done()


def interrupted_line(results: list[SlideResult], rec: Recording, position: int, size: int | None, taught: Collection[str] = ()) -> str:
    """The summary of a file a paced replay was stopped in: where (``position`` of ``size`` samples; None: not known, a
    capture), the slides so far, and against the truth, the true slides that had ended by then."""
    finals = [r for r in results if r.final]
    labelled = sum(r.label is not None for r in finals)
    unknown = sum(r.reason == "unknown_surface" for r in finals)
    of = f" of {size / rec.fs:.1f} s" if size is not None else ""
    line = f"interrupted at {position / rec.fs:.1f} s{of}: {len(finals)} slides, {labelled} labelled, {unknown} unknown surface"
    if rec.slide_start is not None and rec.slide_stop is not None:
        ended = np.asarray(rec.slide_stop) <= position
        so_far = replace(rec, slide_start=np.asarray(rec.slide_start)[ended], slide_stop=np.asarray(rec.slide_stop)[ended],
                         surface=None if rec.surface is None else np.asarray(rec.surface)[ended])
        if not ended.any():
            return line + ", 0 true slides ended"
    elif rec.label is not None:
        so_far = rec
    else:
        return line
    truth, paired, _ = pair_results(so_far, finals)
    right, rejected = right_answers(truth, paired, taught)
    return line + f", {right} of {len(truth)} true slides right (those ended by then" + (
        f"; {rejected} of a surface the model was not taught, called unknown)" if rejected else ")")


def replay_files(paths: Sequence[str], config: Config, choice: ModelChoice, *, block: int | None = None, speed: float | None = None,
                 publish: str | None = None, wait_subscriber_s: float = 0.0, samples: bool = False, jobs: int | None = 1,
                 done: Callable[[int, int], None] | None = None, on_slide: OnSlide | None = None) -> Iterator[Replayed]:
    """Replay ``paths`` in order (see the module docstring). ``block``: samples per block of a recording (None: :data:`BLOCK`,
    or :func:`paced_block` when paced); ``speed``: times real time (None: as fast as possible); ``publish``: an endpoint to
    send the daemon's messages on (after waiting up to ``wait_subscriber_s`` for a first subscriber), with the raw samples if
    ``samples``. ``jobs``: worker processes over the files when neither paced nor published nor handing slides over (None or
    0: every core, :func:`tactiled.run.pool.map_files`; results still in order); ``done(finished, total)`` after each file.

    ``on_slide``: each slide as its final result stands, while the file plays (:class:`LiveSlides`); with it, Ctrl-C
    (KeyboardInterrupt) ends the replay with the file it stopped in (:attr:`Replayed.interrupted_at`), whose standing
    slides were handed over first, and no file after it."""
    if publish is None and speed is None and on_slide is None:
        signal_s = sum(_size(p) for p in paths) / BYTES_PER_S  # about: int16 counts of the default sensor
        if workers(jobs, len(paths), signal_s) > 1:
            _choose_once(paths[0], config, choice)  # its notes and checks here, once, not in every worker
        yield from map_files(_replay_one, [(path, config, choice, block or BLOCK) for path in paths], jobs, done, signal_s=signal_s)
        return
    publisher = None
    if publish:
        from tactiled.service.publish import BURST_SEND_HWM, Publisher  # ZeroMQ and asyncio only when publishing (start-up)

        publisher = Publisher(config.override({"publish.endpoint": publish}).publish, see_subscribers=True, send_hwm=BURST_SEND_HWM)
        publisher.wait_subscriber(wait_subscriber_s)
    try:
        for k, path in enumerate(paths):
            played = _replay_path(path, config, choice, block, speed, publisher, samples, last=k == len(paths) - 1, on_slide=on_slide)
            yield played
            if played.interrupted_at is not None:
                return
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
        choice.for_stream(*_stream_of(source, config), path)
    except (RecordingError, ModelError):  # said where that file is replayed, as its one line
        return


def _replay_one(task: tuple[str, Config, ModelChoice, int]) -> Replayed:
    """One file as fast as possible, unpublished (a worker process's task)."""
    path, config, choice, block = task
    return _replay_path(path, config, choice, block, None, None, False, last=True)


def _replay_path(path: str, config: Config, choice: ModelChoice, block: int | None, speed: float | None, publisher: Publisher | None,
                 samples: bool, last: bool, on_slide: OnSlide | None = None) -> Replayed:
    """One file: opened by its name, its model chosen, paced at ``speed``, published on ``publisher`` (``last``: the
    final status says ``stopping``), its slides handed to ``on_slide`` as they stand; a file that cannot be read or
    analysed, or a capture in which no sensor frame is found, is its one-line error."""
    keep_freed_memory()  # in this process or a worker's: before the recording and the pipeline's temporaries are made
    try:
        source = open_recording(path)
    except RecordingError as exc:
        return Replayed(path, None, [], error=str(exc))
    s = config.sensor
    fs, channels = _stream_of(source, config)
    try:
        model = choice.for_stream(fs, channels, path)
    except ModelError as exc:  # a model of another rate or channel count than this file: its line, and the others go on
        return Replayed(path, None, [], error=str(exc))
    fingerprint = getattr(model, "fingerprint", "")
    taught = tuple(getattr(model, "classes", ()) or ())
    pacer = Pacer(fs, speed)
    if block is None:
        block = paced_block(fs, speed) if speed else BLOCK
    feed = None
    if publisher is not None:
        from tactiled.service.replay_feed import ReplayFeed

        if isinstance(source, Capture):
            feed = ReplayFeed(publisher, config, fingerprint, pacer, fs=fs, channels=channels, volts_per_count=s.volts_per_count,
                              samples=samples)
        else:
            feed = ReplayFeed(publisher, config, fingerprint, pacer, fs=fs, channels=channels, volts_per_count=source.volts_per_count,
                              integer=source.is_integer, samples=samples)
    live = None
    if on_slide is not None:
        shown = Recording(np.zeros((0, channels), dtype=np.int16), fs, s.volts_per_count) if isinstance(source, Capture) else source
        live = LiveSlides(path, shown, fingerprint, config, on_slide, None if isinstance(source, Capture) else source.first_index)
    on_event = _both(feed.event if feed else None, live.event if live else None)
    try:
        if isinstance(source, Capture):
            capture = source if live is None else _WatchedCapture(source.path, live.chunk_done)
            results, rec = replay_capture(capture, config, model, pacer=pacer, on_event=on_event,
                                          on_batch=_both(feed.batch if feed else None, live.batch if live else None))
            if not rec.meta.get("samples"):  # not one frame decoded: not a capture of this sensor's port (or an empty one)
                return Replayed(path, None, [], fingerprint, no_frame(path, rec))
        else:
            rec = source
            results = replay_recording(rec, config, model, block=block, pacer=pacer, on_event=on_event,
                                       on_block=_both(feed.block if feed else None, live.block if live else None))
    except (WindowError, RecordingError) as exc:  # this file's rate or windows cannot be analysed: say which, go on
        return Replayed(path, None, [], fingerprint, f"{path}: {exc}" if path not in str(exc) else str(exc))
    except KeyboardInterrupt:
        if live is None:
            raise
        live.finish()  # what was done: every slide ended so far
        if feed is not None:
            feed.finish(last=True)
        return Replayed(path, live.rec, live.results, fingerprint, interrupted_at=live.position, classes=taught)
    if feed is not None:
        feed.finish(last=last)
    if live is not None:
        live.finish()
    return Replayed(path, rec, results, fingerprint, classes=taught)


def no_frame(path: str, rec: Recording) -> str:
    """The one line of a ``.bin`` in which no sensor frame was found (``rec``: what its replay decoded)."""
    size, m = _size(path), rec.meta
    failures = f" ({m['crc_errors']} frames failed their CRC)" if m.get("crc_errors") else ""
    what = "an empty file" if not size else f"not a raw capture of the sensor's port{failures}"
    return f"{path}: no sensor frame in {size} bytes: {what}"


def _both(*calls: Callable[..., None] | None) -> Callable[..., None] | None:
    """One callback calling each of ``calls`` that is not None, in order (None if none is)."""
    given = [c for c in calls if c is not None]
    if not given:
        return None
    if len(given) == 1:
        return given[0]

    def each(*args: object) -> None:
        for call in given:
            call(*args)
    return each
