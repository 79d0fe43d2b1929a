"""``tactiled replay``: a recording through the daemon's own pipeline.

The recording becomes the same stream the daemon sees (blocks of samples at their sensor
indices, lost rows marked) and runs through :class:`~tactiled.core.pipeline.Pipeline`. A raw
capture (``.bin``: the bytes read from the port) runs through the daemon's whole ingest core,
decoder included (:func:`replay_bytes`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from tactiled_client import schema
from tactiled_client.truth import overlapping

from tactiled import __version__
from tactiled.config import Config
from tactiled.core.matching import match_slides
from tactiled.core.pipeline import Pipeline, PipelineEvent, SlideEnded, SlideResult, SlideStarted
from tactiled.files.recording import Recording
from tactiled.run.ingest import Batch, BatchCollector, Ingest, max_gap_for, run_bytes
from tactiled.run.pool import map_files

BLOCK = 65536  # samples per block fed to the pipeline by default


def truth_of(rec: Recording, start: int, stop: int) -> str | None:
    """The surface of the true slide overlapping [start, stop) most (the file's label without per-slide truth)."""
    truth = rec.slides()
    return overlapping(truth, start, stop) if truth else rec.label


def result_record(file: str, rec: Recording, r: SlideResult, provisional: Sequence[SlideResult] = (), sensor: str = "",
                  model: str = "") -> schema.ReplaySlide:
    """The ``replay --json`` line of one slide (positions in the file): its final roughness message, the truth, the provisional labels."""
    msg = schema.roughness(sensor, r, fs=rec.fs, model=model, version=__version__)
    return schema.ReplaySlide(**msg.to_map(), file=file, slide=r.slide_id, truth=truth_of(rec, r.start, r.stop),
                              duration_s=round((r.stop - r.start) / rec.fs, 4),
                              provisional=[schema.provisional_label(p).to_map() for p in provisional])


def by_slide(results: Sequence[SlideResult]) -> list[tuple[SlideResult, list[SlideResult]]]:
    """(final result, the provisional results before it) per slide, in order; provisional ones of a slide that never ended are dropped."""
    out: list[tuple[SlideResult, list[SlideResult]]] = []
    pending: dict[int, list[SlideResult]] = {}
    for r in results:
        if r.final:
            out.append((r, pending.pop(r.slide_id, [])))
        else:
            pending.setdefault(r.slide_id, []).append(r)
    return out


def pair_results(rec: Recording, results: Sequence[SlideResult]) -> tuple[list[str], list[SlideResult | None], int]:
    """(true label per scored slide, the result paired with it or None, results paired with nothing) for one recording."""
    truth = rec.slides()
    finals = [r for r in results if r.final]
    if truth:
        pairs = match_slides([(r.start, r.stop) for r in finals], [(a, b) for a, b, _ in truth])
        paired = [None if j is None else finals[j] for j in pairs]
        return [str(s) for _, _, s in truth], paired, len(finals) - sum(j is not None for j in pairs)
    if rec.label is not None:
        return [rec.label] * len(finals), list(finals), 0
    return [], [], len(finals)


def summary_line(results: list[SlideResult], rec: Recording) -> str:
    """``N slides, L labelled, U unknown surface[, C of T true slides right]`` for one replayed recording."""
    finals = [r for r in results if r.final]
    labelled = sum(r.label is not None for r in finals)
    unknown = sum(r.reason == "unknown_surface" for r in finals)
    line = f"{len(finals)} slides, {labelled} labelled, {unknown} unknown surface"
    truth = rec.slides()
    if truth or rec.label is not None:
        t, paired, _ = pair_results(rec, results)
        right = sum(p is not None and p.label == x for x, p in zip(t, paired, strict=True))
        line += f", {right} of {len(t)} true slides right"
    return line


def replay_recording(rec: Recording, config: Config, model: Any | None, *, block: int = BLOCK, speed: float | None = None,
                     on_event: Callable[[PipelineEvent], None] | None = None,
                     on_block: Callable[[int, np.ndarray, np.ndarray], None] | None = None) -> list[SlideResult]:
    """Run ``rec`` through a fresh pipeline in blocks of ``block`` samples, then end the stream; returns every slide result.

    Provisional results (``final`` False) come before their slide's final one.

    Samples are fed at their sensor indices (``first_index + position``), exactly as the
    daemon saw them; results are converted back to positions in the file.

    ``speed``: pace the stream at that many times real time (None: as fast as possible).
    ``on_event`` sees every pipeline event as it happens; ``on_block`` every block before the
    pipeline does: (sensor index of its first row, samples (n, C), valid (n,) bool).
    """
    pipeline = Pipeline(config, rec.fs, rec.channels, rec.volts_per_count, rec.is_integer, model)
    valid = rec.valid_mask()
    all_valid = bool(valid.all())
    results: list[SlideResult] = []
    n = rec.samples.shape[0]
    base = rec.first_index
    t0 = time.monotonic()

    def handle(events: list[PipelineEvent]) -> None:
        for ev in events:
            if on_event:
                on_event(ev)
            if isinstance(ev, SlideResult):
                results.append(replace(ev, start=ev.start - base, stop=ev.stop - base, window=(ev.window[0] - base, ev.window[1] - base)))

    for lo in range(0, n, block):
        hi = min(lo + block, n)
        if speed:
            ahead = lo / rec.fs / speed - (time.monotonic() - t0)
            if ahead > 0:
                time.sleep(ahead)  # pacing the replay at --speed, not synchronisation
        if on_block:
            on_block(base + lo, rec.samples[lo:hi], valid[lo:hi])
        handle(pipeline.feed(base + lo, rec.samples[lo:hi], None if all_valid else valid[lo:hi]))
    handle(pipeline.finish())  # a slide still in progress at the end of the file ends there
    return results


def replay_all(recs: Sequence[Recording], config: Config, model: Any | None, jobs: int | None = None,
               done: Callable[[int, int], None] | None = None) -> Iterator[list[SlideResult]]:
    """:func:`replay_recording` of every recording, spread over ``jobs`` processes (None: every core), in order."""
    return map_files(_replay_task, [(rec, config, model) for rec in recs], jobs, done, signal_s=sum(r.samples.shape[0] / r.fs for r in recs))


def _replay_task(task: tuple[Recording, Config, Any]) -> list[SlideResult]:
    return replay_recording(*task)


def replay_bytes(chunks: Iterable[bytes], config: Config, model: Any | None, *, speed: float | None = None,
                 on_event: Callable[[PipelineEvent], None] | None = None, meta: dict[str, Any] | None = None) -> tuple[list[SlideResult], Recording]:
    """Raw serial bytes (a ``.bin`` capture, exactly as read from the port) through the daemon's ingest core and pipeline.

    The same decoder, channel and gap policies and pipeline as ``tactiled run`` (config.sensor
    gives fs, channels and scale); the events do not depend on how the bytes are cut.
    Returns every slide result (positions from the first sample decoded, as for a recording)
    and the samples decoded, as a recording (lost samples listed).
    """
    s = config.sensor
    ingest = Ingest(s.channels, max_gap=max_gap_for(config.ring.seconds, s.fs))
    pipeline = Pipeline(config, s.fs, s.channels, s.volts_per_count, True, model)
    collector = BatchCollector(s.channels)
    events: list[PipelineEvent] = []
    t0 = time.monotonic()

    def on_batch(b: Batch) -> None:
        collector.add(b)
        if speed and collector.first_index is not None:
            ahead = (b.index - collector.first_index) / s.fs / speed - (time.monotonic() - t0)
            if ahead > 0:
                time.sleep(ahead)  # pacing the replay at --speed, not synchronisation

    for ev in run_bytes(chunks, ingest, pipeline, on_batch):
        if on_event:
            on_event(ev)
        events.append(ev)
    base = collector.first_index or 0
    results = [replace(ev, start=ev.start - base, stop=ev.stop - base, window=(ev.window[0] - base, ev.window[1] - base))
               for ev in events if isinstance(ev, SlideResult)]
    st = ingest.stats
    info = {**(meta or {}), "crc_errors": st.crc_errors, "bytes_discarded": st.bytes_discarded, "restarts": st.restarts,
            "channel_errors": st.channel_errors}
    return results, collector.recording(s.fs, s.volts_per_count, info)


class ReplayFeed:
    """What ``replay --publish`` sends for one recording: the daemon's messages, so a bridge on a replay works as on a live sensor.

    Slide and roughness messages (:meth:`event`); with ``samples`` the raw samples on
    ``samples/<id>`` in messages of ``fs / 25`` rows, lost rows zero and listed (:meth:`block`);
    and a status message every ``config.publish.status_interval_s`` of sensor time, counters and
    film levels as the daemon's (state idle or sliding; :meth:`finish` sends the last, ``stopping``).
    Host times: paced (``speed``), when the replay reached each sample; as fast as possible, nil.
    """

    def __init__(self, publisher: Any, config: Config, rec: Recording, model: str, speed: float | None = None, samples: bool = False) -> None:
        self.publisher, self.config, self.rec, self.model, self.speed, self.samples = publisher, config, rec, model, speed, samples
        self.sensor = config.sensor.id
        self._on_event = publisher.replay_handler(self.sensor, rec, model, speed)
        self.t0 = time.monotonic()
        self.chunk = max(1, round(rec.fs / 25))
        self.sliding = False
        self.slides = self.labels = self.unknown = 0
        self.count = self.lost = 0
        self.index = rec.first_index
        self._sumsq = np.zeros(rec.channels)
        self._window = 0
        self._next_status = rec.first_index

    def _to_host(self, index: int) -> tuple[float, float]:
        assert self.speed
        mono = self.t0 + (index - self.rec.first_index) / self.rec.fs / self.speed
        return mono, mono + (time.time() - time.monotonic())

    def event(self, ev: PipelineEvent) -> None:
        """One pipeline event: published as the daemon does, and counted for the status."""
        if isinstance(ev, SlideStarted):
            self.sliding = True
        elif isinstance(ev, SlideEnded):
            self.sliding = False
        elif isinstance(ev, SlideResult) and ev.final:
            self.slides += 1
            self.labels += ev.label is not None
            self.unknown += ev.reason == schema.REASON_UNKNOWN_SURFACE
        self._on_event(ev)

    def block(self, index: int, samples: np.ndarray, valid: np.ndarray) -> None:
        """One block of the replay (sensor index of row 0, (n, C) samples, (n,) valid), before the pipeline sees it."""
        rec = self.rec
        for lo in range(0, samples.shape[0], self.chunk):
            rows, ok = samples[lo:lo + self.chunk], valid[lo:lo + self.chunk]
            first = index + lo
            n = rows.shape[0]
            edges = np.flatnonzero(np.diff(np.concatenate([[0], (~ok).astype(np.int8), [0]])))
            lost = [[int(a), int(b - a)] for a, b in zip(edges[::2], edges[1::2], strict=True)]
            if self.samples:
                counts = rows if rec.is_integer else np.clip(np.rint(rows / rec.volts_per_count), -32768, 32767)
                data = np.where(ok[:, None], counts, 0).astype("<i2").tobytes()
                self.publisher.publish(schema.samples(self.sensor, first, data, n, rec.channels, fs=rec.fs, volts_per_count=rec.volts_per_count,
                                                      lost=lost, to_host=self._to_host if self.speed else None,
                                                      fs_clock=rec.fs * self.speed if self.speed else rec.fs))
            good = rows[ok].astype(np.float64)
            self._sumsq += np.einsum("ij,ij->j", good, good)
            self._window += len(good)
            self.count += int(ok.sum())
            self.lost += n - int(ok.sum())
            self.index = first + n
            if self.index >= self._next_status:
                self._status()
                self._next_status = self.index + max(1, round(self.config.publish.status_interval_s * rec.fs))

    def _status(self, state: str | None = None) -> None:
        rec = self.rec
        scale = rec.volts_per_count if rec.is_integer else 1.0
        level = [round(float(np.sqrt(v / self._window)) * scale, 6) for v in self._sumsq] if self._window else []
        clock: dict[str, Any] = {}
        if self.speed:
            mono, unix = self._to_host(self.index)
            clock = {"clock_index": self.index, "clock_mono": round(mono, 6), "clock_unix": round(unix, 6), "fs_clock": rec.fs * self.speed}
        self.publisher.publish(schema.status(
            self.sensor, state=state or (schema.STATE_SLIDING if self.sliding else schema.STATE_IDLE), samples=self.count,
            samples_lost=self.lost, slides=self.slides, labels=self.labels, unknown=self.unknown, fs_nominal=rec.fs, model=self.model,
            uptime_s=round(time.monotonic() - self.t0, 3), index=self.index, level=level, version=__version__,
            dropped_messages=self.publisher.dropped, **clock))
        self._sumsq[:] = 0.0
        self._window = 0

    def finish(self, last: bool = False) -> None:
        """After the recording: a status with the final counters (``last``: state ``stopping``, as the daemon's last)."""
        self._status(schema.STATE_STOPPING if last else None)
