"""Online slide detection, driven by the sample index only; every threshold relative or in seconds.

Envelope: the input (n, C) volts is cut into hops of ``hop_ms``, at least ``hop_min_samples``
(so that a hop's median is stable at low rates), aligned to the first sample fed; within each hop, samples beyond the hop's median ± ``clamp_mads`` scaled MADs
are clamped (spikes must not ring through the filter); then a Butterworth band-pass
(``band_low_hz`` … min(``band_high_hz``, ``band_high_frac``·fs); DC, offsets and drift are
below it; its state starts at the first sample's steady state, so an offset does not ring)
and notches at the mains frequency and its harmonics up to the 5th (Q ``notch_q``). The
envelope of a hop is the median of its squared filtered samples, summed over channels: a
1–3-sample spike barely moves a median, a slide moves all of it. Decisions at rest and in a
slide use the median envelope of the last three hops, so one loud hop neither starts a slide
nor interrupts the quiet that ends one.

States. The detector starts *undecided*: it does not know whether the stream began at rest
or in the middle of a slide. Its reference is the median envelope over the first
``initial_s``. If the median envelope over the last ``initial_s`` then rises above
``on_factor`` × the reference (a sustained rise: the level of a slide fluctuates from hop to
hop by more than that), the stream began at rest: the reference becomes the noise floor and a slide starts. If it stays below
reference / ``on_factor`` for ``off_hold_s``, the stream began in a slide: a slide from the
first sample to the drop is reported (a retroactive :class:`SlideStart`), and the low level
becomes the floor. If neither happens before :meth:`SlideDetector.finish`, the whole stream
was one slide (reason ``end_of_stream``).

At rest, the floor tracks the envelope (exponential in the log domain, ``floor_tau_s``). A
slide starts when the envelope exceeds ``on_factor`` × floor (its onset moved back over the
hops of the last ``lookback_s`` that were above ``off_factor`` × floor) and ends when it stays
below ``off_factor`` × floor for ``off_hold_s`` (the reported stop is where the quiet
began, so a level dip inside a slide shorter than ``off_hold_s`` never splits it), or after
``max_slide_s``. Slides shorter than ``min_slide_s`` are dropped (reason ``too_short``);
after a slide nothing starts for ``holdoff_s``.

Lost samples (``valid`` False, and index gaps) never start a slide nor move the floor,
count as quiet within a slide, and the ``settle_s`` after them let the filters settle; so
do hops of exact digital silence. The same samples in blocks of any size give identical
events.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt
from scipy import signal

from tactiled.config import DetectorConfig


def median_last(a: npt.NDArray[np.float64], keepdims: bool = False) -> npt.NDArray[np.float64]:
    """The median along the last axis, by ``np.partition`` (same values as ``np.median``, less overhead)."""
    m = a.shape[-1]
    k = m // 2
    if m % 2:
        out = np.partition(a, k, axis=-1)[..., k]
    else:
        p = np.partition(a, (k - 1, k), axis=-1)
        out = (p[..., k - 1] + p[..., k]) / 2
    return out[..., None] if keepdims else out


@dataclass(frozen=True)
class SlideStart:
    start: int  # absolute sample index of the onset (may lie before the samples just fed: see the module docstring)
    at: int = -1  # the index up to which the detector had seen samples when it decided (for ordering; -1: unknown)


@dataclass(frozen=True)
class SlideEnd:
    start: int
    stop: int  # absolute index one past the last sample of the slide
    reason: str = "quiet"  # quiet | max_duration | end_of_stream | too_short
    at: int = -1  # the index up to which the detector had seen samples when it decided


Event = SlideStart | SlideEnd


def envelope_filter(config: DetectorConfig, fs: float) -> npt.NDArray[np.float64]:
    """Second-order sections of the envelope's band-pass and mains notches at rate ``fs``."""
    high = min(config.band_high_hz, config.band_high_frac * fs)
    low = min(config.band_low_hz, 0.3 * high)
    sections = [signal.butter(2, [low, high], btype="bandpass", fs=fs, output="sos")]
    harmonic = config.mains_hz
    while config.mains_hz > 0 and harmonic < min(5.5 * config.mains_hz, config.band_high_frac * fs):
        b, a = signal.iirnotch(harmonic, config.notch_q, fs=fs)
        sections.append(signal.tf2sos(b, a))
        harmonic += config.mains_hz
    return np.concatenate(sections)


class SlideDetector:
    """Feed (index, samples) blocks in order, then :meth:`finish`; both return :class:`SlideStart` / :class:`SlideEnd` events."""

    def __init__(self, config: DetectorConfig, fs: float, channels: int) -> None:
        self.c = config
        self.fs = fs
        self.hop = max(config.hop_min_samples, round(config.hop_ms * 1e-3 * fs))
        self._sos = envelope_filter(config, fs)
        self._zi: npt.NDArray[np.float64] | None = None  # set from the first sample
        self._pending = np.zeros((0, channels))
        self._pending_valid = np.zeros(0, dtype=bool)
        self._pending_index: int | None = None
        self._first: int | None = None
        self._settle = round(config.settle_s * fs)
        self._settle_until = -1
        self._floor: float | None = None
        self._alpha = 1.0 - math.exp(-self.hop / (config.floor_tau_s * fs))
        self._initial: list[float] = []  # undecided: envelopes of the first initial_s
        self._initial_hops = max(1, round(config.initial_s * fs / self.hop))
        lookback = max(1, round(config.lookback_s * fs / self.hop))
        self._recent: deque[tuple[int, float]] = deque(maxlen=max(lookback, self._initial_hops))
        self._reference: float | None = None
        self.sliding = False
        self._start = 0
        self._quiet_since: int | None = None
        self._holdoff_until = -1
        self._last3: deque[float] = deque(maxlen=3)
        self.envelope = 0.0
        self.floor = 0.0

    @property
    def undecided(self) -> bool:
        """True until the detector knows whether the stream began at rest or in a slide."""
        return self._floor is None

    def feed(self, index: int, samples: npt.NDArray[np.float64], valid: npt.NDArray[np.bool_] | None = None) -> list[Event]:
        """Process ``samples`` (n, C) volts whose first sample has absolute ``index``.

        ``valid`` (n,) marks samples that carry data; an index gap counts as invalid samples.
        """
        if valid is None:
            valid = np.ones(samples.shape[0], dtype=bool)
        if self._pending_index is None:
            self._pending_index = index  # hops start at the first sample fed
            self._first = index
        expected = self._pending_index + self._pending.shape[0]
        if index != expected:
            if index < expected:
                raise ValueError(f"block at {index} overlaps samples already fed up to {expected}")
            samples = np.concatenate([np.zeros((index - expected, samples.shape[1])), samples])
            valid = np.concatenate([np.zeros(index - expected, dtype=bool), valid])
        buf = np.concatenate([self._pending, samples]) if self._pending.shape[0] else samples
        vbuf = np.concatenate([self._pending_valid, valid]) if self._pending_valid.shape[0] else valid
        hops = buf.shape[0] // self.hop
        events: list[Event] = []
        if hops:
            # (hops, C, hop), contiguous along the hop: medians reduce along the last axis
            raw = np.ascontiguousarray(buf[: hops * self.hop].reshape(hops, self.hop, -1).transpose(0, 2, 1))
            # clamp spikes within each hop before the filter, so they do not ring through it
            med = median_last(raw, keepdims=True)
            lim = self.c.clamp_mads * 1.4826 * median_last(np.abs(raw - med), keepdims=True)
            clean = np.clip(raw, med - lim, med + lim).transpose(0, 2, 1).reshape(hops * self.hop, -1)
            if self._zi is None:  # start at the first sample's steady state: an offset does not ring
                self._zi = signal.sosfilt_zi(self._sos)[:, :, None] * clean[0][None, None, :]
            filtered, self._zi = signal.sosfilt(self._sos, clean, axis=0, zi=self._zi)
            sq = np.ascontiguousarray((filtered.reshape(hops, self.hop, -1) ** 2).transpose(0, 2, 1))
            energy = median_last(sq).sum(axis=1)
            hop_valid = np.asarray(vbuf[: hops * self.hop].reshape(hops, self.hop).all(axis=1), dtype=bool)
            for h in range(hops):
                at = self._pending_index + h * self.hop
                events += [replace(e, at=at + self.hop) for e in self._step(at, float(energy[h]), bool(hop_valid[h]))]
        self._pending = buf[hops * self.hop:]
        self._pending_valid = vbuf[hops * self.hop:]
        self._pending_index += hops * self.hop
        return events

    def finish(self) -> list[Event]:
        """End of stream: a slide in progress (or a stream that never left its initial level) ends after the last sample fed."""
        if self._pending_index is None or self._first is None:
            return []
        end = self._pending_index + self._pending.shape[0]
        if self.undecided:
            if end - self._first < self.c.min_slide_s * self.fs or not self._initial:
                return []
            self._floor = min(self._initial)
            events = [SlideStart(self._first), *self._finish_at(self._first, end, "end_of_stream")]
        elif not self.sliding:
            return []
        else:
            events = self._finish_at(self._start, self._quiet_since if self._quiet_since is not None else end, "end_of_stream")
        return [replace(e, at=end) for e in events]

    def _step(self, at: int, env: float, valid: bool = True) -> list[Event]:
        self.envelope = env
        if not valid or env <= 0.0:
            # lost samples, or exact digital silence: nothing about the noise floor, no onset;
            # quiet for a slide in progress; the filters settle for a while after a gap
            self._settle_until = at + self.hop + self._settle
            if not self.sliding:
                self._recent.clear()
                return []
            env = 0.0
        elif at < self._settle_until and not self.sliding:
            return []
        if self.undecided:
            self._last3.append(env)
            return self._undecided(at, env)
        # decisions at rest and in a slide use the median of the last three hops: one loud hop
        # (a spike's ringing, a knock) neither starts a slide nor interrupts the quiet that ends one
        self._last3.append(env)
        smooth = float(np.median(self._last3))
        if not self.sliding:
            return self._idle(at, smooth)
        return self._in_slide(at, smooth)

    def _undecided(self, at: int, env: float) -> list[Event]:
        """Before the stream's initial level is known to be rest or slide (see the module docstring)."""
        c = self.c
        if len(self._initial) < self._initial_hops:
            self._initial.append(env)
            if len(self._initial) == self._initial_hops:
                self._reference = float(np.median(self._initial))
            return []
        ref = self._reference or 0.0
        self._recent.append((at, env))
        window = [e for _, e in list(self._recent)[-self._initial_hops:]]
        if len(window) == self._initial_hops and float(np.median(window)) > c.on_factor * ref:
            # the stream began at rest: a sustained rise (a slide's own level fluctuates hop to hop more than on_factor)
            self._floor = ref
            self.floor = ref
            start = at
            for idx, e in reversed(self._recent):
                if e > c.off_factor * ref and idx == start - self.hop:
                    start = idx
                elif idx < start:
                    break
            self.sliding = True
            self._start = start
            self._quiet_since = None
            return [SlideStart(start)]
        if env < ref / c.on_factor:
            if self._quiet_since is None:
                self._quiet_since = at
            if at + self.hop - self._quiet_since >= c.off_hold_s * self.fs:  # the stream began in a slide, which ended here
                assert self._first is not None
                self._floor = max(env, 1e-300)
                self.floor = self._floor
                stop = self._quiet_since
                self._quiet_since = None
                return [SlideStart(self._first), *self._finish_at(self._first, stop, "quiet")]
        else:
            self._quiet_since = None
        return []

    def _idle(self, at: int, env: float) -> list[Event]:
        c, hop = self.c, self.hop
        assert self._floor is not None
        floor = self._floor
        self.floor = floor
        events: list[Event] = []
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
            events.append(SlideStart(start))
        elif env > 0:
            self._floor = math.exp(math.log(floor) + self._alpha * (math.log(env) - math.log(floor)))
        self._recent.append((at, env))
        return events

    def _in_slide(self, at: int, env: float) -> list[Event]:
        c = self.c
        assert self._floor is not None
        end = at + self.hop
        if env < c.off_factor * self._floor:
            if self._quiet_since is None:
                self._quiet_since = at
            if end - self._quiet_since >= c.off_hold_s * self.fs:
                return self._finish_at(self._start, self._quiet_since, "quiet")
        else:
            self._quiet_since = None
            if c.max_slide_s > 0 and end - self._start >= c.max_slide_s * self.fs:
                return self._finish_at(self._start, end, "max_duration")
        self._recent.append((at, env))
        return []

    def _finish_at(self, start: int, stop: int, reason: str) -> list[Event]:
        self.sliding = False
        self._quiet_since = None
        self._holdoff_until = stop + round(self.c.holdoff_s * self.fs)
        self._recent.clear()
        if stop - start < self.c.min_slide_s * self.fs:
            return [SlideEnd(start, stop, "too_short")]
        return [SlideEnd(start, stop, reason)]
