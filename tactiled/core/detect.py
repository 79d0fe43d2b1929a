"""Online slide detection, driven by the sample index only; every threshold relative or in seconds.

Envelope, one value per hop of ``hop_ms`` (at least ``hop_min_samples``, so that a hop holds
enough sub-blocks at low rates), hops aligned to the first sample fed. The front end is
cheap enough for replay at thousands of times real time (numpy only, two or three passes
over the samples):

1. a boxcar low-pass: the sum of the last ``L`` samples, L = round(0.443·fs / high) with
   high = min(``band_high_hz``, ``band_high_frac``·fs) (its −3 dB point is near ``high``;
   L = 1 at low rates);
2. a mains comb: y[n] = s[n] − s[n − P], P = round(fs / ``mains_hz``) (one mains period;
   1 / ``band_low_hz`` when ``mains_hz`` is 0). Its zeros at 0 Hz and at every multiple of
   the mains frequency remove DC offsets, drift and all mains harmonics; elsewhere its
   power gain averages 2, so a broadband slide passes;
3. each hop is cut into at least 12 sub-blocks of D samples (D the largest divisor of the
   hop not above hop/12); a sub-block's energy is Σ y² over its samples and channels; the
   envelope of the hop is the median of its sub-blocks' energies: a 1–3-sample spike (and
   its echo one comb lag later) touches at most four sub-blocks and barely moves the
   median, a slide moves all of them.

The first P + L − 1 samples of a stream (the comb has no history yet) count as settling.
Decisions at rest, in a slide and while undecided use the median envelope of the last three hops, so one
loud hop neither starts a slide nor interrupts the quiet that ends one (the rests a slide the stream began in is split
at are judged on the median of each hop and its neighbours).

States. The detector starts *undecided*: it does not know whether the stream began at rest
or in the middle of a slide. Its reference is the 80th percentile of the envelope over the first
``initial_s`` (a slide's level, not its dips'). If the median envelope over the last ``initial_s`` then rises above
``on_factor`` × the reference (a sustained rise: the level of a slide fluctuates from hop to
hop by more than that), the stream began at rest: the reference becomes the noise floor and a slide starts. If it stays below
reference / ``on_factor`` for ``off_hold_s`` + ``initial_s`` (longer than in a slide: the drop is
measured against the slide's own level, which dips further than a floor), the stream began in a slide: the slides from
the first sample to the drop are reported (retroactive :class:`Onset` and :class:`Offset` pairs), split at every rest the
quiet's level shows there (:func:`rests_split`: a rest shorter than that hold went unseen until then), and the low level
becomes the floor. If neither happens before :meth:`SlideDetector.finish`, the whole stream
was one slide (reason ``end_of_stream``). With a ``start_level`` (a model's, learnt from the rests and slides of its
training recordings: tactiled.learn.levels) the reference decides at once: at or above it the stream began in a slide,
reported then (its end still judged as undecided), below it the stream is at rest. At or above it with the first hops
below the level by √``on_factor`` or more (the median of three), the stream began at rest and a slide within
``initial_s``: that slide starts at the first hop above them, over a floor of theirs.

At rest, the floor tracks the envelope (exponential in the log domain, ``floor_tau_s``). A
slide starts when the envelope exceeds ``on_factor`` × floor (its onset moved back over the
hops of the last ``lookback_s`` that were above ``off_factor`` × floor) and ends when it stays
below ``off_factor`` × floor for ``off_hold_s`` (the reported stop is where the quiet
began, so a level dip inside a slide shorter than ``off_hold_s`` never splits it), or after
``max_slide_s``. Waiting ``off_hold_s`` would delay every label by as much, so after ``end_hold_s`` of the
same quiet (when shorter) a :class:`Pause` says the slide has probably ended there; if the level comes back
before ``off_hold_s`` a :class:`Resume` withdraws it, else the :class:`Offset` has the Pause's ``stop``.
Slides shorter than ``min_slide_s`` are dropped (reason ``too_short``); after a slide nothing starts for ``holdoff_s``.

Lost samples (``valid`` False, and index gaps) never start a slide nor move the floor,
count as quiet within a slide, and the ``settle_s`` after them (at least the comb's P + L − 1
samples) let the front end settle; so do hops of exact digital silence. The same samples in blocks of any size give identical
events.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from typing import cast

import numpy as np
import numpy.typing as npt

from tactiled.config import DetectorConfig
from tactiled.core.events import DetectorEvent, Loud, Offset, Onset, Pause, Quiet, Resume
from tactiled.core.spikes import median_last

CHUNK = 16384  # samples per step of the envelope's front end (its arrays stay in a core's cache)


@dataclass(frozen=True)
class FrontEnd:
    """The envelope's front end at one rate (see the module docstring): boxcar ``boxcar``, comb lag ``lag``, hop and sub-block, samples."""

    boxcar: int
    lag: int
    hop: int
    block: int

    @property
    def history(self) -> int:
        """Samples before a hop its first output needs."""
        return self.lag + self.boxcar - 1


FRONT_END_KEYS = ("hop_ms", "hop_min_samples", "band_low_hz", "band_high_hz", "band_high_frac", "mains_hz")  # what the envelope's scale depends on


def front_end_settings(config: DetectorConfig) -> dict[str, float]:
    """The detector settings the envelope's values depend on (:data:`FRONT_END_KEYS`): a level measured under other ones is
    not comparable."""
    return {k: float(getattr(config, k)) for k in FRONT_END_KEYS}


def front_end(config: DetectorConfig, fs: float) -> FrontEnd:
    """The front end's sample counts at rate ``fs``."""
    high = min(config.band_high_hz, config.band_high_frac * fs)
    boxcar = max(1, round(0.443 * fs / high))
    lag = max(1, round(fs / (config.mains_hz if config.mains_hz > 0 else config.band_low_hz)))
    hop = max(config.hop_min_samples, round(config.hop_ms * 1e-3 * fs))
    block = max(d for d in range(1, max(1, hop // 12) + 1) if hop % d == 0)
    return FrontEnd(boxcar, lag, hop, block)


def envelope(ext: npt.NDArray[np.float64], fe: FrontEnd) -> npt.NDArray[np.float64]:
    """Envelope (h,) of the h whole hops that follow the first ``fe.history`` rows of ``ext`` (history + h·hop, C) volts."""
    n = ext.shape[0] - fe.history
    hops = n // fe.hop
    s = ext[fe.boxcar - 1:]
    for k in range(1, fe.boxcar):  # the same slices in the same order whatever the block: bit-identical sums
        s = s + ext[fe.boxcar - 1 - k: ext.shape[0] - k]
    y = s[fe.lag: fe.lag + hops * fe.hop] - s[: hops * fe.hop]
    np.square(y, out=y)  # in place: one array of the chunk's size fewer
    sub = y.reshape(hops * fe.hop // fe.block, fe.block * y.shape[1]).sum(axis=1).reshape(hops, fe.hop // fe.block)
    return median_last(sub)


def stream_envelope(head: npt.NDArray[np.float64], samples: npt.NDArray[np.float64], hops: int, fe: FrontEnd) -> list[float]:
    """Envelopes of the first ``hops`` hops of the stream ``head`` + ``samples`` (head: the comb's history, then the
    samples pending; volts), in chunks of about :data:`CHUNK` samples that stay in cache (3x faster than whole 64k-sample
    blocks, the same values)."""
    per = max(1, CHUNK // fe.hop)
    out: list[float] = []
    for h in range(0, hops, per):
        lo, hi = h * fe.hop, min(hops, h + per) * fe.hop
        out += envelope(joined_rows(head, samples, lo, hi + fe.history), fe).tolist()
    return out


def joined_rows(head: npt.NDArray[np.float64], tail: npt.NDArray[np.float64], start: int, stop: int) -> npt.NDArray[np.float64]:
    """Rows [start, stop) of ``head`` (m, C) followed by ``tail`` (n, C): a view of one of them when the rows lie in it,
    else a copy of the rows across the join."""
    m = head.shape[0]
    if start >= m:
        return tail[start - m: stop - m]
    if stop <= m:
        return head[start:stop]
    return np.concatenate([head[start:], tail[: stop - m]])


def median3_runs(values: list[float]) -> list[float]:
    """(n,) the median of each value and the two before it (the first two: their own value), as :func:`_median3` of
    three takes it: ``max(min(a, b), min(max(a, b), c))``, for positive values (min and max exact, in numpy at once)."""
    v = np.asarray(values, dtype=np.float64)
    if v.size < 3:
        return v.tolist()  # type: ignore[no-any-return]
    a, b, c = v[:-2], v[1:-1], v[2:]
    mid = np.maximum(np.minimum(a, b), np.minimum(np.maximum(a, b), c))
    return v[:2].tolist() + mid.tolist()  # type: ignore[no-any-return]


def median3_centred(values: Sequence[float]) -> list[float]:
    """(n,) the median of each value and its two neighbours, as :func:`_median3` takes them (at either end the mean of the
    value and its one neighbour; a single value is itself): one loud hop among quiet ones is quiet, and no lag."""
    v = list(values)
    if len(v) < 3:
        return [_median3(v)] * len(v) if v else []
    return [(v[0] + v[1]) / 2, *median3_runs(v)[2:], (v[-2] + v[-1]) / 2]  # the trailing median at k + 1 is centred at k


def _hop_validity(pending: npt.NDArray[np.bool_], valid: npt.NDArray[np.bool_] | None, rows: int, hop: int) -> tuple[list[bool], npt.NDArray[np.bool_]]:
    """(whether each whole hop of the flags ``pending`` followed by ``valid`` (``rows`` new rows; None: all valid) is valid,
    the flags of the rows after the last whole hop); no array is walked when every flag is True."""
    hops = (pending.shape[0] + rows) // hop
    if valid is None and bool(pending.all()):
        return [True] * hops, np.ones(pending.shape[0] + rows - hops * hop, dtype=bool)
    flags = np.concatenate([pending, np.ones(rows, dtype=bool) if valid is None else valid])
    return cast(list[bool], flags[: hops * hop].reshape(hops, hop).all(axis=1).tolist()), flags[hops * hop:]


KNOCK_S = 0.1  # a slide's start loud for less than this, then quiet as long: a knock (and its comb echo), not its start (s)
UNDECIDED_HISTORY_S = 120.0  # the undecided hops kept for splitting the slide the stream began in (s of stream)


def rests_split(hops: Iterable[tuple[int, float]], start: int, stop: int, hop: int, quiet: float, hold: int,
                head: bool = False) -> list[tuple[int, int]]:
    """The slides [a, b) of the span [start, stop) the stream began in, split at its rests: runs of consecutive hops (index,
    envelope) ``hops`` whose envelope, the median of each hop and its neighbours (:func:`median3_centred`: a click in a
    rest is no end of it), stays below ``quiet`` (off_factor × the floor the quiet after the span showed) for at least
    ``hold`` samples (off_hold_s), as a slide ends once the floor is known. ``head``: a quiet run the span begins with is
    rest however short (the stream began at rest, a slide within its first hops), the slide starting after it. Hops
    before the first kept (a stream longer than :data:`UNDECIDED_HISTORY_S`) leave their part of the span whole."""
    inside = [(i, e) for i, e in hops if start <= i < stop]
    spans: list[tuple[int, int]] = []
    a, rest, last = start, None, None  # the slide's start, the rest run's first hop, the hop before this one
    for i, e in zip([i for i, _ in inside], median3_centred([e for _, e in inside]), strict=True):
        if rest is not None and (e >= quiet or (last is not None and i != last + hop)):  # the run ends
            if head and a == start and rest == inside[0][0] and e >= quiet:  # the stream's quiet head
                a = i
            elif last is not None and last + hop - rest >= hold and rest > a:
                spans.append((a, rest))
                a = i
            rest = None
        if e < quiet and rest is None:
            rest = i
        last = i
    if rest is not None and last is not None and last + hop - rest >= hold and rest > a:  # a rest up to the quiet's start
        stop = rest
    spans.append((a, stop))
    return spans


def _median3(v: Sequence[float]) -> float:
    """Median of one to three floats (the mean of two), without numpy's overhead."""
    if len(v) == 3:
        a, b, c = v
        return max(min(a, b), min(max(a, b), c))
    return v[0] if len(v) == 1 else (v[0] + v[1]) / 2


class SlideDetector:
    """Feed (index, samples) blocks in order, then :meth:`finish`; both return :class:`Onset` / :class:`Offset` events."""

    def __init__(self, config: DetectorConfig, fs: float, channels: int, start_level: float | None = None) -> None:
        self.c = config
        self.fs = fs
        # the envelope above which a stream's initial level is a slide's and below which it is rest (a model's, learnt from the
        # rests and slides of its training recordings): the stream's start is then decided after initial_s; None: by its changes
        self.start_level = start_level
        self._early = False  # the stream began in a slide, known by start_level: its Onset reported, its end decided as undecided
        self.front = front_end(config, fs)
        self.hop = self.front.hop
        self._history = np.zeros((self.front.history, channels))  # the samples before the pending ones (zeros before the stream)
        self._pending = np.zeros((0, channels))
        self._pending_valid = np.zeros(0, dtype=bool)
        self._pending_index: int | None = None
        self._first: int | None = None
        self._lead_end: int | None = None  # where exact digital silence at the stream's start ended: no slide began before it
        self._settle = max(round(config.settle_s * fs), self.front.history)
        self._settle_until = -1
        # a gap longer than this is skipped in constant time (:meth:`_skip`): it holds more than the comb's history, two hops
        # and the quiet that ends a slide
        self._skip_after = max(round((config.off_hold_s + config.settle_s) * fs), 1) + 2 * self.front.history + 8 * self.hop
        self._floor: float | None = None
        self._alpha = 1.0 - math.exp(-self.hop / (config.floor_tau_s * fs))
        self._initial: list[float] = []  # undecided: envelopes of the first initial_s
        # undecided: (hop, envelope) of every valid hop since the first, so that a slide the stream began in can be split
        # at its rests once the quiet after it shows the floor (at most UNDECIDED_HISTORY_S of them)
        self._undecided_hops: deque[tuple[int, float]] = deque(maxlen=max(1, round(UNDECIDED_HISTORY_S * fs / self.hop)))
        self._initial_hops = max(1, round(config.initial_s * fs / self.hop))
        # a drop from a slide's own level (not yet from a noise floor) must last off_hold_s + initial_s to be its end:
        # a slide's level dips further below its own median than below a floor
        self._undecided_hold = (config.off_hold_s + config.initial_s) * fs
        lookback = max(1, round(config.lookback_s * fs / self.hop))
        self._recent: deque[tuple[int, float]] = deque(maxlen=max(lookback, self._initial_hops))
        self._reference: float | None = None
        self.sliding = False
        self._start = 0
        self._quiet_since: int | None = None
        self._paused = False  # a Pause was reported for the current quiet
        hold = config.end_hold_s if 0 < config.end_hold_s < config.off_hold_s else math.inf
        self._end_hold = hold * fs
        self._holdoff_until = -1
        self._last3: deque[float] = deque(maxlen=3)
        self.envelope = 0.0
        self.floor = 0.0

    @property
    def _began(self) -> int:
        """Where the slide a stream began in began: its first sample, or the end of the exact silence it began with."""
        assert self._first is not None
        return self._lead_end if self._lead_end is not None else self._first

    @property
    def undecided(self) -> bool:
        """True until the detector knows whether the stream began at rest or in a slide."""
        return self._floor is None

    def feed(self, index: int, samples: npt.NDArray[np.float64], valid: npt.NDArray[np.bool_] | None = None) -> list[DetectorEvent]:
        """Process ``samples`` (n, C) volts whose first sample has absolute ``index``.

        ``valid`` (n,) marks samples that carry data; an index gap counts as invalid samples.
        """
        if self._pending_index is None:
            self._pending_index = index  # hops start at the first sample fed
            self._first = index
        expected = self._pending_index + self._pending.shape[0]
        events: list[DetectorEvent] = []
        if index - expected > self._skip_after:
            events, expected = self._skip(expected, index, samples.shape[1])
        if index != expected:
            if index < expected:
                raise ValueError(f"block at {index} overlaps samples already fed up to {expected}")
            fed = np.ones(samples.shape[0], dtype=bool) if valid is None else valid
            samples = np.concatenate([np.zeros((index - expected, samples.shape[1])), samples])
            valid = np.concatenate([np.zeros(index - expected, dtype=bool), fed])
        # the stream from the comb's history on: head (history, then the samples pending from the last block) + samples, not
        # copied into one array (a block is ~1 MB; only the first chunk of hops reads across the join)
        head = np.concatenate([self._history, self._pending])
        hops = (self._pending.shape[0] + samples.shape[0]) // self.hop
        used = hops * self.hop
        hop_valid, self._pending_valid = _hop_validity(self._pending_valid, valid, samples.shape[0], self.hop)
        if hops:
            energy = stream_envelope(head, samples, hops, self.front)
            events += self._hops(self._pending_index, energy, hop_valid)
        history = self.front.history
        self._history = joined_rows(head, samples, used, used + history).copy()
        self._pending = joined_rows(head, samples, used + history, head.shape[0] + samples.shape[0]).copy()
        self._pending_index += used
        return events

    def _hops(self, at: int, energy: list[float], hop_valid: list[bool]) -> list[DetectorEvent]:
        """:meth:`_step` of each hop from absolute index ``at`` (envelopes, valid flags); the events with their ``at``.

        The hops of the two states nearly every hop is in, at rest below the onset level and in a slide above the quiet
        level, take a short path with the state in local variables (the same decisions and floor arithmetic as
        :meth:`_idle` and :meth:`_in_slide`); every other hop goes through :meth:`_step`.
        """
        events: list[DetectorEvent] = []
        hop, last, recent = self.hop, self._last3, self._recent
        on, off, alpha = self.c.on_factor, self.c.off_factor, self._alpha
        longest = self.c.max_slide_s * self.fs if self.c.max_slide_s > 0 else math.inf
        exp, log = math.exp, math.log
        unsettled = self._first + self.front.history  # type: ignore[operator]
        floor, sliding, settle, holdoff = self._floor, self.sliding, self._settle_until, self._holdoff_until
        shown, envelope = self.floor, self.envelope  # self.floor and self.envelope, written back before any other path
        medians = median3_runs(energy)
        run = 0  # hops just before this one whose envelopes the short path appended to ``last``, in a row
        for env, ok, med in zip(energy, hop_valid, medians, strict=True):
            if floor is not None and ok and env > 0.0 and at >= unsettled and (sliding or at >= settle):
                last.append(env)
                # the last three this hop's and the two before (their median taken ahead), or as _step takes it
                smooth = med if run >= 2 else _median3(last)
                run += 1
                if not sliding and (smooth <= on * floor or at < holdoff):  # at rest: the floor follows (as _idle)
                    shown = floor
                    if smooth > 0:
                        log_floor = log(floor)
                        floor = exp(log_floor + alpha * (log(smooth) - log_floor))
                    recent.append((at, smooth))
                    envelope = env
                    at += hop
                    continue
                # a slide goes on (as _in_slide; a loud hop after a quiet, a dip's end or a knock's, goes through it)
                if sliding and smooth >= off * floor and self._quiet_since is None and at + hop - self._start < longest:
                    recent.append((at, smooth))
                    envelope = env
                    at += hop
                    continue
                self._floor, self.floor, self.envelope = floor, shown, env
                evs = self._idle(at, smooth) if not sliding else self._in_slide(at, smooth)
            else:
                run = 0
                self._floor, self.floor, self.envelope = floor, shown, envelope
                evs = self._step(at, env, ok and at >= unsettled)
            if evs:
                events += [e if e.at >= 0 else replace(e, at=at + hop) for e in evs]
            floor, sliding, settle, holdoff = self._floor, self.sliding, self._settle_until, self._holdoff_until
            shown, envelope = self.floor, self.envelope
            at += hop
        self._floor, self.floor, self.envelope = floor, shown, envelope
        return events

    def _skip(self, expected: int, index: int, channels: int) -> tuple[list[DetectorEvent], int]:
        """A gap of lost samples from ``expected`` to ``index``, longer than :attr:`_skip_after`, in time independent of its length.

        Feeding the gap as invalid samples would end a slide in progress after ``off_hold_s`` of quiet (those hops are fed,
        a bounded number) and then only repeat what an invalid hop does at rest (no event, the recent envelopes forgotten once decided,
        settling after the gap); so the detector jumps to the last hop boundary before ``index`` in that state, with zeros
        (the gap) as the comb's history. The events are those of feeding the whole gap. Returns them and the new expected index.
        """
        events: list[DetectorEvent] = []
        head = self._skip_after // 2
        while self.sliding and index - expected > self._skip_after:
            events += self.feed(expected, np.zeros((head, channels)), np.zeros(head, dtype=bool))
            expected += head
        if index - expected <= self._skip_after:
            return events, expected
        assert self._pending_index is not None
        last = self._pending_index + (index - self._pending_index) // self.hop * self.hop  # the hop boundary at or before index
        self._settle_until = last + self._settle  # the last invalid hop starts at last - hop
        if self._floor is not None:  # as an invalid hop does (_step): at rest the recent envelopes are forgotten, undecided kept
            self._recent.clear()
        self.envelope = 0.0
        self._history = np.zeros((self.front.history, channels))
        self._pending = np.zeros((index - last, channels))
        self._pending_valid = np.zeros(index - last, dtype=bool)
        self._pending_index = last
        return events, index

    def finish(self) -> list[DetectorEvent]:
        """End of stream: a slide in progress (or a stream that never left its initial level) ends after the last sample fed."""
        if self._pending_index is None or self._first is None:
            return []
        end = self._pending_index + self._pending.shape[0]
        if self.undecided:
            began = self._began
            if end - began < self.c.min_slide_s * self.fs or not self._initial:
                return []
            self._floor = min(self._initial)
            events = [*([] if self._early else [Onset(began)]), *self._finish_at(began, end, "end_of_stream")]
            self._early = False
        elif not self.sliding:
            return []
        else:
            events = self._finish_at(self._start, self._quiet_since if self._quiet_since is not None else end, "end_of_stream")
        return [replace(e, at=end) for e in events]

    def _step(self, at: int, env: float, valid: bool = True) -> list[DetectorEvent]:
        self.envelope = env
        if not valid or env <= 0.0:
            # lost samples, or exact digital silence: nothing about the noise floor, no onset;
            # quiet for a slide in progress; the filters settle for a while after a gap
            self._settle_until = at + self.hop + self._settle
            if not self.sliding:
                if self._floor is not None:  # at rest: the onset's lookback runs over contiguous hops only
                    self._recent.clear()
                elif valid and self._reference is not None:  # undecided, its level known: exact silence is quiet (a rest of zeros)
                    self._last3.append(0.0)
                    return self._undecided(at, 0.0)
                elif valid and not self._initial:  # exact silence before any level: the stream's first slide begins after it
                    self._lead_end = at + self.hop
                # undecided: the hops around a gap still tell the stream's level; clearing them here would let a
                # link that loses a frame every few tenths of a second keep the detector undecided (no slide) for good
                return []
            env = 0.0
        elif at < self._settle_until and not self.sliding:
            return []
        last = self._last3
        last.append(env)
        if self._floor is None:  # undecided
            return self._undecided(at, env)
        # decisions at rest and in a slide use the median of the last three hops: one loud hop
        # (a spike's ringing, a knock) neither starts a slide nor interrupts the quiet that ends one
        if len(last) == 3:
            a, b, c = last
            smooth = max(min(a, b), min(max(a, b), c))
        else:
            smooth = _median3(last)
        if not self.sliding:
            return self._idle(at, smooth)
        return self._in_slide(at, smooth)

    def _undecided(self, at: int, env: float) -> list[DetectorEvent]:
        """Before the stream's initial level is known to be rest or slide (see the module docstring)."""
        c = self.c
        self._undecided_hops.append((at, env))
        if len(self._initial) < self._initial_hops:
            self._initial.append(env)
            if len(self._initial) == self._initial_hops:
                self._reference = float(np.quantile(self._initial, 0.8))  # the level of a slide, not of its dips
                if self.start_level is not None:
                    return self._start_by_level(self._reference)
            return []
        ref = self._reference or 0.0
        if self.start_level is not None and not self._early:  # a level given since the initial level was measured (a model loaded)
            return self._start_by_level(ref)
        self._recent.append((at, env))
        window = [e for _, e in list(self._recent)[-self._initial_hops:]]
        if len(window) == self._initial_hops and float(np.median(window)) > c.on_factor * ref:
            # the stream began at rest: a sustained rise (a slide's own level fluctuates hop to hop more than on_factor)
            began, early = self._began, self._early
            self._early = False
            # the rise took a window of hops to show: the slide began at its first loud hop (the median of three above the
            # quiet level, as at rest: one loud hop is a tap) that no quiet of off_hold_s, the quiet that would have ended a
            # slide, separates from this one (its dips are the slide's), with most hops from there on loud (taps at rest
            # less than off_hold_s apart are no slide)
            start = at
            hops = list(self._undecided_hops)
            envs = median3_centred([e for _, e in hops])
            loud = total = 0
            for j in range(len(hops) - 1, -1, -1):
                idx, total = hops[j][0], total + 1
                if envs[j] > c.off_factor * ref:  # the hop and its neighbours
                    loud += 1
                    if 2 * loud >= total:
                        start = idx
                elif start - idx >= c.off_hold_s * self.fs:
                    break
            self._undecided_hops.clear()
            self._floor = ref
            self.floor = ref
            self.sliding = True
            self._start = start
            self._quiet_since = None
            # a slide reported early, and now a sustained rise. A start level √on_factor or more above the model's is a
            # slide's (a quieter surface slid first): it ends where the louder one begins. One just above it was a rest
            # louder where the daemon runs than in the training recordings: withdrawn as no slide (cancelled)
            if not early:
                return [Onset(start)]
            slide = ref >= math.sqrt(c.on_factor) * (self.start_level or 0.0)
            return [Offset(began, max(start, began + 1), "quiet" if slide else "too_short", at=start), Onset(start)]
        said: list[DetectorEvent] = []  # a slide reported early (start_level): its quiets and dips, as a slide's (Quiet, Loud)
        # the median of the last three hops, as at rest and in a slide: one loud hop (a tap) does not restart the quiet
        if _median3(list(self._last3)) < ref / c.on_factor:
            if self._quiet_since is None:
                self._quiet_since = at
                if self._early:
                    said.append(Quiet(self._began, at))
            if at + self.hop - self._quiet_since >= self._undecided_hold:  # the stream began in a slide, which ended here
                assert self._first is not None
                self._floor = env if env > 0 else ref / c.on_factor**2  # a quiet of exact zeros shows no floor: well below the slide's
                self.floor = self._floor
                stop = self._quiet_since
                self._quiet_since = None
                quiet = [e for i, e in self._undecided_hops if i >= stop]
                spans = rests_split(self._undecided_hops, self._began, stop, self.hop, self.c.off_factor * float(np.median(quiet)),
                                    round(self.c.off_hold_s * self.fs), head=not self._early)
                self._undecided_hops.clear()
                events: list[DetectorEvent] = []
                for k, (a, b) in enumerate(spans):  # each known over at its end (Onset.at): no later window is its own
                    onset = [] if k == 0 and self._early else [Onset(a, b)]  # the first span's Onset, reported early, is out
                    events += [*onset, *(replace(e, at=b) for e in self._finish_at(a, b, "quiet"))]
                self._early = False
                return [*said, *events]
        else:
            if self._early and self._quiet_since is not None:
                said.append(Loud(self._began))
            self._quiet_since = None
        return said

    def _start_by_level(self, reference: float) -> list[DetectorEvent]:
        """The stream's start decided by its initial level ``reference`` against :attr:`start_level`: a slide's, so the stream
        began in one (its Onset at the first sample now, while its end is still judged against its own level, as undecided);
        or rest, the floor from now on."""
        assert self.start_level is not None
        if reference >= self.start_level:
            # the stream may have begun at rest and a slide within initial_s (a recording or daemon started just before the
            # finger moved): its first hops then lie well below the start level (a rest's are, by how it is learnt; a dip of
            # a slide rarely is). The slide then begins at the first hop above them, the floor is theirs, and it ends as any
            # slide does, where taken for one the stream began in it ran on through every rest shorter than off_hold_s +
            # initial_s and took the rest before it into its label
            envs = median3_runs([e for _, e in self._undecided_hops])
            head = next((k for k, e in enumerate(envs) if e >= self.start_level / math.sqrt(self.c.on_factor)), len(envs))
            if 2 <= head < len(envs):  # (every hop below them: a loud hop or two lifted the reference, the stream is at rest)
                floor = max(float(np.median(envs[:head])), 1e-300)
                start = self._undecided_hops[head][0]
                self._undecided_hops.clear()
                self._floor = self.floor = floor
                self.sliding = True
                self._start = start
                self._quiet_since = None
                return [Onset(start)]
            if head < len(envs) or not envs:
                self._early = True
                return [Onset(self._began)]
            reference = float(np.median(envs))
        self._undecided_hops.clear()
        self._floor = max(reference, 1e-300)
        self.floor = self._floor
        return []

    def _idle(self, at: int, env: float) -> list[DetectorEvent]:
        c, hop = self.c, self.hop
        assert self._floor is not None
        floor = self._floor
        self.floor = floor
        events: list[DetectorEvent] = []
        if env > c.on_factor * floor and at >= self._holdoff_until:
            start = at
            for idx, e in reversed(self._recent):
                if e > c.off_factor * floor and idx == start - hop:
                    start = idx
                else:
                    break
            self.sliding = True
            self._start = start
            self._quiet_since = None
            events.append(Onset(start))
        elif env > 0:
            self._floor = math.exp(math.log(floor) + self._alpha * (math.log(env) - math.log(floor)))
        self._recent.append((at, env))
        return events

    def _in_slide(self, at: int, env: float) -> list[DetectorEvent]:
        c = self.c
        assert self._floor is not None
        end = at + self.hop
        events: list[DetectorEvent] = []
        if env < c.off_factor * self._floor:
            if self._quiet_since is None:
                self._quiet_since = at
                events.append(Quiet(self._start, at))
            if end - self._quiet_since >= c.off_hold_s * self.fs:
                return events + self._finish_at(self._start, self._quiet_since, "quiet")
            if (not self._paused and end - self._quiet_since >= self._end_hold
                    and self._quiet_since - self._start >= c.min_slide_s * self.fs):
                self._paused = True
                self._recent.append((at, env))
                return [*events, Pause(self._start, self._quiet_since)]
        else:
            if self._paused:
                assert self._quiet_since is not None
                events.append(Resume(self._start, self._quiet_since))
                self._paused = False
            elif self._quiet_since is not None:
                if self._quiet_since - self._start < KNOCK_S * self.fs <= at - self._quiet_since:
                    # what started it was a knock, quiet again before it lasted KNOCK_S, and the slide begins at this hop,
                    # the first loud one since (a quiet shorter than off_hold_s would otherwise join the knock to it)
                    knock = Offset(self._start, self._quiet_since, "too_short")
                    self._start, self._quiet_since = at, None
                    self._recent.append((at, env))
                    return [knock, Onset(at)]
                events.append(Loud(self._start))  # a dip shorter than the pause
            self._quiet_since = None
            if c.max_slide_s > 0 and end - self._start >= c.max_slide_s * self.fs:
                return events + self._finish_at(self._start, end, "max_duration")
            if events:
                self._recent.append((at, env))
                return events
        self._recent.append((at, env))
        return events

    def _finish_at(self, start: int, stop: int, reason: str) -> list[DetectorEvent]:
        self.sliding = False
        self._quiet_since = None
        self._paused = False
        self._holdoff_until = stop + round(self.c.holdoff_s * self.fs)
        self._recent.clear()
        if stop - start < self.c.min_slide_s * self.fs:
            return [Offset(start, stop, "too_short")]
        return [Offset(start, stop, reason)]
