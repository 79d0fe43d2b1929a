"""Lab Streaming Layer outlets (``tactiled lsl``, extra ``tactiled[lsl]``).

Two outlets per sensor, both created at start-up (before any sample: LabRecorder lists them
while it waits), from the config and the daemon's first status:

- ``tactiled-<id>`` (type ``Tactile``, source id ``tactiled-<id>-raw``): one float32 channel per
  film in volts, labelled ``film1`` …, nominal rate the board's ``fs``. Each intact sample is
  stamped with the daemon's host monotonic time for it (``index_mono + k / fs_clock``: the clock
  LSL's ``local_clock()`` reads on Linux; increasing, docs/messages.md). Lost samples are not
  pushed; with ``nan_lost`` they are NaN rows at their own times, so the stream stays regular:
  the rows the daemon sends as lost, the gaps it only counts (``lost_before``, over 1 s) and the
  gaps the bridge finds itself from the index (a daemon restart with the board's index carrying on,
  samples messages the bridge missed), each up to ``nan_max_s`` (:data:`NAN_FILL_MAX_S`) long; a gap
  in the index is stamped evenly from where the last row pushed ended to the next row. Either way
  each lost range is a marker. The description carries, per channel, ``label``,
  ``unit`` (volts), ``type`` (PVDF) and ``scale`` (V per count), and under ``acquisition``: the
  manufacturer, sensor id, firmware rate, scale, ADC bits, model fingerprint (as at start-up),
  versions and how time and losses are given. A samples message whose channels, rate or scale
  differ from the outlet's makes the outlet again (same source id: LSL inlets recover).
- ``tactiled-<id>-labels`` (type ``Markers``, one string channel, irregular rate): JSON markers.
  ``{"event": "roughness", label, reason, confidence, final, used_s, slide_id, start, stop,
  model, novelty}`` per roughness message, stamped at the host time of the slide's ``stop`` (``slide_id`` begins again
  when the daemon restarts: ``slide_id`` and ``start`` together name a slide); and
  ``{"event": "lost", "index": first lost sample, "count": n, "filled": NaN rows stand for it}`` per
  lost range, stamped at the time of its first sample; ``{"event": "lost", "index": null, "count":
  null, "next": index, "filled": false}`` when the index went back (a daemon restarted with a
  fresh index: how many were lost is unknown), stamped where the last row pushed ended; and
  ``{"event": "resumed", slide_id, start, stop}`` when a slide said to have ended goes on (its
  final label is withdrawn; the slide's real final label follows), stamped at the withdrawn ``stop``.
"""

from __future__ import annotations

import json
import logging
from typing import Any

import numpy as np
from tactiled_client import Roughness, Samples, Slide, Status

from tactiled import __version__
from tactiled.apps.bridges import StreamMeta, volts
from tactiled.extras import need

log = logging.getLogger("tactiled")
NAN_FILL_MAX_S = 30.0  # longest gap pushed as NaN rows (s at the nominal rate: 600 000 rows at 20 kHz, half the outlet's buffer)
MARKER_FIELDS = ("label", "reason", "confidence", "final", "used_s", "slide_id", "start", "stop", "model", "novelty")


def raw_description(info: Any, meta: StreamMeta, nan_lost: bool, nan_max_s: float = NAN_FILL_MAX_S) -> None:
    """Fill an LSL StreamInfo's description (XDF conventions: ``channels/channel``, ``acquisition``) from ``meta``."""
    channels = info.desc().append_child("channels")
    for k in range(meta.channels):
        ch = channels.append_child("channel")
        ch.append_child_value("label", f"film{k + 1}")
        ch.append_child_value("unit", "volts")
        ch.append_child_value("type", "PVDF")
        ch.append_child_value("scale", repr(meta.volts_per_count))
    acq = info.desc().append_child("acquisition")
    for key, value in (("manufacturer", "tactiled"), ("model", "two-film PVDF fingertip"), ("sensor_id", meta.sensor),
                       ("fs_firmware", repr(meta.fs)), ("volts_per_count", repr(meta.volts_per_count)), ("adc_bits", "16"),
                       ("model_fingerprint", meta.model), ("daemon_version", meta.version), ("bridge_version", __version__),
                       ("clock", "host CLOCK_MONOTONIC (pylsl.local_clock) mapped from the sensor's sample index: increasing"),
                       ("lost_samples", "a marker on tactiled-<id>-labels per lost range"
                        + (f"; NaN rows here (a gap up to {nan_max_s:g} s)" if nan_lost else "; not pushed"))):
        acq.append_child_value(key, value)


class LslSink:
    """Both outlets of one sensor, from start-up."""

    def __init__(self, meta: StreamMeta, nan_lost: bool = False, nan_max_s: float = NAN_FILL_MAX_S, lsl: Any = None) -> None:
        """``nan_max_s``: the longest gap (s at the nominal rate) pushed as NaN rows with ``nan_lost``; ``lsl``: the pylsl module (a test's fake)."""
        self.lsl: Any = lsl or need("pylsl", "lsl")
        self.meta = meta
        self.nan_lost = nan_lost
        self.nan_max_s = nan_max_s
        self.next_index: int | None = None  # index of the row after the last samples message
        self.next_mono: float | None = None  # its host monotonic time (where the last message's rows end), s
        sensor = meta.sensor
        info = self.lsl.StreamInfo(f"tactiled-{sensor}-labels", "Markers", 1, self.lsl.IRREGULAR_RATE, "string", f"tactiled-{sensor}-labels")
        info.desc().append_child("acquisition").append_child_value("sensor_id", sensor)
        self.markers: Any = self.lsl.StreamOutlet(info)
        self.raw: Any = self._raw_outlet(meta)
        self.pushed = 0  # rows pushed on the raw outlet, NaN rows included
        self.nan_filled = 0  # NaN rows pushed for gaps between messages
        self.lost_marked = 0
        self._open: tuple[dict[str, Any], float | None] | None = None  # a lost range reaching the last message's end, and its time:
        # its marker waits for the next message, whose first rows may be the same range going on (one range, one marker)

    def _raw_outlet(self, meta: StreamMeta) -> Any:
        info = self.lsl.StreamInfo(f"tactiled-{meta.sensor}", "Tactile", meta.channels, meta.fs, "float32", f"tactiled-{meta.sensor}-raw")
        raw_description(info, meta, self.nan_lost, self.nan_max_s)
        return self.lsl.StreamOutlet(info, chunk_size=0, max_buffered=60)

    def _check(self, msg: Samples) -> None:
        m = self.meta
        if (msg.channels, msg.fs, msg.volts_per_count) != (m.channels, m.fs, m.volts_per_count):
            log.warning("sensor %s sends %d channels at %g Hz, %g V/count; the outlet said %d at %g Hz, %g V/count: made again",
                        m.sensor, msg.channels, msg.fs, msg.volts_per_count, m.channels, m.fs, m.volts_per_count)
            self.meta = StreamMeta(m.sensor, msg.channels, msg.fs, msg.volts_per_count, m.model, m.version)
            self.raw = self._raw_outlet(self.meta)

    def samples(self, msg: Samples) -> None:
        """Push the message's rows as float32 volts (n, C), each at its host monotonic time (s); lost rows left out (NaN with ``nan_lost``).

        Each lost range also gets a ``lost`` marker: those the message lists, and the samples between
        the last message and this one (its ``lost_before``, or a jump of the index the daemon did not
        announce: a daemon restart, messages missed), as one range; an index that went back is a
        marker of unknown count. A range that goes on across messages is one marker, pushed once it ends
        (stamped at its first sample). A change of channels, rate or scale makes the raw outlet again first.
        """
        self._check(msg)
        v, valid, t = volts(msg)
        assert isinstance(v, np.ndarray) and isinstance(valid, np.ndarray)
        stamps = t if isinstance(t, np.ndarray) else None
        period = 1.0 / (msg.fs_clock or msg.fs)
        first_at = None if stamps is None or msg.n == 0 else float(stamps[0])
        gap_first, gap = msg.index - msg.lost_before, msg.lost_before
        if self.next_index is not None and gap_first != self.next_index:
            if gap_first > self.next_index:  # not announced: the daemon restarted (the board's index carried on) or messages were missed
                gap_first, gap = self.next_index, msg.index - self.next_index
            else:  # the index went back: a daemon restarted with a fresh index; how many were lost is unknown
                self._close_open()
                self._marker({"event": "lost", "index": None, "count": None, "next": msg.index, "filled": False},
                             self.next_mono if self.next_mono is not None else first_at)
        first_lost = gap_first if gap else msg.index if msg.lost and msg.lost[0][0] == 0 else None
        if self._open is not None and first_lost != self._open[0]["index"] + self._open[0]["count"]:
            self._close_open()  # this message does not go on with the range left open: it ended with the last one
        if gap:
            fill = self.nan_lost and gap <= self.nan_max_s * self.meta.fs
            gap_stamps = None if first_at is None else self._gap_stamps(gap if fill else 1, gap, first_at, period)
            goes_on = msg.n == 0 or (bool(msg.lost) and msg.lost[0][0] == 0)  # the message's first rows lost too: one range
            self._lost(gap_first, gap, fill, None if gap_stamps is None else float(gap_stamps[0]), open_end=goes_on)
            if fill:
                self._push_nan(gap, gap_stamps)
        for p, count in msg.lost:
            self._lost(msg.index + p, count, self.nan_lost, None if stamps is None else float(stamps[p]), open_end=p + count == msg.n)
        self.next_index = msg.index + msg.n
        self.next_mono = None if msg.index_mono is None else msg.index_mono + msg.n * period
        rows = np.ones(msg.n, dtype=bool) if self.nan_lost else valid
        if self.nan_lost:
            v[~valid] = np.nan
        if not rows.any():
            return
        if stamps is None:
            self.raw.push_chunk(v[rows])
        else:
            self.raw.push_chunk(v[rows], timestamp=stamps[rows].tolist())
        self.pushed += int(rows.sum())

    def _gap_stamps(self, rows: int, gap: int, next_at: float, period: float) -> np.ndarray:
        """Host times of the first ``rows`` of ``gap`` lost rows before the row at ``next_at``.

        Evenly from where the last message ended to ``next_at``; a ``period`` apart when that is unknown.
        """
        k = np.arange(rows, dtype=np.float64)
        if self.next_mono is not None and next_at > self.next_mono:
            return self.next_mono + k * ((next_at - self.next_mono) / gap)
        return next_at - (gap - k) * period

    def _push_nan(self, rows: int, stamps: np.ndarray | None) -> None:
        """Push ``rows`` NaN rows, a second of them at a time (at their ``stamps``; now when None)."""
        step = max(1, int(self.meta.fs))
        for lo in range(0, rows, step):
            block = np.full((min(step, rows - lo), self.meta.channels), np.nan, dtype=np.float32)
            if stamps is None:
                self.raw.push_chunk(block)
            else:
                self.raw.push_chunk(block, timestamp=stamps[lo:lo + len(block)].tolist())
        self.pushed += rows
        self.nan_filled += rows

    def _lost(self, index: int, count: int, filled: bool, at: float | None, open_end: bool) -> None:
        """A ``lost`` marker for ``count`` samples from ``index`` (stamped ``at``), or the open range it goes on with;
        ``open_end``: the range reaches the message's end, so its marker waits for the next message."""
        if self._open is not None:
            event = self._open[0]
            if event["index"] + event["count"] == index and event["filled"] == filled:
                event["count"] += count
                if not open_end:
                    self._close_open()
                return
            self._close_open()
        event = {"event": "lost", "index": index, "count": count, "filled": filled}
        if open_end:
            self._open = (event, at)
        else:
            self._marker(event, at)

    def _close_open(self) -> None:
        """Push the marker of the lost range left open at the last message's end, if any."""
        if self._open is not None:
            event, at = self._open
            self._open = None
            self._marker(event, at)

    def _marker(self, event: dict[str, Any], at: float | None) -> None:
        self.markers.push_sample([json.dumps(event)], 0.0 if at is None else float(at))
        self.lost_marked += 1

    def roughness(self, msg: Roughness) -> None:
        """Push a ``roughness`` JSON marker, stamped at the host monotonic time of the slide's ``stop`` (s; 0 when unknown)."""
        marker = json.dumps({"event": "roughness", **{k: getattr(msg, k) for k in MARKER_FIELDS}})
        self.markers.push_sample([marker], msg.stop_mono or 0.0)

    def withdrawn(self, msg: Slide) -> None:
        """Push a ``resumed`` JSON marker (slide_id, start, stop: the final label of that slide is withdrawn), stamped at the withdrawn ``stop``."""
        marker = json.dumps({"event": "resumed", "slide_id": msg.slide_id, "start": msg.start, "stop": msg.stop})
        self.markers.push_sample([marker], msg.stop_mono or 0.0)

    def status(self, msg: Status) -> None:
        """Ignored: LSL carries no status."""
        pass

    def close(self) -> None:
        """Push the marker of a lost range still open, then drop both outlets (pylsl closes an outlet when it is collected)."""
        if self.markers is not None:
            self._close_open()
        self.raw = None
        self.markers = None
