"""The wire schema of tactiled, shared by the daemon and every client (docs/messages.md).

Each message is a two-part ZeroMQ message ``[topic, msgpack map]`` with topic
``roughness/<sensor>``, ``slide/<sensor>`` or ``status/<sensor>``. Every map carries ``v``
(schema version), ``seq`` (per topic and sensor, consecutive from 0), ``sensor`` and
``type``. Fields are only ever added (``v`` goes up when they are); readers ignore
fields they do not know. Times are on the sensor's sample clock (sample indices and
seconds since the sensor's index 0) unless named ``*_unix`` (host wall clock, s).
"""

from __future__ import annotations

import builtins
from dataclasses import dataclass, field, fields
from typing import Any, TypeVar

import msgpack

SCHEMA_VERSION = 2
ROUGHNESS, SLIDE, STATUS = "roughness", "slide", "status"
TOPICS = (ROUGHNESS, SLIDE, STATUS)

# abstain reasons of a roughness message whose label is None
REASON_WINDOW_TOO_SHORT = "window_too_short"
REASON_SAMPLES_LOST = "samples_lost"
REASON_SATURATED = "saturated"
REASON_LOW_CONFIDENCE = "low_confidence"
REASON_OVERWRITTEN = "overwritten"
REASON_NO_MODEL = "no_model"

# status states
STATE_CONNECTED, STATE_DISCONNECTED, STATE_IDLE, STATE_SLIDING = "connected", "disconnected", "idle", "sliding"


def topic(kind: str, sensor: str) -> str:
    """``kind/sensor``, e.g. ``roughness/fingertip0``."""
    return f"{kind}/{sensor}"


def encode(kind: str, sensor: str, body: dict[str, Any]) -> list[bytes]:
    """The two frames of a message; ``body`` must already carry v, seq, sensor and type."""
    return [topic(kind, sensor).encode(), msgpack.packb(body, use_bin_type=True)]


def decode(frames: list[bytes]) -> tuple[str, dict[str, Any]]:
    """(topic, map) of a two-part message; raises ValueError on anything else."""
    if len(frames) != 2:
        raise ValueError(f"expected 2 frames, got {len(frames)}")
    body = msgpack.unpackb(frames[1], raw=False, strict_map_key=False)
    if not isinstance(body, dict):
        raise ValueError("message body is not a map")
    return frames[0].decode("utf-8", "replace"), body


T = TypeVar("T", bound="Message")


@dataclass
class Message:
    """Fields common to every message."""

    v: int
    seq: int
    sensor: str
    type: str
    extra: dict[str, Any] = field(default_factory=dict, repr=False)
    missed: int = field(default=0, compare=False)  # set by the subscriber from seq, never on the wire

    @classmethod
    def from_map(cls: builtins.type[T], body: dict[str, Any]) -> T:
        """Build from a decoded map; unknown fields go to ``extra``, missing optional ones default."""
        names = {f.name for f in fields(cls)} - {"extra", "missed"}
        known = {k: v for k, v in body.items() if k in names}
        extra = {k: v for k, v in body.items() if k not in names}
        return cls(**known, extra=extra)


@dataclass
class Roughness(Message):
    """A label for a slide (None when abstaining, with ``reason``) and its provenance: one final per slide, provisional ones before it."""

    label: str | None = None
    reason: str | None = None
    confidence: float | None = None
    top: list[list[Any]] = field(default_factory=list)  # [[label, probability], ...] best first
    slide_id: int = 0
    start: int = 0  # sensor sample index of the slide's onset
    stop: int = 0  # sensor sample index one past the slide's end
    window: list[int] = field(default_factory=list)  # [start, stop) sensor sample indices analysed
    t_start: float = 0.0  # s on the sensor clock
    t_stop: float = 0.0
    latency_ms: float = 0.0  # from the slide's end being detected to publication
    model: str = ""  # model fingerprint
    quality: dict[str, Any] = field(default_factory=dict)
    time_unix: float = 0.0
    final: bool = True  # v2: False for a provisional label published while the slide goes on
    used_s: float = 0.0  # v2: seconds of the slide (from its start) the label is based on


@dataclass
class Slide(Message):
    """A slide started (``event`` = "start") or ended ("end")."""

    event: str = ""
    slide_id: int = 0
    start: int = 0
    stop: int | None = None
    t_start: float = 0.0
    t_stop: float | None = None
    time_unix: float = 0.0


@dataclass
class Status(Message):
    """At least once a second: state, counters, rate, model and uptime."""

    state: str = ""
    samples: int = 0
    samples_lost: int = 0
    crc_errors: int = 0
    bytes_discarded: int = 0
    bad_headers: int = 0
    reconnects: int = 0
    restarts: int = 0
    slides: int = 0
    labels: int = 0
    fs_nominal: float = 0.0
    fs_measured: float = 0.0
    model: str = ""
    uptime_s: float = 0.0
    index: int = 0  # newest sensor sample index
    level: list[float] = field(default_factory=list)  # RMS per film over the last status interval, V
    version: str = ""
    dropped_messages: int = 0
    channel_errors: int = 0
    time_unix: float = 0.0


MESSAGE_TYPES: dict[str, builtins.type[Message]] = {ROUGHNESS: Roughness, SLIDE: Slide, STATUS: Status}


def parse(topic_: str, body: dict[str, Any]) -> Message:
    """A typed message from (topic, map); unknown types give a plain :class:`Message`."""
    kind = topic_.split("/", 1)[0]
    cls = MESSAGE_TYPES.get(kind, Message)
    return cls.from_map(body)
