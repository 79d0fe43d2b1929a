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

Training may also learn from speed-perturbed copies of each slide (``speeds``): the slide resampled
by a factor near 1, as if slid a few per cent faster or slower, so that its spectrum sits a few per
cent higher or lower (speech recognition's speed perturbation against speaking rate; here against the
sliding speed and another unit's film resonances). A copy's windows carry their slide's index and a
copy number above 0 (:attr:`WindowSet.copy`): they are training rows only, never scored.

A whole-slide candidate learns one row per slide, the mean of its windows (:meth:`WindowSet.averaged`). A long slide
(a recording that slides from its first sample to its last holds one) is also learnt as its pieces of
:data:`PIECE_WINDOWS` windows: several looks at the surface rather than one, as a per-window candidate has. With one
such slide per recording a surface otherwise gives a whole-slide classifier as many rows as it has recordings, and
cross-validation, which holds one of them out, trains it on one row fewer per surface than the final fit (with three
recordings, a third fewer; measured in docs/evaluation.md, *Long slides learnt in pieces*). Pieces are training rows
only (copy number :data:`PIECE`).
"""

from __future__ import annotations

import itertools
import logging
import math
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
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


def undetected(per_file: Sequence[Sequence[LabelledSlide]], rates: Sequence[float], shortest_s: float) -> dict[str, tuple[int, int]]:
    """{surface: (its slides, those the detector found)} of the surfaces whose slides the detector mostly misses (fewer
    than half found; the rest used at their true bounds): a surface the daemon would seldom find, whose slides would
    teach the model, and its unknown-surface test, what the daemon does not meet (a still or silent sensor, a DC step).
    ``rates``: each file's fs, Hz; slides shorter than ``shortest_s`` (no slide to the detector, by its own rule) are
    not counted: their windows' checks say what is wrong with them."""
    total: Counter[str] = Counter()
    found: Counter[str] = Counter()
    for slides, fs in zip(per_file, rates, strict=True):
        for s in slides:
            if s.label is not None and s.stop - s.start >= shortest_s * fs:
                total[s.label] += 1
                found[s.label] += s.source != "truth"
    return {k: (n, found[k]) for k, n in sorted(total.items()) if 2 * found[k] < n}


def undetected_text(surfaces: dict[str, tuple[int, int]]) -> str:
    """The one line of :func:`undetected`'s surfaces."""
    named = ", ".join(f"{k} ({f} of {n})" for k, (n, f) in surfaces.items())
    return (f"the detector finds fewer than half of the slides of {named}: the daemon would seldom label such a surface (a still "
            "or silent sensor? the slides' ground truth is not where the signal is, or the detector's settings do not suit it)")


def some_names(names: Sequence[str], shown: int = 3) -> str:
    """The first ``shown`` of ``names`` joined by commas, and how many more (``a, b, c and 2 more``): a line's list of files."""
    return ", ".join(names[:shown]) + (f" and {len(names) - shown} more" if len(names) > shown else "")


CROSS_VALIDATION = "cross-validation would test it on its own copy"  # check_distinct's reason for train and evaluate


def check_distinct(recs: Sequence[tuple[str, Recording]], why: str = CROSS_VALIDATION) -> None:
    """Refuse (one line naming both, and ``why`` it matters to the command) two recordings with the same samples, such as one
    file given twice or a copy under another name: cross-validation grouped by recording would test each on its own copy
    and promise what it never measured (``train``, ``evaluate``), enrolment would count its slides twice, ``score`` its
    slides, ``features`` its windows."""
    import hashlib

    seen: dict[str, str] = {}
    for name, rec in recs:
        samples = np.ascontiguousarray(rec.samples)
        h = hashlib.blake2b(f"{samples.dtype.str}{samples.shape}".encode())
        h.update(samples.data)
        digest = h.hexdigest()
        if digest in seen:
            raise TactiledError(f"{seen[digest]} and {name} hold the same samples: one recording would count as two ({why}); give each "
                                "recording once")
        seen[digest] = name


def detector_events(rec: Recording, config: Config, start_level: float | None = None) -> list[DetectorEvent]:
    """Every event of the daemon's detector over the whole of ``rec`` (positions in the file), end of file included;
    ``start_level``: a model's (tactiled.learn.levels), as the daemon's detector has it."""
    det = SlideDetector(config.detector, rec.fs, rec.channels, start_level)
    volts = rec.volts()
    valid = rec.valid_mask()
    volts[~valid] = 0.0
    return det.feed(0, volts, valid) + det.finish()


def detect_slides(rec: Recording, config: Config, events: list[DetectorEvent] | None = None,
                  start_level: float | None = None) -> list[tuple[int, int]]:
    """(start, stop) positions of the slides the daemon's detector finds in ``rec`` (from ``events`` if already run; else
    with a model's ``start_level``, as :func:`detector_events`)."""
    events = detector_events(rec, config, start_level) if events is None else events
    return [(e.start, e.stop) for e in events if isinstance(e, Offset) and e.reason != "too_short"]


@dataclass(frozen=True)
class LabelledSlide:
    """One slide to learn from or to score: file number, [start, stop) positions, surface, and where its bounds came from."""

    file: int
    start: int
    stop: int
    label: str | None
    source: str  # detected | truth (the detector missed it) | label (detected, file-level label)


PIECE_WINDOWS = 4  # a long slide's pieces, as whole-slide training rows: this many windows each (1 s of 0.25 s windows)
PIECE = -1  # the copy number of a piece's row (:meth:`WindowSet.averaged`)
GROUP_PIECE_S = 2.0  # train --group-by slide: a slide of at least twice this many seconds is cut into slides about this long


def cut_long_slides(slides: Sequence[LabelledSlide], length: int) -> list[LabelledSlide]:
    """``slides`` with each one of at least 2·``length`` samples cut into consecutive slides of ``length`` to under
    2·``length`` samples (as even as the samples allow), each with its surface and source; shorter slides as they are.

    For ``train --group-by slide``: a recording that is one long slide then gives cross-validation several groups."""
    out: list[LabelledSlide] = []
    for s in slides:
        n = (s.stop - s.start) // max(1, length)
        if n < 2:
            out.append(s)
            continue
        edges = [s.start + (s.stop - s.start) * i // n for i in range(n + 1)]
        out += [replace(s, start=a, stop=b) for a, b in itertools.pairwise(edges)]
    return out


@dataclass
class SlideCounts:
    """What pairing detections with ground truth found, per file name."""

    truth: int = 0
    detected: int = 0
    missed: dict[str, int] = field(default_factory=dict)
    false: dict[str, int] = field(default_factory=dict)


def recording_slides(file: int, name: str, rec: Recording, config: Config, counts: SlideCounts,
                     start_level: float | None = None) -> list[LabelledSlide]:
    """The slides of one recording (see the module docstring), updating ``counts``; ``start_level``: a model's, as the
    daemon's detector has it (:func:`detector_events`)."""
    detected = detect_slides(rec, config, start_level=start_level)
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
    slide) says why a slide has no usable window (None if it has one). ``copy`` (w,): 0 for a
    window of the slide as recorded, k > 0 for one of its k-th speed-perturbed copy (None: no
    copies); a copy's spans are its own sample positions from its slide's start.
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
    copy: npt.NDArray[np.int8] | None = None

    def originals(self) -> npt.NDArray[np.bool_]:
        """(w,) whether each row is of a slide as recorded (not a speed-perturbed copy, nor a piece of a long slide): the rows
        to score and to measure."""
        return np.ones(len(self.y), dtype=bool) if self.copy is None else self.copy == 0

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
        """Of a set of windows: one row per slide with windows (and per copy of it), the mean of its windows' raw features (a
        whole-slide representation), in slide order, each slide's copies after it; then, of each of those with at least
        2·:data:`PIECE_WINDOWS` windows, the means of its pieces (its windows in time order, split into as many runs of at
        least :data:`PIECE_WINDOWS` as they hold), training rows only (copy number :data:`PIECE`)."""
        copies = 1 + (int(self.copy.max(initial=0)) if self.copy is not None else 0)
        key = self.slide * copies + (self.copy if self.copy is not None else 0)
        order, at = np.unique(key, return_inverse=True)
        counts = np.bincount(at, minlength=len(order))
        sums = np.zeros((len(order), self.x.shape[1]))
        np.add.at(sums, at, self.x)
        rows = np.arange(len(key))
        first, last = np.full(len(order), len(key)), np.full(len(order), -1)
        np.minimum.at(first, at, rows)
        np.maximum.at(last, at, rows)
        spans = np.column_stack([self.spans[first, 0], self.spans[last, 1]]).astype(np.int64).reshape(-1, 2)
        copy = None if self.copy is None else (order % copies).astype(np.int8)
        whole = WindowSet(sums / counts[:, None], self.y[first], self.groups[first], (order // copies).astype(np.int64), spans, self.names,
                          self.files, self.slides, self.reasons, self.counts, self.skipped, copy)
        long = np.flatnonzero(counts >= 2 * PIECE_WINDOWS)
        if not len(long):
            return whole
        in_time = np.lexsort((self.spans[:, 0], at))  # every group's windows together, in time order
        bounds = np.r_[0, np.cumsum(counts)]
        parts = [part for g in long for part in np.array_split(in_time[bounds[g]:bounds[g + 1]], counts[g] // PIECE_WINDOWS)]
        x = np.stack([self.x[part].mean(axis=0) for part in parts])
        ends = np.array([[self.spans[part, 0].min(), self.spans[part, 1].max()] for part in parts], dtype=np.int64)
        heads = np.array([part[0] for part in parts])
        return WindowSet(np.vstack([whole.x, x]), np.concatenate([whole.y, self.y[heads]]), np.concatenate([whole.groups, self.groups[heads]]),
                         np.concatenate([whole.slide, self.slide[heads]]), np.vstack([whole.spans, ends]), self.names, self.files,
                         self.slides, self.reasons, self.counts, self.skipped,
                         np.concatenate([whole.copy if whole.copy is not None else np.zeros(len(whole.y), dtype=np.int8),
                                         np.full(len(parts), PIECE, dtype=np.int8)]))


def analyse_slide(analyser: Analyser, rec: Recording, valid: npt.NDArray[np.bool_],
                  slide: LabelledSlide) -> tuple[list[tuple[int, int]], list[Any], str | None]:
    """(spans, feature vectors, reason) of one slide: the windows that could be analysed and, if none, why."""
    return analyse_span(analyser, rec.samples, valid, slide.start, min(slide.stop, rec.samples.shape[0]), rec.fs)


def analyse_span(analyser: Analyser, samples: npt.NDArray[Any], valid: npt.NDArray[np.bool_] | None, start: int, stop: int,
                 fs: float) -> tuple[list[tuple[int, int]], list[Any], str | None]:
    """(spans, feature vectors, reason) of the slide [start, stop) of ``samples`` (n, C) at ``fs`` Hz (``valid`` (n,), None: all
    valid): the windows that could be analysed and, if none, why."""
    spans = analyser.settings.spans(start, stop, fs, analyser.plan.min_samples())
    if not spans:
        return [], [], "window_too_short"
    good_spans, rows, reasons = [], [], []
    for lo, hi in spans:
        res = analyser.analyse(samples[lo:hi], None if valid is None else valid[lo:hi])
        if res.features is None:
            reasons.append(res.reason or "?")
            continue
        good_spans.append((lo, hi))
        rows.append(res.features)
    return good_spans, rows, None if rows else Counter(reasons).most_common(1)[0][0]


def speed_ratios(percent: float) -> tuple[tuple[int, int], ...]:
    """The (up, down) resampling ratios of the two speed-perturbed copies ``percent`` per cent faster and slower (0: none):
    ``resample_poly(x, up, down)`` has up/down as many samples, so at the same rate it plays ``x`` at down/up of its speed
    (5: (20, 21), 5 % faster, and (21, 20), 4.8 % slower). ValueError unless 0 <= percent <= 30 with at most one decimal."""
    if not (math.isfinite(percent) and 0.0 <= percent <= 30.0) or abs(percent * 10 - round(percent * 10)) > 1e-9:
        raise ValueError(f"must be between 0 and 30 per cent, in steps of 0.1, got {percent}")
    if percent == 0:
        return ()
    step = round(percent * 10)
    a, b = 1000, 1000 + step
    g = math.gcd(a, b)
    return ((a // g, b // g), (b // g, a // g))


def speed_copies(floats: Analyser, rec: Recording, valid: npt.NDArray[np.bool_], slide: LabelledSlide,
                 speeds: Sequence[tuple[int, int]]) -> tuple[list[tuple[int, int]], list[Any], list[int]]:
    """(spans, feature vectors, copy numbers 1, 2, ...) of the windows of the slide's speed-perturbed copies (``speeds``:
    (up, down) ratios, :func:`speed_ratios`), each the slide in volts resampled by ``scipy.signal.resample_poly`` (its
    anti-aliasing filter) and analysed by ``floats`` (an analyser of volts, not counts) as a slide of its own; none for a
    slide with lost samples (nothing to resample)."""
    from scipy.signal import resample_poly

    stop = min(slide.stop, rec.samples.shape[0])
    if not speeds or stop - slide.start < 2 or not bool(valid[slide.start:stop].all()):
        return [], [], []
    volts = np.asarray(rec.samples[slide.start:stop], dtype=np.float64)
    if rec.is_integer:
        volts = volts * rec.volts_per_count
    spans: list[tuple[int, int]] = []
    rows: list[Any] = []
    copies: list[int] = []
    for k, (up, down) in enumerate(speeds, 1):
        y = resample_poly(volts, up, down, axis=0)
        s_spans, s_rows, _ = analyse_span(floats, y, None, 0, y.shape[0], rec.fs)
        spans += [(slide.start + lo, slide.start + hi) for lo, hi in s_spans]
        rows += s_rows
        copies += [k] * len(s_rows)
    return spans, rows, copies


def find_slides(recs: Sequence[tuple[str, Recording]], config: Config,
                start_level: float | None = None) -> tuple[list[list[LabelledSlide]], SlideCounts]:
    """The slides of every recording (:func:`recording_slides`, with a model's ``start_level`` if given), and the pairing counts."""
    counts = SlideCounts()
    return [recording_slides(g, name, rec, config, counts, start_level) for g, (name, rec) in enumerate(recs)], counts


def collect_windows(recs: Sequence[tuple[str, Recording]], config: Config, settings: AnalysisSettings, progress: Progress | None = None,
                    require_labels: bool = True, found: tuple[list[list[LabelledSlide]], SlideCounts] | None = None,
                    jobs: int | None = 1, speeds: Sequence[tuple[int, int]] = ()) -> WindowSet:
    """Analyse every window of every slide of ``recs`` with ``settings`` (all of ``settings.names``).

    ``found``: the slides from :func:`find_slides`, if already known (else they are found here). ``jobs``: worker
    processes over the recordings (None or 0: every core; :func:`tactiled.run.pool.map_files`). ``speeds``: also the
    windows of each labelled slide's speed-perturbed copies (:func:`speed_copies`; :attr:`WindowSet.copy` says which).
    """
    from tactiled.run.pool import map_files

    rows: list[Any] = []
    labels, groups, slide_idx, spans, copy = [], [], [], [], []
    slides: list[LabelledSlide] = []
    reasons: list[str | None] = []
    per_file, counts = found if found is not None else find_slides(recs, config)
    skipped: dict[str, int] = {}

    def done(g: int, n: int) -> None:
        if progress and (g % 10 == 0 or g == n):
            progress(f"windows: {g}/{n} files")

    tasks = [(rec, per_file[g], config, settings, require_labels, tuple(speeds)) for g, (_name, rec) in enumerate(recs)]
    for kept, per_slide, file_skipped in map_files(file_windows, tasks, jobs, done, signal_s=sum(rec.samples.shape[0] / rec.fs for _, rec in recs)):
        for k, (slide, (s_spans, s_rows, why, s_copy)) in enumerate(zip(kept, per_slide, strict=True), len(slides)):
            reasons.append(why)
            rows += s_rows
            spans += s_spans
            copy += s_copy
            labels += [slide.label or ""] * len(s_rows)
            groups += [slide.file] * len(s_rows)  # the group of the slide: its recording (or itself, train --group-by slide)
            slide_idx += [k] * len(s_rows)
        slides += kept
        for why, c in file_skipped.items():
            skipped[why] = skipped.get(why, 0) + c
    if progress and recs:
        made = sum(c > 0 for c in copy)
        progress(f"windows: {len(recs)} files, {len(slides)} slides, {len(rows) - made} windows"
                 + (f" (and {made} windows of the {len(speeds)} speed-perturbed copies of each slide)" if speeds else ""))
    f = len(settings.names)
    return WindowSet(np.asarray(rows, dtype=np.float64).reshape(-1, f), np.asarray(labels, dtype=np.str_), np.asarray(groups, dtype=np.int64),
                     np.asarray(slide_idx, dtype=np.int64), np.asarray(spans, dtype=np.int64).reshape(-1, 2), list(settings.names),
                     [n for n, _ in recs], slides, reasons, counts, skipped, np.asarray(copy, dtype=np.int8) if speeds else None)


SlideWindows = tuple[list[tuple[int, int]], list[Any], str | None, list[int]]


def file_windows(task: tuple[Recording, list[LabelledSlide], Config, AnalysisSettings, bool, tuple[tuple[int, int], ...]]
                 ) -> tuple[list[LabelledSlide], list[SlideWindows], dict[str, int]]:
    """One recording's part of :func:`collect_windows`: (the slides kept; per slide its :func:`analyse_slide`'s windows, then
    its copies' (:func:`speed_copies`, labelled slides with a usable window only), with each window's copy number; what was
    skipped and why).

    ``task``: (recording, its slides, config, settings, whether unlabelled slides are skipped, speed ratios).
    """
    rec, file_slides, config, settings, require_labels, speeds = task
    analyser = Analyser(settings, rec.fs, rec.volts_per_count, rec.is_integer, config.classifier.max_saturated, config.classifier.max_lost)
    floats = Analyser(settings, rec.fs, 1.0, False, config.classifier.max_saturated, config.classifier.max_lost) if speeds else None  # copies: volts
    valid = rec.valid_mask()
    kept: list[LabelledSlide] = []
    per_slide: list[SlideWindows] = []
    skipped: dict[str, int] = {}
    for slide in file_slides:
        if require_labels and slide.label is None:
            skipped["unlabelled"] = skipped.get("unlabelled", 0) + 1
            continue
        spans, rows, why = analyse_slide(analyser, rec, valid, slide)
        if why is not None:
            skipped[why] = skipped.get(why, 0) + 1
        copy = [0] * len(rows)
        if floats is not None and why is None and slide.label is not None:
            c_spans, c_rows, c_copy = speed_copies(floats, rec, valid, slide, speeds)
            spans, rows, copy = spans + c_spans, rows + c_rows, copy + c_copy
        kept.append(slide)
        per_slide.append((spans, rows, why, copy))
    return kept, per_slide, skipped
