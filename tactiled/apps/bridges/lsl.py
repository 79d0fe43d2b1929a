"""Lab Streaming Layer outlets (``tactiled lsl``, extra ``tactiled[lsl]``).

Two outlets per sensor, both created at start-up (before any sample: LabRecorder lists them
while it waits), from the config and the daemon's first status:

- ``tactiled-<id>`` (type ``Tactile``, source id ``tactiled-<id>-raw``): one float32 channel per
  film in volts, labelled ``film1`` …, nominal rate the board's ``fs``. Each intact sample is
  stamped with the daemon's host monotonic time for it (``index_mono + k / fs_clock``: the clock
  LSL's ``local_clock()`` reads on Linux; increasing, docs/messages.md). Lost samples are not
  pushed (``nan_lost``: pushed as NaN rows at their own times, so the stream stays regular);
  either way each lost range is a marker. The description carries, per channel, ``label``,
  ``unit`` (volts), ``type`` (PVDF) and ``scale`` (V per count), and under ``acquisition``: the
  manufacturer, sensor id, firmware rate, scale, ADC bits, model fingerprint (as at start-up),
  versions and how time and losses are given. A samples message whose channels, rate or scale
  differ from the outlet's makes the outlet again (same source id: LSL inlets recover).
- ``tactiled-<id>-labels`` (type ``Markers``, one string channel, irregular rate): JSON markers.
  ``{"event": "roughness", label, reason, confidence, final, used_s, slide_id, start, stop,
  model}`` per roughness message, stamped at the host time of the slide's ``stop``; and
  ``{"event": "lost", "index": first lost sample, "count": n}`` per lost range, stamped at the
  time of its first sample.
"""

from __future__ import annotations

import json
import logging
from typing import Any

import numpy as np
from tactiled_client import Roughness, Samples, Slide, Status

from tactiled import __version__
from tactiled.apps.bridges import StreamMeta, lost_ranges, volts
from tactiled.extras import need

log = logging.getLogger("tactiled")
MARKER_FIELDS = ("label", "reason", "confidence", "final", "used_s", "slide_id", "start", "stop", "model")


def raw_description(info: Any, meta: StreamMeta, nan_lost: bool) -> None:
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
                       ("lost_samples", "a marker on tactiled-<id>-labels per lost range" + ("; NaN rows here" if nan_lost else "; not pushed"))):
        acq.append_child_value(key, value)


class LslSink:
    """Both outlets of one sensor, from start-up."""

    def __init__(self, meta: StreamMeta, nan_lost: bool = False) -> None:
        self.lsl: Any = need("pylsl", "lsl")
        self.meta = meta
        self.nan_lost = nan_lost
        sensor = meta.sensor
        info = self.lsl.StreamInfo(f"tactiled-{sensor}-labels", "Markers", 1, self.lsl.IRREGULAR_RATE, "string", f"tactiled-{sensor}-labels")
        info.desc().append_child("acquisition").append_child_value("sensor_id", sensor)
        self.markers: Any = self.lsl.StreamOutlet(info)
        self.raw: Any = self._raw_outlet(meta)
        self.pushed = 0
        self.lost_marked = 0

    def _raw_outlet(self, meta: StreamMeta) -> Any:
        info = self.lsl.StreamInfo(f"tactiled-{meta.sensor}", "Tactile", meta.channels, meta.fs, "float32", f"tactiled-{meta.sensor}-raw")
        raw_description(info, meta, self.nan_lost)
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

        Each lost range also gets a ``lost`` marker; a change of channels, rate or scale makes the raw outlet again first.
        """
        self._check(msg)
        v, valid, t = volts(msg)
        assert isinstance(v, np.ndarray) and isinstance(valid, np.ndarray)
        stamps = t if isinstance(t, np.ndarray) else None
        period = 1.0 / (msg.fs_clock or msg.fs)
        for first, count in lost_ranges(msg):
            at = 0.0 if stamps is None else (stamps[0] + (first - msg.index) * period if first < msg.index else stamps[first - msg.index])
            self.markers.push_sample([json.dumps({"event": "lost", "index": first, "count": count})], float(at))
            self.lost_marked += 1
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
        """Drop both outlets (pylsl closes an outlet when it is collected)."""
        self.raw = None
        self.markers = None
