"""Replay: a recording or a raw capture through the daemon's own :class:`~tactiled.run.stream.Stream`.

A recording becomes the same stream the daemon sees (blocks of samples at their sensor indices, lost rows
marked, the port's losses where the recorder marked them: :func:`replay_recording`); a raw capture (``.bin``: the
bytes read from the port) runs through the whole ingest core, decoder included (:func:`replay_capture`). Results come
back in positions of the file, and are paired here with the file's ground truth (:func:`pair_results`,
:func:`summary_line`).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import replace
from itertools import pairwise
from typing import Any

import numpy as np
from tactiled_client import schema
from tactiled_client.truth import overlapping

from tactiled import __version__
from tactiled.config import Config
from tactiled.core.events import PipelineEvent, SlideResult, SlideResumed
from tactiled.core.matching import match_slides
from tactiled.errors import RecordingError
from tactiled.files.capture import Capture
from tactiled.files.recording import Recording, merge_ranges
from tactiled.run.ingest import Batch, BatchCollector
from tactiled.run.pacer import Pacer
from tactiled.run.pool import map_files
from tactiled.run.stream import Stream

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


def right_answers(truth: Sequence[str], paired: Sequence[SlideResult | None], taught: Collection[str] = ()) -> tuple[int, int]:
    """(true slides answered right, of them slides of a surface the model was not taught called unknown) of ``truth`` and
    the results ``paired`` with them (:func:`pair_results`): a label equal to the truth, or, for a surface not among
    ``taught`` (given), no label with reason ``unknown_surface``, the right answer there (as ``score`` counts it)."""
    right = rejected = 0
    for t, p in zip(truth, paired, strict=True):
        if p is None:
            continue
        if taught and t not in taught and p.label is None and p.reason == "unknown_surface":
            rejected += 1
        elif p.label == t:
            right += 1
    return right + rejected, rejected


def summary_line(results: list[SlideResult], rec: Recording, taught: Collection[str] = ()) -> str:
    """``N slides, L labelled, U unknown surface[, C of T true slides right]`` for one replayed recording; with the model's
    ``taught`` surfaces, a slide of another surface called unknown counts right, and the line says how many."""
    finals = [r for r in results if r.final]
    labelled = sum(r.label is not None for r in finals)
    unknown = sum(r.reason == "unknown_surface" for r in finals)
    line = f"{len(finals)} slides, {labelled} labelled, {unknown} unknown surface"
    truth = rec.slides()
    if truth or rec.label is not None:
        t, paired, _ = pair_results(rec, results)
        right, rejected = right_answers(t, paired, taught)
        line += f", {right} of {len(t)} true slides right" + (f" ({rejected} of a surface the model was not taught, called unknown)"
                                                              if rejected else "")
    lost = samples_lost(rec)
    return line + (f", {lost} samples lost" if lost else "")


def samples_lost(rec: Recording) -> int:
    """Samples lost in ``rec``: its meta's ``samples_lost`` if it says (a replayed capture: every gap, kept as rows or
    not), else the rows its ``lost`` ranges list."""
    counted = rec.meta.get("samples_lost")
    return int(counted) if isinstance(counted, int) else int(merge_ranges(rec.lost)[:, 1].sum())


def _to_file(ev: SlideResult, base: int) -> SlideResult:
    """A result in positions of the file (its sensor indices less ``base``, the file's first index)."""
    return replace(ev, start=ev.start - base, stop=ev.stop - base, window=(ev.window[0] - base, ev.window[1] - base))


def collect(results: list[SlideResult], ev: PipelineEvent, base: int) -> None:
    """Add a result event to ``results`` (positions of the file: sensor index less ``base``); a :class:`SlideResumed`
    takes back the final result it withdraws, so that each slide keeps the one final result that stood."""
    if isinstance(ev, SlideResult):
        results.append(_to_file(ev, base))
    elif isinstance(ev, SlideResumed):
        for i in range(len(results) - 1, -1, -1):
            if results[i].final and results[i].slide_id == ev.slide_id:
                del results[i]
                break


def replay_recording(rec: Recording, config: Config, model: Any | None, *, block: int = BLOCK, pacer: Pacer | None = None,
                     on_event: Callable[[PipelineEvent], None] | None = None,
                     on_block: Callable[[int, np.ndarray, np.ndarray], None] | None = None) -> list[SlideResult]:
    """Run ``rec`` through a fresh :class:`~tactiled.run.stream.Stream` in blocks of ``block`` samples, then end it;
    returns every slide result, in positions of the file (provisional ones before their slide's final one).

    Samples are fed at their sensor indices (``first_index + position``), exactly as the daemon saw them. At each
    position of ``rec.disconnected`` (the host lost the port there) a slide in progress ends as the daemon ended it
    (:meth:`~tactiled.run.stream.Stream.disconnected`: reason ``disconnected``, its label from the rows before), and the
    rows after go on; such a recording is fed block by block, cut at its marks (the daemon's path: about twice the time
    of the whole-file replay of one without marks, measured).
    ``pacer`` paces the blocks (``--speed``); ``on_event`` sees every pipeline event as it happens (sensor indices);
    ``on_block`` every block before the pipeline does: (sensor index of its first row, samples (n, C), valid (n,) bool).
    """
    stream = Stream.for_recording(rec, config, model)
    valid = rec.valid_mask()
    all_valid = bool(valid.all())
    results: list[SlideResult] = []
    base = rec.first_index

    def handle(events: list[PipelineEvent]) -> None:
        for ev in events:
            if on_event:
                on_event(ev)
            collect(results, ev, base)

    n = rec.samples.shape[0]
    marks = [int(d) for d in rec.disconnected]
    if (pacer is not None and pacer.paced) or marks:  # block by block, as they come: the first events at once
        if stream.pipeline is not None:  # a block is written to the ring at once: at most half of it (at 2.2 kHz the default
            block = max(1, min(block, stream.pipeline.ring.capacity // 2))  # 65 536 rows overwrote a third of each before its analysis)
        cuts = [*sorted({*range(0, n, block), *(d for d in marks if d < n)}), n]
        k = 0  # marks handled
        for lo, hi in pairwise(cuts):
            while k < len(marks) and marks[k] <= lo:  # the port was lost after the rows before lo
                handle(stream.disconnected().events)
                k += 1
            if pacer is not None:
                pacer.wait(base + lo)
            if on_block:
                on_block(base + lo, rec.samples[lo:hi], valid[lo:hi])
            handle(stream.feed_samples(base + lo, rec.samples[lo:hi], None if all_valid else valid[lo:hi]).events)
        for _ in marks[k:]:  # lost after the last row
            handle(stream.disconnected().events)
        handle(stream.finish().events)  # a slide still in progress at the end of the file ends there
        return results
    # as fast as possible: the whole file at once (the same events, each block's after on_block saw it)
    for lo, step in stream.replay_samples(base, rec.samples, None if all_valid else valid, block):
        if on_block and lo < n:
            on_block(base + lo, rec.samples[lo: lo + block], valid[lo: lo + block])
        handle(step.events)
    return results


def replay_all(recs: Sequence[Recording], config: Config, model: Any | None, jobs: int | None = None,
               done: Callable[[int, int], None] | None = None) -> Iterator[list[SlideResult]]:
    """:func:`replay_recording` of every recording, spread over ``jobs`` processes (None: every core), in order."""
    return map_files(_replay_task, [(rec, config, model) for rec in recs], jobs, done, signal_s=sum(r.samples.shape[0] / r.fs for r in recs))


def _replay_task(task: tuple[Recording, Config, Any]) -> list[SlideResult]:
    return replay_recording(*task)


def replay_capture(capture: Capture, config: Config, model: Any | None, *, pacer: Pacer | None = None,
                   on_event: Callable[[PipelineEvent], None] | None = None,
                   on_batch: Callable[[Batch], None] | None = None) -> tuple[list[SlideResult], Recording]:
    """A raw capture (``.bin``: the bytes exactly as read from the port) through the daemon's own
    :class:`~tactiled.run.stream.Stream`: the same decoder, channel and gap policies and pipeline as ``tactiled run``
    (``config.sensor`` gives fs, channels and scale); the events do not depend on how the bytes are cut.

    Returns every slide result (positions from the first sample decoded, as for a recording) and the samples
    decoded, as a recording (lost samples listed). Its zero rows for index gaps are bounded by the capture's size
    (:meth:`~tactiled.files.capture.Capture.lost_rows_budget`): past that, the recording ends at the gap that went over
    (meta ``truncated_at``), and meta ``samples`` and ``samples_lost`` count every sample decoded and lost in the whole
    capture. ``pacer``, ``on_event`` as for :func:`replay_recording`; ``on_batch`` sees every decoded batch before the
    pipeline does.
    """
    s = config.sensor
    stream = Stream(config, model)
    try:
        budget = capture.lost_rows_budget()
    except OSError as exc:
        raise RecordingError(f"{capture.path}: cannot read: {exc.strerror or exc}") from None
    collector = BatchCollector(s.channels, max_lost=budget)
    events: list[PipelineEvent] = []

    def run(step_batches: list[Batch], finish: bool = False) -> None:
        for b in step_batches:
            collector.add(b)
            if pacer is not None:
                pacer.wait(b.index)
            if on_batch is not None:
                on_batch(b)
        step = stream.process(step_batches)
        if finish:
            step += stream.finish()
        for ev in step.events:
            if on_event:
                on_event(ev)
            events.append(ev)

    try:
        for data in capture.chunks():
            run(stream.decode(data))
    except OSError as exc:
        raise RecordingError(f"{capture.path}: cannot read: {exc.strerror or exc}") from None
    run([], finish=True)
    base = collector.first_index or 0
    results: list[SlideResult] = []
    for ev in events:
        collect(results, ev, base)
    st = stream.stats
    if st.channel_errors and not collector.samples_seen:  # every intact frame had another layout: nothing was replayed
        raise RecordingError(f"{capture.path}: {stream.ingest.decoder.channel_mismatch(s.id)} (--config)")
    info = {"capture": str(capture.path), "crc_errors": st.crc_errors, "bytes_discarded": st.bytes_discarded, "restarts": st.restarts,
            "channel_errors": st.channel_errors, "duplicate_frames": st.duplicates, "samples": collector.samples_seen,
            "samples_lost": collector.samples_lost}
    if collector.truncated:
        info["truncated_at"] = collector.n
    return results, collector.recording(s.fs, s.volts_per_count, info)
