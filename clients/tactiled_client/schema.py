"""The wire schema of tactiled, shared by the daemon, its tools and every client (docs/messages.md).

Each message is a two-part ZeroMQ message ``[topic, msgpack map]`` with topic
``roughness/<sensor>``, ``slide/<sensor>``, ``status/<sensor>`` or ``samples/<sensor>``.
Every map carries ``v`` (schema version), ``seq`` (per topic and sensor, consecutive from
0), ``sensor``, ``type`` and ``time_unix``. Fields are only ever added (``v`` goes up when
they are); readers ignore fields they do not know. Times are on the sensor's sample clock
(sample indices and seconds since the sensor's index 0) unless named ``*_mono`` (host
monotonic clock, s) or ``*_unix`` (host wall clock, s).

This module is both the reader's and the writer's side: the dataclasses are the messages,
and the builder functions (:func:`roughness`, :func:`slide_start`, :func:`slide_end`,
:func:`samples`) are the only place their bodies are made. The daemon, ``tactiled replay``
and the bridges all build through them.
"""

from __future__ import annotations

import builtins
import reprlib
import threading
import types
import typing
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, Protocol, TypeVar

from tactiled_client.errors import ClientError

SCHEMA_VERSION = 9  # 3: roughness messages carry novelty; reason unknown_surface. 4: shadow messages, status.shadow.
# 5: roughness.overloaded; status.overloaded, status.behind_s, status.input_shed_bytes (load shed when the daemon cannot keep up)
# 6: slide event "resumed": an end published after a short quiet (detector.end_hold_s) is withdrawn with its final label
# 7: status.discarded_at_start (stale bytes in the port when the daemon first opened it, dropped rather than counted as lost samples)
# 8: slide end reason "disconnected" (the serial port went away during the slide, which ends at the last sample read)
# 9: slide end reason "interrupted" (the board restarted, more samples were lost than the ring holds, or the daemon shed
#    load, during the slide)
ROUGHNESS, SLIDE, STATUS, SAMPLES, SHADOW = "roughness", "slide", "status", "samples", "shadow"
TOPICS = (ROUGHNESS, SLIDE, STATUS, SAMPLES, SHADOW)

# abstain reasons of a roughness message whose label is None
REASON_WINDOW_TOO_SHORT = "window_too_short"
REASON_SAMPLES_LOST = "samples_lost"
REASON_SATURATED = "saturated"
REASON_LOW_CONFIDENCE = "low_confidence"
REASON_OVERWRITTEN = "overwritten"
REASON_NO_MODEL = "no_model"
REASON_UNKNOWN_SURFACE = "unknown_surface"
REASONS = (REASON_WINDOW_TOO_SHORT, REASON_SAMPLES_LOST, REASON_SATURATED, REASON_LOW_CONFIDENCE, REASON_OVERWRITTEN, REASON_NO_MODEL,
           REASON_UNKNOWN_SURFACE)

# status states
STATE_CONNECTED, STATE_DISCONNECTED, STATE_IDLE, STATE_SLIDING, STATE_STOPPING = "connected", "disconnected", "idle", "sliding", "stopping"
STATES = (STATE_DISCONNECTED, STATE_CONNECTED, STATE_IDLE, STATE_SLIDING, STATE_STOPPING)

# slide events, and why a slide ended
SLIDE_START, SLIDE_END, SLIDE_CANCELLED, SLIDE_RESUMED = "start", "end", "cancelled", "resumed"
END_QUIET, END_MAX_DURATION, END_TOO_SHORT = "quiet", "max_duration", "too_short"
END_DISCONNECTED = "disconnected"  # the daemon's serial port went away during the slide (it ends at the last sample read)
END_INTERRUPTED = "interrupted"  # the board restarted, a gap longer than the ring came, or the daemon shed load, during the slide

HostTime = Callable[[int], tuple[float, float]]
"""Sensor sample index → (host monotonic time, host unix time) of that sample, s."""


def topic(kind: str, sensor: str) -> str:
    """``kind/sensor``, e.g. ``roughness/fingertip0``."""
    return f"{kind}/{sensor}"


_packers = threading.local()


def pack(body: dict[str, Any]) -> bytes:
    """``msgpack.packb(body, use_bin_type=True)`` through this thread's own reused packer.

    ``packb`` allocates and frees a 256 kB buffer per call; a reused packer allocates nothing per message and packs a status
    map in 0.57 us against 0.82 (measured on the project's machine). It resets its buffer after each message, and on error.
    """
    packer = getattr(_packers, "packer", None)
    if packer is None:
        import msgpack  # on first use: a replay that only builds messages (replay --json) never packs one (start-up)

        packer = _packers.packer = msgpack.Packer(use_bin_type=True)
    out: bytes = packer.pack(body)
    return out


def encode(kind: str, sensor: str, body: dict[str, Any]) -> list[bytes]:
    """The two frames of a message; ``body`` must already carry v, seq, sensor and type."""
    return [topic(kind, sensor).encode(), pack(body)]


def decode(frames: list[bytes]) -> tuple[str, dict[str, Any]]:
    """(topic, map) of a two-part message; raises ValueError on anything else."""
    if len(frames) != 2:
        raise ValueError(f"expected 2 frames, got {len(frames)}")
    import msgpack

    body = msgpack.unpackb(frames[1], raw=False, strict_map_key=False)
    if not isinstance(body, dict):
        raise ValueError("message body is not a map")
    return frames[0].decode("utf-8", "replace"), body


T = TypeVar("T", bound="Message")


class FieldTypeError(ClientError, ValueError):
    """A known field of a message map whose value is not of the field's declared type (one line: field, expected, what came)."""

    def __init__(self, name: str, expected: str, value: object) -> None:
        super().__init__(f"{name} is {builtins.type(value).__name__} {reprlib.repr(value)[:40]}, not {expected}")
        self.field = name
        self.expected = expected


@dataclass(frozen=True)
class _Check:
    """What a decoded value of one field may be: ``exact`` its types (the fast test), ``accepted`` the types it may be an
    instance of (subclasses: a numpy float64 is a float) and ``expected`` their name in an error (``float | None``)."""

    exact: frozenset[builtins.type]
    accepted: tuple[builtins.type, ...]
    expected: str

    def fits(self, value: object) -> bool:
        """Whether ``value`` is one of the accepted types; a bool is none of int and float unless bool itself is accepted."""
        return isinstance(value, self.accepted) and (not isinstance(value, bool) or bool in self.accepted)


def _field_check(hint: Any) -> _Check:
    """The check of a field annotated ``hint``: its class (``list[X]``, ``dict[K, V]``: the container alone, not its items);
    ``float`` also takes an int (JSON and other writers send 1 for 1.0); ``X | None`` takes None too; ``Any`` takes anything.
    A bool never passes for an int or a float (msgpack keeps them apart, so True where a count is declared is a fault)."""
    accepted: list[builtins.type] = []
    for arg in typing.get_args(hint) if typing.get_origin(hint) in (types.UnionType, typing.Union) else (hint,):
        if arg is Any:
            accepted.append(object)
        else:
            kind = typing.get_origin(arg) or arg
            accepted += [float, int] if kind is float else [kind]
    expected = hint.__name__ if isinstance(hint, builtins.type) and not typing.get_args(hint) else str(hint).replace("typing.", "")
    return _Check(frozenset(accepted) - {object}, tuple(accepted), expected)


def _field_checks(cls: builtins.type[Message]) -> dict[str, _Check]:
    """{wire field: its check} of ``cls``, built from its annotations on first use and kept in :data:`_FIELD_CHECKS`."""
    hints = typing.get_type_hints(cls)
    checks = {name: _field_check(hints[name]) for name in cls.wire_fields()}
    _FIELD_CHECKS[cls] = checks
    return checks


_FIELD_CHECKS: dict[builtins.type[Message], dict[str, _Check]] = {}


@dataclass
class Message:
    """Fields common to every message."""

    v: int
    seq: int
    sensor: str
    type: str
    time_unix: float = 0.0  # host wall clock when the message was sent, s
    extra: dict[str, Any] = field(default_factory=dict, repr=False)
    missed: int = field(default=0, compare=False)  # set by the subscriber from seq, never on the wire

    ABSENT_IF_NONE: ClassVar[frozenset[str]] = frozenset()  # fields left out of the map (not nil) when None

    @classmethod
    def from_map(cls: builtins.type[T], body: dict[str, Any]) -> T:
        """Build from a decoded map; unknown fields go to ``extra`` (whatever their type), missing optional ones default.

        :class:`FieldTypeError` if a known field's value is not of its declared type (see :func:`_field_check`)."""
        checks = _FIELD_CHECKS.get(cls) or _field_checks(cls)
        known: dict[str, Any] = {}
        extra: dict[str, Any] = {}
        for name, value in body.items():
            check = checks.get(name)
            if check is None:
                extra[name] = value
            elif type(value) in check.exact or check.fits(value):
                known[name] = value
            else:
                raise FieldTypeError(name, check.expected, value)
        return cls(**known, extra=extra)

    @classmethod
    def wire_fields(cls) -> set[str]:
        """The names of every field this message has on the wire."""
        return {f.name for f in fields(cls)} - {"extra", "missed"}

    def to_map(self) -> dict[str, Any]:
        """The msgpack map of this message (what the daemon sends): its known fields, then those of a newer daemon that this
        client does not know (``extra``), so that what passes a message on (the ROS 2 bridge's JSON) keeps them."""
        out = {}
        for f in fields(self):
            if f.name in ("extra", "missed"):
                continue
            value = getattr(self, f.name)
            if value is None and f.name in self.ABSENT_IF_NONE:
                continue
            out[f.name] = value
        out.update((k, v) for k, v in self.extra.items() if k not in out)
        return out


@dataclass
class LabelFields(Message):
    """The fields of a slide's label and its provenance (:class:`Roughness`, :class:`Shadow`)."""

    label: str | None = None
    reason: str | None = None
    confidence: float | None = None  # the probability that `label` (the top class) is right, calibrated in training
    top: list[list[Any]] = field(default_factory=list)  # [[label, probability], ...] best first: the classifier's softmax, uncalibrated
    slide_id: int = 0
    start: int = 0  # sensor sample index of the slide's onset
    stop: int = 0  # sensor sample index one past the slide's end (provisional: one past the samples used)
    window: list[int] = field(default_factory=list)  # [start, stop) sensor sample indices analysed
    t_start: float = 0.0  # s on the sensor clock
    t_stop: float = 0.0
    latency_ms: float = 0.0  # from the slide's end being detected to publication
    model: str = ""  # model fingerprint
    quality: dict[str, Any] = field(default_factory=dict)
    version: str = ""
    final: bool = True  # False: a provisional label published while the slide goes on
    used_s: float = 0.0  # seconds of the slide (from its onset) the label is based on
    start_mono: float | None = None  # host time of sample `start`, monotonic clock, s (nil if unknown)
    start_unix: float | None = None
    stop_mono: float | None = None  # host time of sample `stop`
    stop_unix: float | None = None
    novelty: float | None = None  # > 1: unlike every surface the model was trained on (label nil, reason unknown_surface); nil: not known
    overloaded: bool = False  # the daemon could not keep up and skipped analysing part of this slide (it ended where analysis stopped)


@dataclass
class Roughness(LabelFields):
    """One per slide (and, when the pipeline makes them, provisional ones while it goes on): the live label and its provenance."""


@dataclass
class Slide(Message):
    """A slide started (``event`` = "start"), ended ("end"), was too short to be one ("cancelled"), or went on after an
    end ("resumed": the end at ``stop`` and its final roughness label are withdrawn; a new end and label follow)."""

    ABSENT_IF_NONE: ClassVar[frozenset[str]] = frozenset({"stop", "t_stop", "reason", "stop_mono", "stop_unix"})

    event: str = ""
    slide_id: int = 0
    start: int = 0
    stop: int | None = None
    t_start: float = 0.0
    t_stop: float | None = None
    reason: str | None = None
    start_mono: float | None = None
    start_unix: float | None = None
    stop_mono: float | None = None
    stop_unix: float | None = None


@dataclass
class Status(Message):
    """At least once a second: state, counters, rate, model, uptime and the sample-clock mapping."""

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
    level: list[float] = field(default_factory=list)  # RMS per film about its mean over the last status interval, V
    version: str = ""
    dropped_messages: int = 0  # messages the PUB socket refused (0: a subscriber's own losses are its seq gaps)
    channel_errors: int = 0
    clock_index: int | None = None  # a sample index ...
    clock_mono: float | None = None  # ... its host monotonic time, s ...
    clock_unix: float | None = None  # ... and its host unix time, s (nil until samples arrive)
    fs_clock: float = 0.0  # sample indices per second of host monotonic time (the measured rate), Hz
    duplicate_frames: int = 0  # frames dropped as duplicates of ones already placed (an index that went back a little)
    unknown: int = 0  # final labels withheld as unknown_surface since start (most slides unknown: another unit, or untaught surfaces)
    shadow: dict[str, Any] | None = None  # a candidate model run in the shadow of the live one (run --shadow): model, slides,
    # agreement with the live labels, its mean confidence and unknown rate (nil without one)
    overloaded: int = 0  # samples decoded (recorded, published, counted) whose analysis was skipped because the daemon fell behind
    behind_s: float = 0.0  # how long the oldest input read but not yet processed has waited, s (0: keeping up)
    input_shed_bytes: int = 0  # bytes read but dropped before decoding because the backlog was full (their samples count as lost)
    discarded_at_start: int = 0  # bytes the port held when the daemon first opened it (sent before it started), read and dropped

    def host_mono(self, index: int) -> float | None:
        """Host monotonic time of sensor sample ``index`` by this status's clock mapping (None before samples)."""
        if self.clock_index is None or self.clock_mono is None or not self.fs_clock:
            return None
        return self.clock_mono + (index - self.clock_index) / self.fs_clock

    def host_unix(self, index: int) -> float | None:
        """Host unix time of sensor sample ``index`` (None before samples)."""
        if self.clock_index is None or self.clock_unix is None or not self.fs_clock:
            return None
        return self.clock_unix + (index - self.clock_index) / self.fs_clock


@dataclass
class Samples(Message):
    """One processing batch of raw samples (opt-in: ``publish.samples``), every index exactly once."""

    index: int = 0  # sensor index of the first row
    n: int = 0  # rows (samples per channel)
    channels: int = 0
    fs: float = 0.0  # nominal rate, Hz
    volts_per_count: float = 0.0
    data: bytes = b""  # n x channels int16 little-endian, interleaved by sample; lost samples are zero rows
    lost: list[list[int]] = field(default_factory=list)  # [[position, count], ...] rows lost, relative to index
    lost_before: int = 0  # samples lost just before index, not sent as rows (a gap longer than 1 s)
    index_mono: float | None = None  # host monotonic time of sample `index`, s
    index_unix: float | None = None  # host unix time of sample `index`, s
    fs_clock: float = 0.0  # rows per second of host time (add k / fs_clock for row k), Hz

    def counts(self) -> Any:
        """The rows as a numpy (n, channels) int16 array (needs numpy)."""
        import numpy as np

        return np.frombuffer(self.data, dtype="<i2").reshape(self.n, self.channels)

    def valid(self) -> Any:
        """(n,) numpy bool array, False on lost rows."""
        import numpy as np

        mask = np.ones(self.n, dtype=bool)
        for pos, count in self.lost:
            mask[pos:pos + count] = False
        return mask


@dataclass
class ProvisionalLabel:
    """A label given while the slide was still going on (in ``tactiled replay --json`` lines)."""

    label: str | None
    confidence: float | None
    used_s: float
    top: list[list[Any]]
    reason: str | None = None
    novelty: float | None = None
    stop: int | None = None  # one past the samples it used (as a live provisional label's stop); None in lines written before 2026-11-27
    quality: dict[str, Any] | None = None  # of the windows it used, as a live one's; None in older lines

    def to_map(self) -> dict[str, Any]:
        """The fields as a dict (the object in a ``tactiled replay --json`` line)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass
class Shadow(LabelFields):
    """A candidate model's result for a slide (``run --shadow``), on ``shadow/<sensor>``: the fields of :class:`Roughness`,
    never the live label (not a :class:`Roughness`, so a controller's ``isinstance`` check never takes it for one)."""


@dataclass
class ReplaySlide(Roughness):
    """One line of ``tactiled replay --json``: the final roughness message of a slide (positions in the file) and more."""

    file: str = ""
    slide: int = 0  # = slide_id
    truth: str | None = None  # the recording's ground-truth surface overlapping the slide
    duration_s: float = 0.0
    provisional: list[dict[str, Any]] = field(default_factory=list)  # ProvisionalLabel maps, in order


MESSAGE_TYPES: dict[str, builtins.type[Message]] = {ROUGHNESS: Roughness, SLIDE: Slide, STATUS: Status, SAMPLES: Samples, SHADOW: Shadow}


def parse(topic_: str, body: dict[str, Any]) -> Message:
    """A typed message from (topic, map); unknown types give a plain :class:`Message`."""
    kind = topic_.split("/", 1)[0]
    cls = MESSAGE_TYPES.get(kind, Message)
    return cls.from_map(body)


# ---- writer side -----------------------------------------------------------------------------

class SlideOutcome(Protocol):
    """What :func:`roughness` needs of a slide's result (``tactiled.core.pipeline.SlideResult`` is one)."""

    slide_id: int
    start: int
    stop: int
    window: tuple[int, int]
    label: str | None
    reason: str | None
    confidence: float | None
    top: list[tuple[str, float]]
    quality: dict[str, Any]
    compute_ms: float
    final: bool
    used_s: float
    novelty: float | None


def _head(kind: str, sensor: str) -> dict[str, Any]:
    return {"v": SCHEMA_VERSION, "seq": 0, "sensor": sensor, "type": kind}


def _host(to_host: HostTime | None, index: int | None) -> tuple[float | None, float | None]:
    if to_host is None or index is None:
        return None, None
    mono, unix = to_host(index)
    return round(mono, 6), round(unix, 6)


def roughness(sensor: str, r: SlideOutcome, *, fs: float, model: str, version: str, latency_ms: float = 0.0,
              to_host: HostTime | None = None, overloaded: bool = False) -> Roughness:
    """The roughness message of slide result ``r`` (sensor indices; ``seq`` and ``time_unix`` are set when sent); ``overloaded``:
    the daemon skipped analysing part of the slide."""
    start_mono, start_unix = _host(to_host, r.start)
    stop_mono, stop_unix = _host(to_host, r.stop)
    return Roughness(**_head(ROUGHNESS, sensor), label=r.label, reason=r.reason, confidence=r.confidence,
                     top=[[c, p] for c, p in r.top], slide_id=r.slide_id, start=r.start, stop=r.stop, window=[r.window[0], r.window[1]],
                     t_start=r.start / fs, t_stop=r.stop / fs, latency_ms=round(latency_ms, 3), model=model,
                     quality={**r.quality, "compute_ms": round(r.compute_ms, 3)}, version=version, final=r.final,
                     used_s=round(r.used_s, 6), start_mono=start_mono, start_unix=start_unix, stop_mono=stop_mono, stop_unix=stop_unix,
                     novelty=r.novelty, overloaded=overloaded)


def shadow(sensor: str, r: SlideOutcome, *, fs: float, model: str, version: str, latency_ms: float = 0.0,
           to_host: HostTime | None = None, overloaded: bool = False) -> Shadow:
    """A candidate model's result for slide ``r``: the fields of :func:`roughness`, on the shadow topic."""
    return Shadow(**{**roughness(sensor, r, fs=fs, model=model, version=version, latency_ms=latency_ms, to_host=to_host,
                                 overloaded=overloaded).to_map(),
                     "type": SHADOW})  # not from_map: the writer's values are not checked (a reader checks what it takes)


def provisional_label(r: SlideOutcome) -> ProvisionalLabel:
    """The short form of a provisional result kept inside a replay line."""
    return ProvisionalLabel(r.label, r.confidence, round(r.used_s, 6), [[c, p] for c, p in r.top], r.reason, r.novelty, r.stop,
                            {**r.quality, "compute_ms": round(r.compute_ms, 3)})


def slide_start(sensor: str, slide_id: int, start: int, fs: float, to_host: HostTime | None = None) -> Slide:
    """A slide began at sample ``start``."""
    start_mono, start_unix = _host(to_host, start)
    return Slide(**_head(SLIDE, sensor), event=SLIDE_START, slide_id=slide_id, start=start, t_start=start / fs,
                 start_mono=start_mono, start_unix=start_unix)


def slide_end(sensor: str, slide_id: int, start: int, stop: int, reason: str, fs: float, to_host: HostTime | None = None) -> Slide:
    """A slide ended at ``stop`` (``reason`` too_short: cancelled, it was no slide)."""
    start_mono, start_unix = _host(to_host, start)
    stop_mono, stop_unix = _host(to_host, stop)
    return Slide(**_head(SLIDE, sensor), event=SLIDE_CANCELLED if reason == END_TOO_SHORT else SLIDE_END, slide_id=slide_id,
                 start=start, stop=stop, t_start=start / fs, t_stop=stop / fs, reason=reason,
                 start_mono=start_mono, start_unix=start_unix, stop_mono=stop_mono, stop_unix=stop_unix)


def slide_resumed(sensor: str, slide_id: int, start: int, stop: int, fs: float, to_host: HostTime | None = None) -> Slide:
    """Slide ``slide_id``, said to have ended at ``stop``, goes on: that end and its final label are withdrawn."""
    start_mono, start_unix = _host(to_host, start)
    stop_mono, stop_unix = _host(to_host, stop)
    return Slide(**_head(SLIDE, sensor), event=SLIDE_RESUMED, slide_id=slide_id, start=start, stop=stop, t_start=start / fs, t_stop=stop / fs,
                 start_mono=start_mono, start_unix=start_unix, stop_mono=stop_mono, stop_unix=stop_unix)


def status(sensor: str, **values: Any) -> Status:
    """A status message with ``values`` (field names of :class:`Status`)."""
    return Status(**_head(STATUS, sensor), **values)


def samples(sensor: str, index: int, data: bytes, n: int, channels: int, *, fs: float, volts_per_count: float,
            lost: Sequence[Sequence[int]] = (), lost_before: int = 0, to_host: HostTime | None = None, fs_clock: float = 0.0) -> Samples:
    """A raw batch: ``data`` = n x channels int16 LE interleaved rows whose first has sensor index ``index``."""
    if len(data) != 2 * n * channels:
        raise ValueError(f"samples: {len(data)} bytes for {n} rows x {channels} channels")
    index_mono, index_unix = _host(to_host, index)
    return Samples(**_head(SAMPLES, sensor), index=index, n=n, channels=channels, fs=fs, volts_per_count=volts_per_count, data=data,
                   lost=[[int(p), int(c)] for p, c in lost], lost_before=lost_before, index_mono=index_mono, index_unix=index_unix,
                   fs_clock=fs_clock or fs)
