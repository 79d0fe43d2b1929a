"""The streaming pipeline shared by the daemon, replay, scoring and the demo.

samples (index, (n, C), valid) → ring buffer → slide detector → windows of the slide →
spike removal + features (only those the model uses) → model scores → events. Driven by
the sample index only: the same samples in any block sizes give the same events.

A slide is cut into successive windows (:meth:`AnalysisSettings.spans`); each is analysed
as soon as the ring holds it, while the slide goes on. After each window the scores so
far are combined (:meth:`Classifier.assess_many`: probabilities, the calibrated confidence that the
top class is right, and the novelty); when the confidence first reaches
``classifier.provisional_confidence`` (and again whenever the leading label changes
while above it) and the slide is not novel, a provisional :class:`SlideResult` (``final=False``)
is emitted; not from windows that reach into a quiet of the slide (:class:`~tactiled.core.events.Quiet`) until the
slide turns out to go on (:class:`~tactiled.core.events.Loud`): a window past the slide's end would give its last
provisional label from the lift-off. When the slide ends, the windows that lie inside it are fused into the final
result. The end is published as soon as the detector's short quiet (:class:`~tactiled.core.events.Pause`,
``detector.end_hold_s``) says it probably came, not after the whole ``off_hold_s``: if the slide goes on, a
:class:`SlideResumed` withdraws that end and label, and a new pair follows when it really ends. In the final result, a novelty above 1 gives no label, with
reason ``unknown_surface``. Windows that could not be analysed (lost samples, too short, ...) are skipped; a slide with
none gets no label and the most common reason. :meth:`Pipeline.finish` ends the stream:
a slide still running is analysed as far as it goes.
"""

from __future__ import annotations

import copy
import time
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, cast

import numpy as np
import numpy.typing as npt

from tactiled.config import Config, DetectorConfig
from tactiled.core.analysis import Analyser, AnalysisSettings, WindowResult
from tactiled.core.detect import SlideDetector, front_end_settings
from tactiled.core.events import (
    DetectorEvent,
    Loud,
    Offset,
    Onset,
    Pause,
    PipelineEvent,
    Quiet,
    Resume,
    SlideEnded,
    SlideResult,
    SlideResumed,
    SlideStarted,
)
from tactiled.core.ringbuffer import HeldSamples, RingBuffer
from tactiled.errors import OverwrittenError, WindowError

AHEAD = 16  # windows analysed in one call when a replay analyses ahead: as fast as 32, half the temporaries (~1.3 MB each)


class Classifier(Protocol):
    """What the pipeline needs of a model (see :class:`tactiled.learn.model.Model`)."""

    classes: list[str]
    fingerprint: str
    settings: AnalysisSettings

    def assess_many(self, features: npt.NDArray[np.float64], rows: Sequence[tuple[int, int]],
                    final: bool = True) -> tuple[npt.NDArray[np.float64], list[float], list[float | None]]:
        """(probabilities (q, K), calibrated confidences that the top class is right (q,), novelties or None (q,)) of q slides in
        one call, slide i the windows ``features[lo:hi]`` ((lo, hi) = ``rows[i]``) of raw features (n, F); ``final``: whole
        slides, else each slide's first windows (provisional labels). Row i is the same, bit for bit, as slide i alone."""



def start_level(model: Classifier | None, config: DetectorConfig) -> float | None:
    """The detector's :attr:`~tactiled.core.detect.SlideDetector.start_level` that ``model`` learnt from its training recordings
    (``start_level``), if it was measured under ``config``'s front end (``start_front``: another mains notch or band gives
    other envelope values, and a rest above the level would be one slide for good); None: none learnt, no model, or other
    settings."""
    level = getattr(model, "start_level", None)
    return float(level) if level is not None and getattr(model, "start_front", None) == front_end_settings(config) else None


@dataclass
class FinalCounts:
    """Final results that stand: slides, those labelled, those withheld as unknown_surface, and ends withdrawn (``resumed``)."""

    slides: int = 0
    labels: int = 0
    unknown: int = 0
    resumed: int = 0

    def add(self, result: SlideResult, sign: int = 1) -> None:
        """Count a final result (``sign`` -1: take a withdrawn one back out)."""
        self.slides += sign
        self.labels += sign * (result.label is not None)
        self.unknown += sign * (result.reason == "unknown_surface")

    def withdraw(self, result: SlideResult) -> None:
        """A final result withdrawn because its slide went on."""
        self.add(result, -1)
        self.resumed += 1


@dataclass
class _Window:
    span: tuple[int, int]
    result: WindowResult

    @property
    def usable(self) -> bool:
        return self.result.features is not None

    @property
    def features(self) -> npt.NDArray[np.float64]:
        """The window's features (F,) (a usable window's)."""
        assert self.result.features is not None
        return self.result.features


Assessed = tuple[npt.NDArray[np.float64], float, float | None]  # one slide of Classifier.assess_many: probabilities (K,), confidence, novelty
AssessmentKey = tuple[tuple[tuple[int, int], ...], bool]  # replay's assessments ahead: (the windows' spans, final)


def _assessment_keys(used: list[_Window], ends: Iterable[int], final: bool) -> list[AssessmentKey]:
    """The key of the assessment of the first ``end`` of a slide's usable windows ``used`` for each of ``ends`` (``final``:
    the whole slide)."""
    spans = [w.span for w in used]
    return [(tuple(spans[:end]), final) for end in ends]


class Pipeline:
    """Feed blocks in order with :meth:`feed`, end with :meth:`finish`; both return the events completed."""

    def __init__(self, config: Config, fs: float, channels: int, volts_per_count: float, integer: bool = True,
                 model: Classifier | None = None, settings: AnalysisSettings | None = None) -> None:
        self.fs = fs
        self.channels = channels
        self.model = model
        self.settings = model.settings if model is not None else (settings or AnalysisSettings.from_config(config, channels, fs))
        self.min_confidence = config.classifier.min_confidence
        self.provisional_confidence = config.classifier.provisional_confidence
        self.counts = FinalCounts()
        self._analyser_args = (fs, volts_per_count, integer, config.classifier.max_saturated, config.classifier.max_lost)
        self.analyser = Analyser(self.settings, *self._analyser_args)
        self.min_samples = self.analyser.plan.min_samples()
        self._pending_model: Classifier | None = None
        window = round(self.settings.duration_s * fs)
        capacity = max(round(config.ring.seconds * fs), 2 * window + round(config.detector.off_hold_s * fs) + round(fs))
        self.ring = RingBuffer(capacity, channels, np.int16 if integer else np.float64)
        self._reader: RingBuffer | HeldSamples = self.ring  # where windows are read: the ring, or a whole recording (replay)
        self._ahead: dict[tuple[int, int], _Window] = {}  # windows analysed ahead of need (replay), by span
        self._assessed: dict[AssessmentKey, Assessed] = {}  # replay: assessed ahead, by (windows' spans, final)
        self._detector_args = (config.detector, fs, channels, start_level(model, config.detector))
        self.detector = SlideDetector(*self._detector_args)
        self._fresh_detector = False  # after shed(): the next samples fed start a new detector
        self.volts_per_count = volts_per_count if integer else 1.0
        self._slide_id = -1
        self._onset: int | None = None
        self._windows: list[_Window] = []
        self._next: tuple[int, int] | None = None  # the next window of the slide in progress
        self._provisional: str | None = None
        self._paused: SlideResult | None = None  # the final result published at a Pause, while the quiet lasts
        self._quiet: int | None = None  # where the slide in progress went quiet (a Quiet not yet followed by Loud, Pause or Offset)
        self._held = 0  # usable windows since then, whose provisional results wait for the quiet to turn out a dip

    @property
    def slides(self) -> int:
        """Slides with a final result that stands."""
        return self.counts.slides

    @property
    def labels(self) -> int:
        """... of them labelled."""
        return self.counts.labels

    @property
    def unknown(self) -> int:
        """... of them withheld as unknown_surface."""
        return self.counts.unknown

    @property
    def resumed(self) -> int:
        """Ends withdrawn because the slide went on."""
        return self.counts.resumed

    @property
    def sliding(self) -> bool:
        """True while a slide is in progress (its onset seen, its offset not yet)."""
        return self._onset is not None

    def swap_model(self, model: Classifier) -> None:
        """Use ``model`` from the next slide on (at once if no slide is in progress): a slide ends with the model it began with.

        The new model's windows and features replace the old ones with it; the ring must hold two of its windows.
        """
        self.check_model(model)
        self._pending_model = model
        if self._onset is None:
            self._take_pending_model()

    def check_model(self, model: Classifier) -> None:
        """Raise :class:`WindowError` if the ring cannot hold two of ``model``'s windows (:meth:`swap_model` would refuse it)."""
        window = round(model.settings.duration_s * self.fs)
        if 2 * window > self.ring.capacity:
            raise WindowError("window_too_short", f"the model's {model.settings.duration_s:g} s windows do not fit the ring "
                              f"({self.ring.capacity / self.fs:g} s): raise ring.seconds")

    def follow(self, other: Pipeline) -> None:
        """Go on in step with ``other``, the live pipeline of the same stream (the same detector settings), between its slides:
        a shadow model started mid-stream. A copy of its detector, so that the samples fed to both from now on give the
        same slides; its slide count, so that they have the same ``slide_id``; and the samples its ring holds, so that a
        slide whose onset lies before the next samples is read in full."""
        if other.sliding:
            raise ValueError("Pipeline.follow: the pipeline to follow has a slide in progress (a shadow starts between slides)")
        self.detector = copy.deepcopy(other.detector)
        self._detector_args = other._detector_args  # its detectors after a gap too: the live model's start level, not this one's
        self._fresh_detector = other._fresh_detector
        self._slide_id = other._slide_id
        ring = other.ring
        if ring.end > ring.oldest:
            samples, valid = ring.read(ring.oldest, ring.end)
            self.ring.write(ring.oldest, samples, valid)

    def _take_pending_model(self) -> None:
        if self._pending_model is None:
            return
        self.model, self._pending_model = self._pending_model, None
        self._detector_args = (*self._detector_args[:3], start_level(self.model, self._detector_args[0]))  # a new detector (after a gap) takes its level
        if self.detector.undecided and self.detector.start_level is None:  # and one still undecided (the stream's start unknown)
            self.detector.start_level = self._detector_args[3]
        self.settings = self.model.settings
        self.analyser = Analyser(self.settings, *self._analyser_args)
        self.min_samples = self.analyser.plan.min_samples()

    def will_analyse(self, end: int) -> bool:
        """True if feeding samples up to absolute index ``end`` completes a window of the slide in progress (feature work)."""
        return self._onset is not None and self._next is not None and end >= self._next[1]

    def shed(self) -> list[PipelineEvent]:
        """Stop analysing (load shed: the caller cannot keep up): a slide in progress ends at the last sample fed and gets
        its final result, as at the end of a stream. The next block fed, at any later index, starts a new detector there,
        so the samples skipped in between cost nothing (they are not walked as lost samples)."""
        events = self.finish()
        self._fresh_detector = True
        return events

    def disconnected(self) -> list[PipelineEvent]:
        """The sensor's port is gone after the samples fed so far: a slide in progress ends at the last sample fed and gets its
        final result (reason ``end_of_stream``; the caller names it). A stream that began in a slide not yet known as one (the
        detector undecided) ends there as at the end of a stream (:meth:`SlideDetector.finish`: the whole stream so far one
        slide), and the samples after the port comes back start a new detector: that stream, too, may begin in a slide."""
        if self.detector.undecided:
            self._fresh_detector = True
        elif not self.sliding:
            return []
        return self.finish()

    def feed(self, index: int, samples: npt.NDArray[Any], valid: npt.NDArray[np.bool_] | None = None) -> list[PipelineEvent]:
        """Process ``samples`` (n, C) whose first sample has absolute ``index`` (gaps are lost samples)."""
        self.ring.write(index, samples, valid)
        if self._fresh_detector:  # a new detector starts at the first sample that carries data: lost rows before it are no stream
            skip = 0 if valid is None else int(np.argmax(valid)) if valid.any() else samples.shape[0]
            if skip == samples.shape[0]:
                return self._analyse_ready()
            self.detector = SlideDetector(*self._detector_args)
            self._fresh_detector = False
            index, samples, valid = index + skip, samples[skip:], None if valid is None else valid[skip:]
        events = self._handle(self.detector.feed(index, self._volts(samples, valid), valid))  # the detector treats index gaps as lost itself
        events += self._analyse_ready()
        return events

    def _volts(self, samples: npt.NDArray[Any], valid: npt.NDArray[np.bool_] | None) -> npt.NDArray[np.float64]:
        """The detector's input: ``samples`` (n, C) in volts, float64 (one pass), 0 where not ``valid`` (n,)."""
        volts: npt.NDArray[np.float64] = np.multiply(samples, self.volts_per_count, dtype=np.float64)
        if valid is not None:
            volts[~valid] = 0.0
        return volts

    def replay(self, index: int, samples: npt.NDArray[Any], valid: npt.NDArray[np.bool_] | None = None,
               block: int = 65536) -> Iterator[tuple[int, list[PipelineEvent]]]:
        """Offline: a whole recording held in memory, ``samples`` (n, C) (``valid`` (n,)) whose first row has absolute ``index``,
        with the events of :meth:`feed` of its blocks of ``block`` rows and then of :meth:`finish`: yields (row of the block's
        first sample, its events), then (n, the end's events). The same events as feeding those blocks, in less time.

        Three passes: the detector over every block (its events do not depend on the analysis); every window those slides
        need (:meth:`_needs`), analysed in batches of ``AHEAD`` windows read straight from ``samples`` (no ring), and every
        assessment of them the events will ask for in one call (:meth:`_assess_ahead`); then the events, block by block,
        with those windows and assessments (any other is analysed or assessed when asked for, as in :meth:`feed`).
        """
        n = samples.shape[0]
        steps: list[tuple[int, list[DetectorEvent]]] = []
        for lo in range(0, n, block):
            rows = slice(lo, min(n, lo + block))
            ok = None if valid is None else valid[rows]
            steps.append((lo, self.detector.feed(index + lo, self._volts(samples[rows], ok), ok)))
        end_events = self.detector.finish()
        self._reader = held = HeldSamples(index, samples, valid)
        held.end = index + n
        needs = self._needs([ev for _, evs in steps for ev in evs] + end_events)
        spans = sorted({sp for group, _ in needs for sp in group})
        for i in range(0, len(spans), AHEAD):
            self._ahead.update((w.span, w) for w in self._analyse(spans[i: i + AHEAD]))
        self._assess_ahead(needs)
        for lo, evs in steps:
            held.end = index + min(n, lo + block)
            yield lo, self._handle(evs) + self._analyse_ready()
        yield n, self._handle(end_events)
        self._ahead.clear()
        self._assessed.clear()

    def _needs(self, events: Iterable[DetectorEvent]) -> list[tuple[list[tuple[int, int]], bool]]:
        """What the pipeline reads for these detector events (all of a stream, in order), as (window spans, whole): a slide's
        windows up to its Offset's ``at`` (:meth:`_analyse_ready`; whole False: each prefix is assessed for a provisional
        label), and those :meth:`_final` reads at each Pause and Offset (whole True: assessed together)."""
        s, fs = self.settings, self.fs
        hop = max(1, round(s.hop() * fs))
        out: list[tuple[list[tuple[int, int]], bool]] = []
        onset: int | None = None
        for ev in events:
            if isinstance(ev, Onset):
                onset = ev.start
            elif isinstance(ev, Offset | Pause):
                if isinstance(ev, Offset) and onset is not None:
                    lo, hi = s.first_span(onset, fs)
                    group: list[tuple[int, int]] = []
                    while hi <= ev.at and not (s.max_windows and len(group) >= s.max_windows):
                        group.append((lo, hi))
                        lo, hi = lo + hop, hi + hop
                    out.append((group, False))
                    onset = None
                if not (isinstance(ev, Offset) and ev.reason == "too_short"):
                    out.append((s.spans(ev.start, ev.stop, fs, self.min_samples), True))
        return out

    def _assess_ahead(self, needs: list[tuple[list[tuple[int, int]], bool]]) -> None:
        """Every assessment of the windows analysed ahead that :meth:`_provisional_results` (each prefix of a slide's usable
        windows) and :meth:`_final` (all of them) can ask for these ``needs`` (:meth:`_needs`), in one
        :meth:`Classifier.assess_many` call for each kind, kept by (the windows' spans, final)."""
        if self.model is None:
            return
        for final in (False, True):
            features: list[npt.NDArray[np.float64]] = []
            rows: list[tuple[int, int]] = []
            keys: list[AssessmentKey] = []
            for group, whole in needs:
                used = [self._ahead[sp] for sp in group if self._ahead[sp].usable]
                if whole != final or not used:
                    continue
                ends = [len(used)] if final else range(1, len(used) + 1)  # the whole slide, or each prefix (provisional)
                rows += [(len(features), len(features) + end) for end in ends]
                keys += _assessment_keys(used, ends, final)
                features += [w.features for w in used]
            if rows:
                proba, confidence, novelty = self.model.assess_many(np.stack(features), rows, final)
                self._assessed.update((key, (proba[i], confidence[i], novelty[i])) for i, key in enumerate(keys))

    def finish(self) -> list[PipelineEvent]:
        """End of stream: a slide in progress ends at the last sample fed and gets its final result."""
        return self._handle(self.detector.finish())

    def _handle(self, detector_events: list[DetectorEvent]) -> list[PipelineEvent]:
        events: list[PipelineEvent] = []
        for ev in detector_events:
            # windows the ring held when the detector decided come first: the same order whatever the block size
            events += self._analyse_ready(until=ev.at if ev.at >= 0 else None)
            if isinstance(ev, Quiet):
                self._quiet, self._held = ev.stop, 0
            elif isinstance(ev, Loud):  # a dip: the windows held over it are the slide's, and get their provisional results
                held, self._quiet, self._held = self._held, None, 0
                events += self._provisional_results(time.perf_counter(), held)
            elif isinstance(ev, Onset):
                self._slide_id += 1
                self._onset = ev.start
                self._windows = []
                self._provisional = None
                self._quiet, self._held = None, 0
                self._next = self.settings.first_span(ev.start, self.fs)
                events.append(SlideStarted(self._slide_id, ev.start))
                events += self._analyse_ready(until=ev.at if ev.at >= 0 else None)
            elif isinstance(ev, Pause):
                self._held = 0  # windows past the slide's end: no provisional label from them
                events.append(SlideEnded(self._slide_id, ev.start, ev.stop, "quiet"))
                self._paused = self._final(ev.start, ev.stop)
                self.counts.add(self._paused)
                events.append(self._paused)
            elif isinstance(ev, Resume):
                self._quiet, self._held = None, 0
                if self._paused is not None:
                    self.counts.withdraw(self._paused)
                    events.append(SlideResumed(self._slide_id, ev.start, ev.stop))
                self._paused = None
            elif isinstance(ev, Offset):
                paused, self._paused = self._paused, None
                if paused is None or paused.stop != ev.stop:  # else its end and label were published at the Pause
                    if paused is not None:
                        self.counts.withdraw(paused)
                        events.append(SlideResumed(self._slide_id, ev.start, paused.stop))
                    events.append(SlideEnded(self._slide_id, ev.start, ev.stop, ev.reason))
                    if ev.reason != "too_short":
                        final = self._final(ev.start, ev.stop)
                        self.counts.add(final)
                        events.append(final)
                self._onset = None
                self._next = None
                self._quiet, self._held = None, 0
                self._take_pending_model()
                self._windows = []
        return events

    def _analyse_ready(self, until: int | None = None) -> list[PipelineEvent]:
        """Analyse every window of the slide in progress that the ring holds (up to ``until``), all in one call (offline,
        a block holds many); then, window by window, the provisional results."""
        if self._onset is None or self._next is None:
            return []
        s = self.settings
        end = self._reader.end
        limit = end if until is None else min(until, end)
        hop = max(1, round(s.hop() * self.fs))
        spans: list[tuple[int, int]] = []
        nxt: tuple[int, int] | None = self._next
        while nxt is not None and limit >= nxt[1]:
            if s.max_windows and len(self._windows) + len(spans) >= s.max_windows:
                nxt = None
                break
            spans.append(nxt)
            nxt = (nxt[0] + hop, nxt[1] + hop)
        self._next = nxt
        if not spans:
            return []
        t0 = time.perf_counter()
        new = self._analyse(spans)
        self._windows += new
        return self._provisional_results(t0, sum(w.usable for w in new))

    def _analyse(self, spans: list[tuple[int, int]]) -> list[_Window]:
        """The windows ``spans``, analysed ahead (:meth:`replay`) or now: those of one length in one
        :meth:`Analyser.analyse_many` call."""
        ahead = [self._ahead.get(sp) for sp in spans]
        todo = [sp for sp, w in zip(spans, ahead, strict=True) if w is None]
        done = iter(self._analyse_now(todo) if todo else [])
        return [w if w is not None else next(done) for w in ahead]

    def _analyse_now(self, spans: list[tuple[int, int]]) -> list[_Window]:
        results: list[WindowResult | None] = [None] * len(spans)
        groups: dict[int, list[tuple[int, npt.NDArray[Any], npt.NDArray[np.bool_]]]] = {}
        for i, (lo, hi) in enumerate(spans):
            if hi - lo < self.min_samples:
                # a slide that ended before (or soon after) its window began: nothing to read, whatever the block timing
                results[i] = WindowResult(None, "window_too_short", {"samples": max(hi - lo, 0), "lost": 0, "saturated": 0.0, "spikes": 0})
                continue
            try:
                samples, valid = self._reader.read(lo, hi)
            except OverwrittenError:
                results[i] = WindowResult(None, "overwritten", {"samples": hi - lo, "lost": hi - lo, "saturated": 0.0, "spikes": 0})
                continue
            groups.setdefault(hi - lo, []).append((i, samples, valid))
        for group in groups.values():
            analysed = self.analyser.analyse_many(np.stack([g[1] for g in group]), np.stack([g[2] for g in group]))
            for (i, _, _), result in zip(group, analysed, strict=True):
                results[i] = result
        return [_Window(span, r) for span, r in zip(spans, results, strict=True) if r is not None]

    def _assessments(self, used: list[_Window], ends: Sequence[int], final: bool) -> list[Assessed]:
        """The assessment of the first ``ends[i]`` of a slide's usable windows ``used``, for each i: as replay assessed them
        ahead (:meth:`_assess_ahead`), else in one :meth:`Classifier.assess_many` call."""
        assert self.model is not None
        if self._assessed:
            known = [self._assessed.get(key) for key in _assessment_keys(used, ends, final)]
            if all(a is not None for a in known):
                return cast(list[Assessed], known)
        features = np.stack([w.features for w in used])
        proba, confidence, novelty = self.model.assess_many(features, [(0, end) for end in ends], final)
        return [(proba[i], confidence[i], novelty[i]) for i in range(len(ends))]

    def _provisional_results(self, t0: float, fresh: int) -> list[PipelineEvent]:
        """The provisional results to publish after each of the slide's last ``fresh`` usable windows (all of them just
        analysed), in order: the slide's windows up to each assessed in one call (offline, a block holds many; the daemon, one)."""
        if (self.model is None or self._onset is None or self.provisional_confidence >= 1.0 or self._paused is not None
                or not fresh):
            return []
        if self._quiet is not None:  # the windows reach into a quiet that may be the slide's end: held until it is known
            self._held += fresh
            return []
        used = [w for w in self._windows if w.usable]
        ends = range(len(used) - fresh + 1, len(used) + 1)
        events: list[PipelineEvent] = []
        for end, assessed in zip(ends, self._assessments(used, ends, final=False), strict=True):
            proba, confidence, novelty = assessed
            label = self.model.classes[int(np.argmax(proba))]
            if (confidence < max(self.provisional_confidence, self.min_confidence) or label == self._provisional
                    or (novelty is not None and novelty > 1.0)):
                continue
            self._provisional = label
            events.append(self._result(self._onset, used[end - 1].span[1], used[:end], assessed, t0, final=False))
        return events

    def _final(self, start: int, stop: int) -> SlideResult:
        t0 = time.perf_counter()
        spans = self.settings.spans(start, stop, self.fs, self.min_samples)
        done = {w.span: w for w in self._windows}
        missing = [sp for sp in spans if sp not in done]
        done.update(zip(missing, self._analyse(missing), strict=True))
        windows = [done[sp] for sp in spans]
        used = [w for w in windows if w.usable] if self.model is not None else []
        if not used:
            reasons = [w.result.reason for w in windows if w.result.reason] or ["window_too_short"]
            reason = "no_model" if self.model is None and any(w.usable for w in windows) else Counter(reasons).most_common(1)[0][0]
            return SlideResult(self._slide_id, start, stop, (spans[0][0], spans[-1][1]) if spans else (start, start), None, reason, None, [],
                               _quality(windows), None, (time.perf_counter() - t0) * 1e3, True, (stop - start) / self.fs)
        return self._result(start, stop, used, self._assessments(used, [len(used)], final=True)[0], t0, final=True)

    def _result(self, start: int, stop: int, used: list[_Window], assessed: Assessed, t0: float,
                final: bool) -> SlideResult:
        assert self.model is not None
        proba, confidence, novelty = assessed
        order = np.argsort(proba)[::-1][:3]
        top = [(self.model.classes[i], round(float(proba[i]), 4)) for i in order]
        label: str | None = self.model.classes[order[0]]
        reason = None
        if novelty is not None and novelty > 1.0:
            label, reason = None, "unknown_surface"
        elif confidence < self.min_confidence:
            label, reason = None, "low_confidence"
        feats = used[-1].result.features
        return SlideResult(self._slide_id, start, stop, (used[0].span[0], used[-1].span[1]), label, reason, round(confidence, 4), top,
                           _quality(used), feats, (time.perf_counter() - t0) * 1e3, final, (used[-1].span[1] - start) / self.fs,
                           None if novelty is None else round(novelty, 4), self.model.fingerprint)


def _quality(windows: list[_Window]) -> dict[str, Any]:
    q = [w.result.quality for w in windows]
    return {"samples": sum(x["samples"] for x in q), "lost": sum(x["lost"] for x in q), "saturated": max((x["saturated"] for x in q), default=0.0),
            "spikes": sum(x["spikes"] for x in q), "windows": sum(w.usable for w in windows)}
