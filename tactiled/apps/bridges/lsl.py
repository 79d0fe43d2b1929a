"""Lab Streaming Layer outlets (``tactiled lsl``, extra ``tactiled[lsl]``).

Two outlets per sensor: ``tactiled-<id>`` (type ``Tactile``, one float32 channel per film in
volts, labelled ``film1`` …, nominal rate ``fs``) with the intact samples, each stamped with its
host monotonic time from the daemon's clock mapping (``index_mono + k / fs_clock``: the clock
LSL's ``local_clock()`` reads on Linux); lost samples are not pushed. And
``tactiled-<id>-labels`` (type ``Markers``, one string channel, irregular rate): one JSON marker
per roughness message (label, reason, confidence, final, used_s, slide_id, start, stop) stamped
at the host time of the slide's ``stop``.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
from tactiled_client import Roughness, Samples, Status

from tactiled.apps.bridges import volts
from tactiled.extras import need

MARKER_FIELDS = ("label", "reason", "confidence", "final", "used_s", "slide_id", "start", "stop")


class LslSink:
    """Creates the outlets on the first samples message (channels and rate come from it)."""

    def __init__(self, sensor: str) -> None:
        self.lsl: Any = need("pylsl", "lsl")
        self.sensor = sensor
        self.raw: Any = None
        info = self.lsl.StreamInfo(f"tactiled-{sensor}-labels", "Markers", 1, self.lsl.IRREGULAR_RATE, "string", f"tactiled-{sensor}-labels")
        self.markers = self.lsl.StreamOutlet(info)
        self.pushed = 0

    def _raw_outlet(self, msg: Samples) -> Any:
        info = self.lsl.StreamInfo(f"tactiled-{self.sensor}", "Tactile", msg.channels, msg.fs, "float32", f"tactiled-{self.sensor}-raw")
        channels = info.desc().append_child("channels")
        for k in range(msg.channels):
            ch = channels.append_child("channel")
            ch.append_child_value("label", f"film{k + 1}")
            ch.append_child_value("unit", "volts")
            ch.append_child_value("type", "PVDF")
        info.desc().append_child("acquisition").append_child_value("manufacturer", "tactiled")
        return self.lsl.StreamOutlet(info, chunk_size=0, max_buffered=60)

    def samples(self, msg: Samples) -> None:
        if self.raw is None:
            self.raw = self._raw_outlet(msg)
        v, valid, t = volts(msg)
        assert isinstance(v, np.ndarray) and isinstance(valid, np.ndarray)
        if not valid.any():
            return
        if t is None:
            self.raw.push_chunk(v[valid])
        else:
            assert isinstance(t, np.ndarray)
            self.raw.push_chunk(v[valid], timestamp=t[valid].tolist())
        self.pushed += int(valid.sum())

    def roughness(self, msg: Roughness) -> None:
        marker = json.dumps({k: getattr(msg, k) for k in MARKER_FIELDS})
        self.markers.push_sample([marker], msg.stop_mono or 0.0)

    def status(self, msg: Status) -> None:
        pass

    def close(self) -> None:
        self.raw = None
        self.markers = None
