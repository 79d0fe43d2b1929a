"""The streaming pipeline shared by the daemon and replay.

samples (index, (n, C), valid) → ring buffer → slide detector → analysis window → spike
removal + features (only those the model uses) → model → events. Driven by the sample
index only: the same samples in any block sizes give the same events. The window is
analysed as soon as it is complete (usually before the slide ends), so the label is ready
when the slide's end is detected.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from tactiled.analysis import Analyser, AnalysisSettings, WindowResult
from tactiled.config import Config
from tactiled.detect import SlideDetector, SlideEnd, SlideStart
from tactiled.errors import OverwrittenError
from tactiled.ringbuffer import RingBuffer


class Classifier(Protocol):
    """What the pipeline needs of a model (see :class:`tactiled.model.Model`)."""

    classes: list[str]
    fingerprint: str
    settings: AnalysisSettings

    def predict_proba(self, x: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]: ...


@dataclass
class SlideStarted:
    slide_id: int
    start: int


@dataclass
class SlideEnded:
    slide_id: int
    start: int
    stop: int
    reason: str  # quiet | max_duration | too_short (too short is not a slide: no result follows)


@dataclass
class SlideResult:
    """The outcome of one slide: label (None when abstaining, with ``reason``) and provenance."""

    slide_id: int
    start: int
    stop: int
    window: tuple[int, int]
    label: str | None
    reason: str | None
    confidence: float | None
    top: list[tuple[str, float]]
    quality: dict[str, Any]
    features: npt.NDArray[np.float64] | None = field(default=None, repr=False)
    compute_ms: float = 0.0
    final: bool = True  # False: a provisional label published while the slide goes on
    used_s: float = 0.0  # seconds of the slide (from its start) the label is based on


PipelineEvent = SlideStarted | SlideEnded | SlideResult


class Pipeline:
    """Feed blocks in order with :meth:`feed`; it returns the events they complete."""

    def __init__(self, config: Config, fs: float, channels: int, volts_per_count: float, integer: bool = True,
                 model: Classifier | None = None, settings: AnalysisSettings | None = None) -> None:
        self.fs = fs
        self.channels = channels
        self.model = model
        self.settings = model.settings if model is not None else (settings or AnalysisSettings.from_config(config, channels))
        self.min_confidence = config.classifier.min_confidence
        self.analyser = Analyser(self.settings, volts_per_count, integer, config.classifier.max_saturated, config.classifier.max_lost)
        capacity = max(round(config.ring.seconds * fs), round((config.detector.max_slide_s + 1.0) * fs))
        self.ring = RingBuffer(capacity, channels, np.int16 if integer else np.float64)
        self.detector = SlideDetector(config.detector, fs, channels)
        self.volts_per_count = volts_per_count if integer else 1.0
        self.slides = 0
        self.labels = 0
        self._slide_id = -1
        self._onset: int | None = None
        self._pending: WindowResult | None = None  # analysed window of the slide in progress
        self._pending_window: tuple[int, int] | None = None

    @property
    def sliding(self) -> bool:
        return self._onset is not None

    def will_analyse(self, end: int) -> bool:
        """True if feeding samples up to absolute index ``end`` completes the current slide's window (feature work)."""
        return self._onset is not None and self._pending is None and self._pending_window is not None and end >= self._pending_window[1]

    def feed(self, index: int, samples: npt.NDArray[Any], valid: npt.NDArray[np.bool_] | None = None) -> list[PipelineEvent]:
        """Process ``samples`` (n, C) whose first sample has absolute ``index`` (gaps are lost samples)."""
        self.ring.write(index, samples, valid)
        volts = samples.astype(np.float64) * self.volts_per_count
        if valid is not None:
            volts[~valid] = 0.0
        events: list[PipelineEvent] = []
        for ev in self.detector.feed(index, volts, valid):  # the detector treats index gaps as lost itself
            if isinstance(ev, SlideStart):
                self._slide_id += 1
                self._onset = ev.start
                self._pending = None
                self._pending_window = self.settings.window(ev.start, ev.start + 10**12, self.fs)
                events.append(SlideStarted(self._slide_id, ev.start))
            elif isinstance(ev, SlideEnd):
                events.append(SlideEnded(self._slide_id, ev.start, ev.stop, ev.reason))
                if ev.reason != "too_short":
                    events.append(self._result(ev.start, ev.stop))
                self._onset = None
                self._pending = None
            self._analyse_if_complete()
        self._analyse_if_complete()
        return events

    def _analyse_if_complete(self) -> None:
        if self._onset is None or self._pending is not None or self._pending_window is None:
            return
        lo, hi = self._pending_window
        if self.ring.end >= hi:
            self._pending = self._analyse(lo, hi)

    def _analyse(self, lo: int, hi: int) -> WindowResult:
        if hi - lo < self.analyser.plan.min_samples():
            # a slide that ended before (or soon after) its window began: nothing to read, whatever the block timing
            return WindowResult(None, "window_too_short", {"samples": max(hi - lo, 0), "lost": 0, "saturated": 0.0, "spikes": 0})
        try:
            samples, valid = self.ring.read(lo, hi)
        except OverwrittenError:
            return WindowResult(None, "overwritten", {"samples": hi - lo, "lost": hi - lo, "saturated": 0.0, "spikes": 0})
        return self.analyser.analyse(samples, valid)

    def _result(self, start: int, stop: int) -> SlideResult:
        t0 = time.perf_counter()
        window = self.settings.window(start, stop, self.fs)
        analysed = self._pending if self._pending is not None and self._pending_window == window else self._analyse(*window)
        self.slides += 1
        label, reason, confidence, top = None, analysed.reason, None, []
        if analysed.features is not None:
            if self.model is None:
                reason = "no_model"
            else:
                proba = self.model.predict_proba(analysed.features[None, :])[0]
                order = np.argsort(proba)[::-1][:3]
                top = [(self.model.classes[i], round(float(proba[i]), 4)) for i in order]
                confidence = float(proba[order[0]])
                if confidence < self.min_confidence:
                    reason = "low_confidence"
                else:
                    label = self.model.classes[order[0]]
                    self.labels += 1
        return SlideResult(self._slide_id, start, stop, window, label, reason, confidence, top, analysed.quality,
                           analysed.features, (time.perf_counter() - t0) * 1e3)
