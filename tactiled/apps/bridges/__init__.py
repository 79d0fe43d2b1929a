"""Bridges from a daemon's ZeroMQ topics to other middleware (ROS 2, LSL).

A bridge is a :class:`Sink` fed by :func:`run_bridge`, which subscribes to a daemon (or to
``tactiled replay --publish``) and hands every samples, roughness and status message of one
sensor to it, and every withdrawal of a final label (a slide message ``resumed``). The sinks take
the messages' own fields, host times included (docs/messages.md), so they never rebuild a message body. Their heavy imports live in their own modules.

:func:`run_bridge` also says, in one line each, what a user would otherwise wait for in silence:
a sensor id the daemon does not publish (an error: exit 2), nothing at all from the endpoint,
and status without samples (the daemon runs without ``--samples``).
"""

from __future__ import annotations

import json
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from tactiled_client import BlockingSubscriber, NoData, Roughness, Samples, Slide, Status, schema

from tactiled.errors import TactiledError

PATIENCE_S = 3.0  # six status intervals of the daemon: long enough to know what it publishes


class Sink(Protocol):
    """Where a bridge sends the daemon's messages."""

    def samples(self, msg: Samples) -> None:
        """Take one samples message: n rows of C channels, int16 counts with their lost rows listed (docs/messages.md)."""

    def roughness(self, msg: Roughness) -> None:
        """Take one roughness message: a slide's provisional or final label."""

    def status(self, msg: Status) -> None:
        """Take one status message of the daemon."""

    def withdrawn(self, msg: Slide) -> None:
        """Take one slide message of event ``resumed``: the final label of slide ``msg.slide_id`` is withdrawn (it went on)."""

    def close(self) -> None:
        """Release the outlets, node or connections; no message follows."""


@dataclass
class StreamMeta:
    """What a bridge announces before any samples arrive: from the config, then from the daemon's first status."""

    sensor: str
    channels: int
    fs: float  # the board's (firmware) nominal rate, Hz
    volts_per_count: float  # ADC scale, V per count
    model: str = ""  # fingerprint of the daemon's model ("" unknown: no status yet)
    version: str = ""  # the daemon's tactiled version


def _say(line: str) -> None:
    print(f"tactiled: {line}", file=sys.stderr, flush=True)


SERVICE_RUNTIME = Path("/run/tactiled")  # where the systemd unit's daemons bind their sockets (its RuntimeDirectory)


def sockets_beside(endpoint: str, service: Path = SERVICE_RUNTIME) -> str:
    """Where ``endpoint`` is an ``ipc://`` socket that does not exist: the sockets its folder and the service's folder
    ``service`` hold instead (the daemons running there: a wrong ``--sensor-id`` picks a socket nobody binds), as a
    clause for a waiting line; else ""."""
    if not endpoint.startswith("ipc://") or Path(endpoint[6:]).exists():
        return ""
    folders = dict.fromkeys([Path(endpoint[6:]).parent, service])
    others = [str(p) for folder in folders if folder.is_dir() for p in sorted(folder.glob("*.sock")) if p.is_socket()]
    return f"; no socket there yet, and {', '.join(others)} are: another --sensor-id or --connect?" if others else "; no socket there yet"


def first_status(endpoint: str, sensor: str, timeout: float, curve: tuple[str, str] | None = None) -> Status | None:
    """The first status message of ``sensor`` within ``timeout`` s, or None (no daemon, or not that sensor); ``curve``: the
    daemon's CURVE certificates, as a subscriber takes them."""
    deadline = time.monotonic() + timeout
    with BlockingSubscriber(endpoint, topics=["status"], curve=curve) as sub:
        while (left := deadline - time.monotonic()) > 0:
            try:
                msg = sub.receive(timeout=left)
            except NoData:
                return None
            if isinstance(msg, Status) and msg.sensor == sensor:
                return msg
    return None


def run_bridge(endpoint: str, sink: Sink, stop: threading.Event, sensor: str | None = None, poll_s: float = 0.2,
               patience_s: float = PATIENCE_S, say: Callable[[str], None] = _say, raw_name: str = "raw samples",
               curve: tuple[str, str] | None = None) -> int:
    """Forward ``sensor``'s messages (every sensor's when None) from ``endpoint`` (``curve``: its CURVE certificates) to
    ``sink`` until ``stop`` is set.

    Returns how many were forwarded. After ``patience_s`` s: raises :class:`TactiledError` if only
    other sensors were heard (a wrong ``--sensor-id``), says once if nothing was heard, and says
    once if status came but no samples (``raw_name`` stays empty).
    """
    forwarded = 0
    started = time.monotonic()
    others: set[str] = set()
    ours_at: float | None = None  # when the first message of the sensor came
    samples_seen = heard_any = said_silent = said_no_samples = False
    with BlockingSubscriber(endpoint, topics=["samples", "roughness", "status", "slide"], curve=curve) as sub:
        try:
            while not stop.is_set():
                try:
                    msg = sub.receive(timeout=poll_s)
                except NoData:
                    msg = None
                if msg is not None:
                    heard_any = True
                    if sensor is not None and msg.sensor != sensor:
                        others.add(msg.sensor)
                        msg = None
                if msg is not None:
                    ours_at = ours_at or time.monotonic()
                    if isinstance(msg, Samples):
                        samples_seen = True
                        sink.samples(msg)
                    elif isinstance(msg, Roughness):
                        sink.roughness(msg)
                    elif isinstance(msg, Status):
                        sink.status(msg)
                    elif isinstance(msg, Slide) and msg.event == schema.SLIDE_RESUMED:
                        sink.withdrawn(msg)
                    else:
                        continue  # other slide events: not bridged
                    forwarded += 1
                now = time.monotonic()
                if now - started < patience_s:
                    continue
                if ours_at is None and others:
                    raise TactiledError(f"{endpoint} publishes sensor {', '.join(sorted(others))}, not {sensor!r}: nothing to bridge "
                                        "(--sensor-id, or sensor.id of --config)")
                if not heard_any and not said_silent:
                    say(f"nothing from {endpoint} in {patience_s:g} s; waiting (is a daemon or tactiled replay --publish there?"
                        f"{sockets_beside(endpoint)})")
                    said_silent = True
                if ours_at is not None and now - ours_at >= patience_s and not samples_seen and not said_no_samples:
                    say(f"sensor {sensor or '(any)'}: status and labels but no samples in {patience_s:g} s: the {raw_name} stays empty "
                        "until the daemon publishes them (tactiled run --samples, or publish.samples = true)")
                    said_no_samples = True
        finally:
            sink.close()
    return forwarded


def volts(msg: Samples) -> tuple[object, object, object]:
    """(volts (n, C) float32, valid (n,) bool, host monotonic time (n,) float64 or None) of a samples message."""
    import numpy as np

    v = (msg.counts().astype(np.float64) * msg.volts_per_count).astype(np.float32)
    t = None if msg.index_mono is None else msg.index_mono + np.arange(msg.n) / (msg.fs_clock or msg.fs)
    return v, msg.valid(), t


def lost_ranges(msg: Samples) -> list[tuple[int, int]]:
    """(first sensor index, count) of every sample lost in or just before ``msg``, in index order."""
    out = [(msg.index - msg.lost_before, msg.lost_before)] if msg.lost_before else []
    return out + [(msg.index + p, c) for p, c in msg.lost]


def json_value(value: Any) -> str:
    """A field as text for a key/value list: strings as they are, everything else as JSON (null, true, lists)."""
    return value if isinstance(value, str) else json.dumps(value)

