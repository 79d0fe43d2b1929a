"""Bridges from a daemon's ZeroMQ topics to other middleware (ROS 2, LSL).

A bridge is a :class:`Sink` fed by :func:`run_bridge`, which subscribes to a daemon (or to
``tactiled replay --publish``) and hands every samples, roughness and status message to it.
The sinks take the messages' own fields, host times included (docs/messages.md), so they
never rebuild a message body. Their heavy imports live in their own modules.
"""

from __future__ import annotations

import threading
from typing import Protocol

from tactiled_client import BlockingSubscriber, NoData, Roughness, Samples, Status


class Sink(Protocol):
    """Where a bridge sends the daemon's messages."""

    def samples(self, msg: Samples) -> None: ...

    def roughness(self, msg: Roughness) -> None: ...

    def status(self, msg: Status) -> None: ...

    def close(self) -> None: ...


def run_bridge(endpoint: str, sink: Sink, stop: threading.Event, sensor: str | None = None, poll_s: float = 0.2) -> int:
    """Forward messages from ``endpoint`` to ``sink`` until ``stop`` is set; returns how many were forwarded."""
    forwarded = 0
    with BlockingSubscriber(endpoint, topics=["samples", "roughness", "status"], sensor=sensor) as sub:
        try:
            while not stop.is_set():
                try:
                    msg = sub.receive(timeout=poll_s)
                except NoData:
                    continue
                if isinstance(msg, Samples):
                    sink.samples(msg)
                elif isinstance(msg, Roughness):
                    sink.roughness(msg)
                elif isinstance(msg, Status):
                    sink.status(msg)
                forwarded += 1
        finally:
            sink.close()
    return forwarded


def volts(msg: Samples) -> tuple[object, object, object]:
    """(volts (n, C) float32, valid (n,) bool, host monotonic time (n,) float64 or None) of a samples message."""
    import numpy as np

    v = (msg.counts().astype(np.float64) * msg.volts_per_count).astype(np.float32)
    t = None if msg.index_mono is None else msg.index_mono + np.arange(msg.n) / (msg.fs_clock or msg.fs)
    return v, msg.valid(), t
