"""Slides and windows of recordings, as the daemon would see them: what training, scoring and evaluation learn from.

Every recording goes through the daemon's own slide detector. With per-slide ground truth,
each true slide is paired with the detection that overlaps it most
(:func:`tactiled.core.matching.match_slides`): the slide is analysed where the detector put it,
exactly as live use will. A true slide the detector misses is still used, at its true
bounds, and counted (``missed``); detections that overlap no true slide are counted
(``false``) and not used. A file with only a file-level ``label`` gives every detected
slide that label. A slide still running at the end of a file is analysed as far as it goes.

Each slide is cut into windows (:meth:`tactiled.core.analysis.AnalysisSettings.spans`); each
window becomes one feature row. Slides without a usable window stay in the slide table
(so that scores count them) with the reason.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from tactiled.config import Config
from tactiled.core.analysis import Analyser, AnalysisSettings
from tactiled.core.detect import SlideDetector
from tactiled.core.events import DetectorEvent, Offset
from tactiled.core.matching import match_slides
from tactiled.errors import RecordingError, TactiledError
from tactiled.files.recording import Recording, load_recording

log = logging.getLogger(__name__)
Progress = Callable[[str], None]


def load_recordings(paths: Sequence[str | Path], report: Progress | None = None) -> list[tuple[str, Recording]]:
    """Load every file; a malformed one is reported (one line through ``report``) and skipped."""
    out = []
    for p in paths:
        try:
            out.append((str(p), load_recording(p)))
        except RecordingError as exc:
            if report is not None:
                report(f"skipped: {exc}")
    return out


def check_distinct(recs: Sequence[tuple[str, Recording]]) -> None:
    """Refuse (one line naming both) two recordings with the same samples, such as one file given twice or a copy under
    another name: cross-validation grouped by recording would test each on its own copy and promise what it never measured
    (``train``, ``evaluate``), and enrolment would count its slides twice."""
    import hashlib

    seen: dict[str, str] = {}
    for name, rec in recs:
        samples = np.ascontiguousarray(rec.samples)
        h = hashlib.blake2b(f"{samples.dtype.str}{samples.shape}".encode())
        h.update(samples.data)
        digest = h.hexdigest()
        if digest in seen:
            raise TactiledError(f"{seen[digest]} and {name} hold the same samples: one recording would count as two (cross-validation "
                                "would test it on its own copy); give each recording once")
        seen[digest] = name


def detector_events(rec: Recording, config: Config) -> list[DetectorEvent]:
    """Every event of the daemon's detector over the whole of ``rec`` (positions in the file), end of file included."""
    det = SlideDetector(config.detector, rec.fs, rec.channels)
    volts = rec.volts()
    valid = rec.valid_mask()
    volts[~valid] = 0.0
    return det.feed(0, volts, valid) + det.finish()


def detect_slides(rec: Recording, config: Config, events: list[DetectorEvent] | None = None) -> list[tuple[int, int]]:
    """(start, stop) positions of the slides the daemon's detector finds in ``rec`` (from ``events`` if already run)."""
    events = detector_events(rec, config) if events is None else events
    return [(e.start, e.stop) for e in events if isinstance(e, Offset) and e.reason != "too_short"]


@dataclass(frozen=True)
class LabelledSlide:
    """One slide to learn from or to score: file number, [start, stop) positions, surface, and where its bounds came from."""

    file: int
    start: int
    stop: int
    label: str | None
    source: str  # detected | truth (the detector missed it) | label (detected, file-level label)


@dataclass
class SlideCounts:
    """What pairing detections with ground truth found, per file name."""

    truth: int = 0
    detected: int = 0
    missed: dict[str, int] = field(default_factory=dict)
    false: dict[str, int] = field(default_factory=dict)


def recording_slides(file: int, name: str, rec: Recording, config: Config, counts: SlideCounts) -> list[LabelledSlide]:
    """The slides of one recording (see the module docstring), updating ``counts``."""
    detected = detect_slides(rec, config)
    counts.detected += len(detected)
    truth = rec.slides()
    if not truth:
        source = "label" if rec.label is not None else "detected"
        return [LabelledSlide(file, a, b, rec.label, source) for a, b in detected]
    counts.truth += len(truth)
    pairs = match_slides(detected, [(a, b) for a, b, _ in truth])
    out = []
    for (t_start, t_stop, surface), j in zip(truth, pairs, strict=True):
        if j is None:
            counts.missed[name] = counts.missed.get(name, 0) + 1
            out.append(LabelledSlide(file, t_start, t_stop, surface, "truth"))
        else:
            out.append(LabelledSlide(file, detected[j][0], detected[j][1], surface, "detected"))
    false = len(detected) - sum(j is not None for j in pairs)
    if false:
        counts.false[name] = false
    return out


@dataclass
class WindowSet:
    """Feature rows of every window of every slide.

    ``x`` (w, F) raw features in ``names`` order; per window: ``y`` label, ``groups`` file
    number, ``slide`` index into ``slides``, ``spans`` (w, 2) positions. ``reasons`` (per
    slide) says why a slide has no usable window (None if it has one).
    """

    x: npt.NDArray[np.float64]
    y: npt.NDArray[np.str_]
    groups: npt.NDArray[np.int64]
    slide: npt.NDArray[np.int64]
    spans: npt.NDArray[np.int64]
    names: list[str]
    files: list[str]
    slides: list[LabelledSlide]
    reasons: list[str | None]
    counts: SlideCounts
    skipped: dict[str, int]

    def slide_labels(self) -> npt.NDArray[np.str_]:
        """(s,) surface of every slide in ``slides`` order, "" when unknown."""
        return np.array([s.label or "" for s in self.slides], dtype=np.str_)

    def per_class(self) -> dict[str, tuple[int, int, int]]:
        """{surface: (slides, slides with a usable window, files)}."""
        out: dict[str, tuple[int, int, int]] = {}
        files: dict[str, set[int]] = {}
        for s, why in zip(self.slides, self.reasons, strict=True):
            if s.label is None:
                continue
            n, ok, _ = out.get(s.label, (0, 0, 0))
            files.setdefault(s.label, set()).add(s.file)
            out[s.label] = (n + 1, ok + (why is None), len(files[s.label]))
        return dict(sorted(out.items()))

    def averaged(self) -> WindowSet:
        """One row per slide with windows: the mean of its windows' raw features (a whole-slide representation)."""
        order = np.unique(self.slide)
        counts = np.bincount(self.slide, minlength=len(self.slides))[order]
        sums = np.zeros((len(self.slides), self.x.shape[1]))
        np.add.at(sums, self.slide, self.x)
        first = {int(k): int(i) for i, k in reversed(list(enumerate(self.slide)))}
        last = {int(k): int(i) for i, k in enumerate(self.slide)}
        spans = np.array([[self.spans[first[k], 0], self.spans[last[k], 1]] for k in order], dtype=np.int64).reshape(-1, 2)
        return WindowSet(sums[order] / counts[:, None], self.y[[first[k] for k in order]], self.groups[[first[k] for k in order]],
                         order.astype(np.int64), spans, self.names, self.files, self.slides, self.reasons, self.counts, self.skipped)


def analyse_slide(analyser: Analyser, rec: Recording, valid: npt.NDArray[np.bool_],
                  slide: LabelledSlide) -> tuple[list[tuple[int, int]], list[Any], str | None]:
    """(spans, feature vectors, reason) of one slide: the windows that could be analysed and, if none, why."""
    spans = analyser.settings.spans(slide.start, min(slide.stop, rec.samples.shape[0]), rec.fs, analyser.plan.min_samples())
    if not spans:
        return [], [], "window_too_short"
    good_spans, rows, reasons = [], [], []
    for lo, hi in spans:
        res = analyser.analyse(rec.samples[lo:hi], valid[lo:hi])
        if res.features is None:
            reasons.append(res.reason or "?")
            continue
        good_spans.append((lo, hi))
        rows.append(res.features)
    return good_spans, rows, None if rows else Counter(reasons).most_common(1)[0][0]


def find_slides(recs: Sequence[tuple[str, Recording]], config: Config) -> tuple[list[list[LabelledSlide]], SlideCounts]:
    """The slides of every recording (:func:`recording_slides`), and the pairing counts."""
    counts = SlideCounts()
    return [recording_slides(g, name, rec, config, counts) for g, (name, rec) in enumerate(recs)], counts


def collect_windows(recs: Sequence[tuple[str, Recording]], config: Config, settings: AnalysisSettings, progress: Progress | None = None,
                    require_labels: bool = True, found: tuple[list[list[LabelledSlide]], SlideCounts] | None = None,
                    jobs: int | None = 1) -> WindowSet:
    """Analyse every window of every slide of ``recs`` with ``settings`` (all of ``settings.names``).

    ``found``: the slides from :func:`find_slides`, if already known (else they are found here). ``jobs``: worker
    processes over the recordings (None or 0: every core; :func:`tactiled.run.pool.map_files`).
    """
    from tactiled.run.pool import map_files

    rows: list[Any] = []
    labels, groups, slide_idx, spans = [], [], [], []
    slides: list[LabelledSlide] = []
    reasons: list[str | None] = []
    per_file, counts = found if found is not None else find_slides(recs, config)
    skipped: dict[str, int] = {}

    def done(g: int, n: int) -> None:
        if progress and (g % 10 == 0 or g == n):
            progress(f"windows: {g}/{n} files")

    tasks = [(rec, per_file[g], config, settings, require_labels) for g, (_name, rec) in enumerate(recs)]
    for kept, per_slide, file_skipped in map_files(file_windows, tasks, jobs, done, signal_s=sum(rec.samples.shape[0] / rec.fs for _, rec in recs)):
        for k, (slide, (s_spans, s_rows, why)) in enumerate(zip(kept, per_slide, strict=True), len(slides)):
            reasons.append(why)
            rows += s_rows
            spans += s_spans
            labels += [slide.label or ""] * len(s_rows)
            groups += [slide.file] * len(s_rows)  # the group of the slide: its recording (or itself, train --group-by slide)
            slide_idx += [k] * len(s_rows)
        slides += kept
        for why, c in file_skipped.items():
            skipped[why] = skipped.get(why, 0) + c
    if progress and recs:
        progress(f"windows: {len(recs)} files, {len(slides)} slides, {len(rows)} windows")
    f = len(settings.names)
    return WindowSet(np.asarray(rows, dtype=np.float64).reshape(-1, f), np.asarray(labels, dtype=np.str_), np.asarray(groups, dtype=np.int64),
                     np.asarray(slide_idx, dtype=np.int64), np.asarray(spans, dtype=np.int64).reshape(-1, 2), list(settings.names),
                     [n for n, _ in recs], slides, reasons, counts, skipped)


def file_windows(task: tuple[Recording, list[LabelledSlide], Config, AnalysisSettings, bool]
                 ) -> tuple[list[LabelledSlide], list[tuple[list[tuple[int, int]], list[Any], str | None]], dict[str, int]]:
    """One recording's part of :func:`collect_windows`: (the slides kept, their :func:`analyse_slide`, what was skipped and why).

    ``task``: (recording, its slides, config, settings, whether unlabelled slides are skipped).
    """
    rec, file_slides, config, settings, require_labels = task
    analyser = Analyser(settings, rec.fs, rec.volts_per_count, rec.is_integer, config.classifier.max_saturated, config.classifier.max_lost)
    valid = rec.valid_mask()
    kept: list[LabelledSlide] = []
    per_slide: list[tuple[list[tuple[int, int]], list[Any], str | None]] = []
    skipped: dict[str, int] = {}
    for slide in file_slides:
        if require_labels and slide.label is None:
            skipped["unlabelled"] = skipped.get("unlabelled", 0) + 1
            continue
        result = analyse_slide(analyser, rec, valid, slide)
        if result[2] is not None:
            skipped[result[2]] = skipped.get(result[2], 0) + 1
        kept.append(slide)
        per_slide.append(result)
    return kept, per_slide, skipped
