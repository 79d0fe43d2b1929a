"""One sensor stream: bytes (a port, a raw capture) or sample blocks (a recording) in, events out, and an explicit end.

Every driver uses this one object, built from a config and a model: the daemon, ``tactiled replay`` of a
recording or a capture, the recorder, the benches and the tests. Nobody wires the ingest core and the
pipeline by hand, and nobody has to remember what the end of a stream or a board restart asks of them:

- **Bytes** (:meth:`Stream.feed_bytes`) go through the ingest core (tactiled/run/ingest.py: decoder, channel
  and gap policies, batches), then the pipeline; a batch after a board restart, or after a gap longer than
  the ring (an unplug: nothing could be analysed across it), ends the stream's slide in progress before it
  goes on.
- **Sample blocks** (:meth:`Stream.feed_samples`) go straight to the pipeline, at their sensor indices.
- **The end** (:meth:`Stream.finish`) is explicit: what the decoder still held, then a slide in progress
  ends at the last sample fed (it gets its final result).
- **A lost port** (:meth:`Stream.disconnected`: the daemon when its port goes, a replay at a recording's
  ``disconnected`` mark) ends a slide in progress at the last sample fed, reason ``disconnected``, and the stream
  goes on with the samples after it. A board restart, a gap longer than the ring or a load shed ends it the same way,
  reason ``interrupted``.

Each call returns a :class:`Step`: the batches decoded (for a recorder or the samples topic), the live
pipeline's events and, with a shadow model, the shadow pipeline's events. Sans-IO: nothing here reads a
port or a clock.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt
from tactiled_client import schema

from tactiled.board.frames import DecoderStats
from tactiled.config import Config
from tactiled.core.events import PipelineEvent, SlideEnded
from tactiled.core.pipeline import Classifier, Pipeline
from tactiled.files.recording import Recording
from tactiled.run.ingest import Batch, Ingest, max_gap_for


@dataclass
class Step:
    """What one call to a :class:`Stream` produced: ``batches`` decoded from bytes (none for sample blocks), the live
    pipeline's ``events``, and the ``shadow`` pipeline's events (empty without a shadow model)."""

    batches: list[Batch] = field(default_factory=list)
    events: list[PipelineEvent] = field(default_factory=list)
    shadow: list[PipelineEvent] = field(default_factory=list)

    def __iadd__(self, other: Step) -> Step:
        self.batches += other.batches
        self.events += other.events
        self.shadow += other.shadow
        return self


class Stream:
    """One sensor's stream (see the module docstring).

    ``fs`` (Hz), ``channels``, ``volts_per_count`` default to ``config.sensor``'s; ``integer``: samples are int16
    counts (False: float volts, from a recording). ``min_batch``: samples the ingest core holds before it hands a
    batch on (bytes only). ``max_gap``: the longest index jump counted as lost samples (default: any the board's
    counter can say, 2**31 - 1; a longer one is a restart). A gap longer than the ring ends a slide in progress.
    ``analyse`` False: decode only (a recorder), no detection and no labels. ``shadow``: a second model run on the
    same samples (:meth:`set_shadow`).
    """

    def __init__(self, config: Config, model: Classifier | None = None, *, fs: float | None = None, channels: int | None = None,
                 volts_per_count: float | None = None, integer: bool = True, min_batch: int = 1, max_gap: int | None = None,
                 analyse: bool = True, shadow: Classifier | None = None) -> None:
        s = config.sensor
        self.config = config
        self.fs = fs if fs is not None else s.fs
        self.channels = channels if channels is not None else s.channels
        self.volts_per_count = volts_per_count if volts_per_count is not None else s.volts_per_count
        self.integer = integer
        self.ingest = Ingest(self.channels, max_gap=max_gap, min_batch=min_batch)
        self.long_gap = max_gap_for(config.ring.seconds, self.fs)  # a gap longer than this ends a slide in progress
        self.pipeline = self._pipeline(model) if analyse else None
        self.shadow: Pipeline | None = None
        self._shadow_asked: tuple[int, Classifier | None] = (0, None)  # the last set_shadow: (its number, its model)
        self._shadow_taken = 0  # the number of the last set_shadow applied (_take_requests)
        self._shadow_waiting: Classifier | None = None  # a shadow model applied, waiting for the live slide in progress to end
        self._swap_asked: tuple[int, Classifier | None] = (0, None)  # the last swap_model: (its number, its model)
        self._swap_taken = 0  # the number of the last swap_model applied
        self.set_shadow(shadow)
        self._take_requests()

    @classmethod
    def for_recording(cls, rec: Recording, config: Config, model: Classifier | None = None) -> Stream:
        """A stream with ``rec``'s rate, channels and scale (its samples go in with :meth:`feed_samples`)."""
        return cls(config, model, fs=rec.fs, channels=rec.channels, volts_per_count=rec.volts_per_count, integer=rec.is_integer)

    def _pipeline(self, model: Classifier | None) -> Pipeline:
        return Pipeline(self.config, self.fs, self.channels, self.volts_per_count, self.integer, model)

    @property
    def stats(self) -> DecoderStats:
        """The ingest core's counters (samples, lost, CRC failures, restarts, ...)."""
        return self.ingest.stats

    @property
    def live(self) -> Pipeline:
        """The live pipeline (a stream made with ``analyse`` False has none: :class:`RuntimeError`)."""
        if self.pipeline is None:
            raise RuntimeError("this stream decodes only (analyse=False)")
        return self.pipeline

    def set_shadow(self, model: Classifier | None) -> None:
        """Run ``model`` in the shadow of the live one (None: no shadow) from the next samples fed on: a shadow running stops
        there, and ``model``'s starts there if no live slide is in progress, else once it has ended. Its pipeline goes on
        from the live one's detector, slide count and ring (:meth:`Pipeline.follow`): the same samples give it the same
        slides, under the same ``slide_id``. Only records the request (one assignment), so it is safe while another thread
        feeds the stream (the daemon answers a control request while a batch is analysed off its loop)."""
        self._shadow_asked = (self._shadow_asked[0] + 1, model)

    def _take_requests(self) -> None:
        """Apply the last :meth:`swap_model` and :meth:`set_shadow` not applied yet, then start the shadow model waiting if no
        live slide is in progress: what feeds or ends the stream calls this first."""
        number, swap = self._swap_asked
        if number != self._swap_taken:
            self._swap_taken = number
            if swap is not None and self.pipeline is not None:
                self.pipeline.swap_model(swap)
        number, model = self._shadow_asked
        if number != self._shadow_taken:
            self._shadow_taken = number
            self.shadow, self._shadow_waiting = None, model
        live = self.pipeline
        if self._shadow_waiting is not None and live is not None and not live.sliding:
            self.shadow = self._pipeline(self._shadow_waiting)
            self.shadow.follow(live)
            self._shadow_waiting = None

    def swap_model(self, model: Classifier) -> None:
        """The live model from the next slide on (from the next samples fed between slides): a slide ends with the model it
        began with. Checked at once (:class:`WindowError` if the ring cannot hold its windows: :meth:`Pipeline.check_model`);
        otherwise only recorded (one assignment) and applied by what next feeds or ends the stream, so it is safe while
        another thread feeds the stream (the daemon answers a reload while a batch is analysed off its loop)."""
        self.live.check_model(model)
        self._swap_asked = (self._swap_asked[0] + 1, model)

    @property
    def next_model(self) -> Classifier | None:
        """The live model from the next slide on: the last :meth:`swap_model` asked, applied or not, else the live pipeline's."""
        number, model = self._swap_asked
        return model if number != self._swap_taken else self.live.model

    def will_analyse(self, end: int) -> bool:
        """True if samples up to absolute index ``end`` complete an analysis window (live or shadow): feature work ahead."""
        return any(p is not None and p.will_analyse(end) for p in (self.pipeline, self.shadow))

    def decode(self, data: bytes | bytearray | memoryview) -> list[Batch]:
        """Bytes through the ingest core only: the batches they complete (hand them to :meth:`process`)."""
        return self.ingest.feed(data)

    def held(self) -> list[Batch]:
        """The samples decoded but still held for the next batch (``min_batch``), as batches, without analysing them:
        for a stop, so that what the counters include reaches the recording too."""
        return self.ingest.flush()

    def process(self, batches: list[Batch]) -> Step:
        """Decoded batches through the pipelines; a batch after a board restart or a gap longer than the ring first ends the
        slide in progress, reason ``schema.END_INTERRUPTED`` (the detector then skips the gap in constant time)."""
        step = Step(batches=batches)
        for b in batches:
            if b.restart or b.lost > self.long_gap:
                step += self._finish_pipelines(schema.END_INTERRUPTED)
            step += self._feed(b.index, b.samples, None)
        return step

    def shed(self) -> Step:
        """Stop analysing until the next batch (load shed): slides in progress end at the last sample fed, reason
        ``schema.END_INTERRUPTED``, and get their final results; the next batch processed, at any later index, starts new
        detectors there (tactiled.core.pipeline.Pipeline.shed)."""
        if self.pipeline is None:
            return Step()
        self._take_requests()
        return Step(events=_ended_by(self.pipeline.shed(), schema.END_INTERRUPTED), shadow=self.shadow.shed() if self.shadow is not None else [])

    def feed_bytes(self, data: bytes | bytearray | memoryview) -> Step:
        """Bytes read from a port or a capture, cut anywhere: the events do not depend on how."""
        return self.process(self.decode(data))

    def feed_samples(self, index: int, samples: npt.NDArray[Any], valid: npt.NDArray[np.bool_] | None = None) -> Step:
        """A block of ``samples`` (n, C) whose first sample has absolute ``index``; ``valid`` (n,) marks the rows that carry
        data (an index gap from the previous block counts as lost samples)."""
        return self._feed(index, samples, valid)

    def replay_samples(self, index: int, samples: npt.NDArray[Any], valid: npt.NDArray[np.bool_] | None = None,
                       block: int = 65536) -> Iterator[tuple[int, Step]]:
        """Offline: a whole recording held in memory, ``samples`` (n, C) (``valid`` (n,)) whose first row has absolute
        ``index``: the steps :meth:`feed_samples` of its blocks of ``block`` rows and then :meth:`finish` would give, in
        less time (:meth:`tactiled.core.pipeline.Pipeline.replay`). Yields (row of each block's first sample, its step),
        then (n, the end's step). The stream is used up."""
        if self.pipeline is None:
            return
        self._take_requests()
        shadow = self.shadow.replay(index, samples, valid, block) if self.shadow is not None else None
        for lo, events in self.pipeline.replay(index, samples, valid, block):
            yield lo, Step(events=events, shadow=next(shadow)[1] if shadow is not None else [])

    def finish(self) -> Step:
        """The explicit end of the stream: what the decoder still held, then a slide in progress ends at the last sample."""
        step = self.process(self.ingest.flush())
        step += self._finish_pipelines()
        return step

    def disconnected(self) -> Step:
        """The sensor's port is gone after the samples fed so far: a slide in progress (live or shadow) ends at the last sample
        fed and gets its final result from the samples before, its end with reason ``schema.END_DISCONNECTED``; the detector goes
        on with the samples fed after. A stream that began in a slide the detector has not yet told from rest (undecided) ends
        as a stream does, one slide so far, and the samples after start a new detector (:meth:`Pipeline.disconnected`)."""
        step = Step()
        self._take_requests()
        if self.pipeline is not None:
            step.events = _ended_by(self.pipeline.disconnected(), schema.END_DISCONNECTED)
        if self.shadow is not None:
            step.shadow = self.shadow.disconnected()
        return step

    def _feed(self, index: int, samples: npt.NDArray[Any], valid: npt.NDArray[np.bool_] | None) -> Step:
        if self.pipeline is None:
            return Step()
        self._take_requests()
        return Step(events=self.pipeline.feed(index, samples, valid),
                    shadow=self.shadow.feed(index, samples, valid) if self.shadow is not None else [])

    def _finish_pipelines(self, reason: str | None = None) -> Step:
        """Slides in progress end at the last sample fed, with ``reason`` where the stream goes on (None: the stream ends)."""
        if self.pipeline is None:
            return Step()
        self._take_requests()
        events = self.pipeline.finish()
        return Step(events=events if reason is None else _ended_by(events, reason),
                    shadow=self.shadow.finish() if self.shadow is not None else [])


def _ended_by(events: list[PipelineEvent], reason: str) -> list[PipelineEvent]:
    """``events`` with each slide end that says the stream ended (``end_of_stream``) saying ``reason`` instead: the stream
    goes on after a lost port or an interruption."""
    return [replace(ev, reason=reason) if isinstance(ev, SlideEnded) and ev.reason == "end_of_stream" else ev for ev in events]
