"""Online slide detection, driven by the sample index only.

The input (n, C) volts is cut into hops starting at the first sample fed; within each
hop samples beyond the hop's median ± 6 scaled MADs are clamped (spikes must not ring
through the filter), then it goes through an 8th-order Butterworth band-pass (``band_low_hz`` … min(4 kHz,
0.45·fs); DC and drift are below it) and notches (Q 5: short ringing) at the mains frequency and its
harmonics up to the 5th, with carried state. Per hop of
``hop_ms`` (hops are aligned to absolute sample indices) the envelope is the median of
the squared band-passed samples summed over channels: a 1–3-sample spike barely moves a
median, a slide moves all of it. A noise floor tracks the envelope while idle (exponential
in the log domain, time constant ``floor_tau_s``); hops of exact digital silence (zero-filled
lost samples) never move it: hops with lost samples (``valid``) never start a slide nor move
the floor, count as quiet within a slide, and the 20 ms after them let the filters settle. A slide starts when the envelope
exceeds ``on_factor`` × floor (its onset is moved back over the hops just before that were
above ``off_factor`` × floor), and ends when it stays below ``off_factor`` × floor for
``off_hold_s``, or after ``max_slide_s``. Slides shorter than ``min_slide_s`` are dropped;
after a slide nothing starts for ``holdoff_s``.

The same samples in blocks of any size give identical events.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

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
    start: int  # absolute sample index of the onset


@dataclass(frozen=True)
class SlideEnd:
    start: int
    stop: int  # absolute index one past the last sample of the slide
    reason: str = "quiet"  # quiet | max_duration


Event = SlideStart | SlideEnd


class SlideDetector:
    """Feed (index, samples) blocks in order; returns :class:`SlideStart` / :class:`SlideEnd` events."""

    def __init__(self, config: DetectorConfig, fs: float, channels: int) -> None:
        self.c = config
        self.fs = fs
        self.hop = max(1, round(config.hop_ms * 1e-3 * fs))
        high = min(4000.0, 0.45 * fs)
        low = min(config.band_low_hz, 0.3 * high)
        sections = [signal.butter(2, [low, high], btype="bandpass", fs=fs, output="sos")]
        harmonic = config.mains_hz
        while config.mains_hz > 0 and harmonic < min(5.5 * config.mains_hz, 0.45 * fs):
            b, a = signal.iirnotch(harmonic, 5.0, fs=fs)
            sections.append(signal.tf2sos(b, a))
            harmonic += config.mains_hz
        self._sos = np.concatenate(sections)
        self._zi = np.zeros((self._sos.shape[0], 2, channels))
        self._pending = np.zeros((0, channels))
        self._pending_valid = np.zeros(0, dtype=bool)
        self._pending_index: int | None = None
        self._settle = round(0.02 * fs)  # after lost samples the filters ring: no onset, no floor update
        self._settle_until = -1
        self._floor: float | None = None
        self._alpha = 1.0 - math.exp(-self.hop / (config.floor_tau_s * fs))
        self._recent: deque[tuple[int, float]] = deque(maxlen=max(1, round(0.2 * fs / self.hop)))
        self.sliding = False
        self._start = 0
        self._quiet_since: int | None = None
        self._holdoff_until = -1
        self._warmup = max(1, round(0.05 * fs / self.hop))
        self._hops_seen = 0
        self.envelope = 0.0
        self.floor = 0.0

    def feed(self, index: int, samples: npt.NDArray[np.float64], valid: npt.NDArray[np.bool_] | None = None) -> list[Event]:
        """Process ``samples`` (n, C) volts whose first sample has absolute ``index``.

        ``valid`` (n,) marks samples that carry data; an index gap counts as invalid samples.
        """
        if valid is None:
            valid = np.ones(samples.shape[0], dtype=bool)
        if self._pending_index is None:
            self._pending_index = index  # hops start at the first sample fed
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
            lim = 6 * 1.4826 * median_last(np.abs(raw - med), keepdims=True)
            clean = np.clip(raw, med - lim, med + lim).transpose(0, 2, 1).reshape(hops * self.hop, -1)
            filtered, self._zi = signal.sosfilt(self._sos, clean, axis=0, zi=self._zi)
            sq = np.ascontiguousarray((filtered.reshape(hops, self.hop, -1) ** 2).transpose(0, 2, 1))
            energy = median_last(sq).sum(axis=1)
            hop_valid = np.asarray(vbuf[: hops * self.hop].reshape(hops, self.hop).all(axis=1), dtype=bool)
            for h in range(hops):
                events += self._step(self._pending_index + h * self.hop, float(energy[h]), bool(hop_valid[h]))
        self._pending = buf[hops * self.hop:]
        self._pending_valid = vbuf[hops * self.hop:]
        self._pending_index += hops * self.hop
        return events

    def finish(self) -> list[Event]:
        """End of stream: a slide in progress ends after the last sample fed (reason ``end_of_stream``)."""
        if not self.sliding or self._pending_index is None:
            return []
        end = self._pending_index + self._pending.shape[0]
        return self._finish(self._quiet_since if self._quiet_since is not None else end, "end_of_stream")

    def _step(self, at: int, env: float, valid: bool = True) -> list[Event]:
        c, hop = self.c, self.hop
        self.envelope = env
        self._hops_seen += 1
        if not valid or env <= 0.0:
            # lost samples, or exact digital silence: nothing about the noise floor, no onset;
            # quiet for a slide in progress; the filters settle for a while after a gap
            self._settle_until = at + hop + self._settle
            if self._floor is None or not self.sliding:
                self._recent.clear()
                return []
            env = 0.0
        if self._floor is None:
            self._floor = env
            self._hops_seen = 1
        floor = self._floor
        self.floor = floor
        events: list[Event] = []
        if not self.sliding:
            if self._hops_seen <= self._warmup:
                self._floor = min(floor, env) if env > 0 else floor
            elif env > c.on_factor * floor and at >= max(self._holdoff_until, self._settle_until):
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
            elif at >= self._settle_until:
                self._floor = math.exp(math.log(floor) + self._alpha * (math.log(env) - math.log(floor)))
            self._recent.append((at, env))
            return events
        # sliding
        end = at + hop
        if env < c.off_factor * floor:
            if self._quiet_since is None:
                self._quiet_since = at
            if end - self._quiet_since >= c.off_hold_s * self.fs:
                events += self._finish(self._quiet_since, "quiet")
        else:
            self._quiet_since = None
            if end - self._start >= c.max_slide_s * self.fs:
                events += self._finish(end, "max_duration")
        self._recent.append((at, env))
        return events

    def _finish(self, stop: int, reason: str) -> list[Event]:
        self.sliding = False
        self._holdoff_until = stop + round(self.c.holdoff_s * self.fs)
        self._recent.clear()
        if stop - self._start < self.c.min_slide_s * self.fs:
            return [SlideEnd(self._start, stop, "too_short")]
        return [SlideEnd(self._start, stop, reason)]
