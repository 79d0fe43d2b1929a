"""Subscribe to one or more tactiled daemons.

Async (``from tactiled_client import Subscriber, local_endpoint``)::

    async with Subscriber(local_endpoint("fingertip0"), topics=["roughness"]) as sub:   # or "tcp://host:port"
        async for msg in sub:
            print(msg.label, msg.confidence)

Blocking (scripts)::

    with BlockingSubscriber(local_endpoint("fingertip0")) as sub:
        for msg in sub:
            ...

``curve=(daemon_public_cert, my_secret_cert)`` connects to a daemon that requires ZeroMQ
CURVE. Every message is typed (:mod:`tactiled_client.schema`); ``msg.missed`` is how many
messages of that topic were lost just before it (from ``seq``); ``timeout`` (s) raises
:class:`NoData` when nothing arrives for that long; :meth:`latest` returns the newest
roughness label if it was sent at most a given time ago (a label that waited in the queue counts its wait). A message that is not a tactiled message
(something else publishing there), or one with a known field of the wrong type (a ``confidence`` that
is a string), is skipped and counted in ``malformed`` (``last_malformed`` says why), never raised.
"""

from __future__ import annotations

import math
import os
import time
from collections import deque
from collections.abc import AsyncIterator, Iterator, Sequence
from types import TracebackType
from typing import Any

import zmq
import zmq.asyncio

from tactiled_client import schema
from tactiled_client.endpoints import connect
from tactiled_client.errors import NoData, UsageError

__all__ = ["BlockingSubscriber", "NoData", "Subscriber"]

# s of arrivals over which the quickest message's lag (arrival less send time, on two hosts' wall clocks) stands for that
# of a message that did not wait in a queue: long enough to span a controller's busy spell; a daemon's wall clock stepped
# back (or the controller's forward) makes its labels look that much older (no label rather than a stale one) for at most
# this long
LAG_WINDOW_S = 300.0


class _Lags:
    """One daemon's message lags (arrival less send time ``time_unix``, on the two hosts' wall clocks, s): their least over
    the last :data:`LAG_WINDOW_S` of arrivals is the lag of a message that did not wait. Each lag is taken with the one before
    it (the larger of two in a row), so one message stamped wrongly, by a clock wrong for a moment, cannot make the later
    ones look late."""

    def __init__(self) -> None:
        self._window: deque[tuple[float, float]] = deque()  # (arrived, lag): increasing lags, the first the least
        self._last: float | None = None

    def add(self, arrived: float, lag: float) -> None:
        """The lag of a message that arrived at ``arrived`` (on :meth:`_Tracker.now`'s clock)."""
        last, self._last = self._last, lag
        if last is None:
            return
        pair, window = max(lag, last), self._window
        while window and window[-1][1] >= pair:
            window.pop()
        window.append((arrived, pair))
        while window[0][0] < arrived - LAG_WINDOW_S:
            window.popleft()

    def least(self) -> float | None:
        """The lag of a message that did not wait (None: not yet two messages)."""
        return self._window[0][1] if self._window else None


class _Tracker:
    """seq bookkeeping and the freshest roughness message, shared by the subscribers and the replays.

    Ages are measured on :meth:`now` (the host's monotonic clock; a replay's own clock in recorded time).
    """

    def __init__(self) -> None:
        self.last_seq: dict[str, int] = {}
        self.missed: dict[str, int] = {}
        self.malformed = 0  # messages skipped because they are not tactiled messages (docs/messages.md)
        self.last_malformed: str | None = None  # why the last of them was skipped (topic and fault, one line)
        self._latest: tuple[float, float | None, schema.Roughness] | None = None  # (arrived, its lag, the message)
        self._lags: dict[str, _Lags] = {}  # per sensor: each daemon's clock is its own

    def accept(self, frames: list[bytes], arrived_unix: float | None = None, arrived: float | None = None) -> schema.Message | None:
        """The typed message of ``frames`` with its ``missed`` set (``arrived_unix``: when it arrived on the wall clock, s;
        ``arrived``: on :meth:`now`'s clock; None: now); None, counted in :attr:`malformed`, if it is not a
        tactiled message (not two frames, a body that is not a msgpack map, ``v``, ``seq``, ``sensor`` or ``type`` missing
        or of the wrong type, any other field the schema knows of a type it does not declare): something else publishing
        on the endpoint, or a faulty publisher, must neither end a controller's loop nor hand it garbage."""
        checked = _checked(frames)
        fault = checked if isinstance(checked, str) else None
        if not isinstance(checked, str):
            topic, body = checked
            try:
                msg = schema.parse(topic, body)
            except schema.FieldTypeError as exc:
                fault = f"{topic[:80]}: {exc}"
        if fault is not None:
            self.malformed += 1
            self.last_malformed = fault
            return None
        last = self.last_seq.get(topic)
        gap = 0 if last is None or msg.seq <= last else msg.seq - last - 1
        if last is not None and msg.seq <= last:
            gap = 0  # the daemon restarted: seq starts again
        self.last_seq[topic] = msg.seq
        self.missed[topic] = self.missed.get(topic, 0) + gap
        msg.missed = gap
        arrived = self.now() if arrived is None else arrived
        lag: float | None = (time.time() if arrived_unix is None else arrived_unix) - msg.time_unix
        if msg.time_unix > 0 and lag is not None and math.isfinite(lag):
            self._lags.setdefault(msg.sensor, _Lags()).add(arrived, lag)
        else:
            lag = None
        if isinstance(msg, schema.Roughness):
            self._latest = (arrived, lag, msg)
        elif (isinstance(msg, schema.Slide) and msg.event == schema.SLIDE_RESUMED and self._latest is not None
              and self._latest[2].slide_id == msg.slide_id and self._latest[2].sensor == msg.sensor):
            self._latest = None  # its final label is withdrawn: the slide went on
        return msg

    def now(self) -> float:
        """The clock ages are measured on, s."""
        return time.monotonic()

    def latest(self, max_age_s: float) -> schema.Roughness | None:
        """The newest roughness message if it was sent at most ``max_age_s`` ago, else None (also when a ``resumed`` slide
        message withdrew it; subscribe to ``slide`` to see those).

        Its age is the time since it arrived plus how long it had waited to be received: how much later it arrived than
        the quickest of its daemon's messages of the last :data:`LAG_WINDOW_S` did, by the daemon's send time
        (``time_unix``) on each host's wall clock. So a label that waited in the queue while the controller was busy is as
        old as it is, and the hosts' clocks need not agree, only not step. The quickest lag is known as well as the
        freshest message of the window shows it: subscribe to ``status`` too (one every 0.5 s), as ``example_controller.py``
        does. A replay ages a label from when it was due on the replay's clock.
        """
        if self._latest is None:
            return None
        arrived, lag, msg = self._latest
        least = self._lags[msg.sensor].least() if msg.sensor in self._lags else None
        waited = lag - least if lag is not None and least is not None else 0.0
        return None if self.now() - arrived + max(waited, 0.0) > max_age_s else msg


MAX_SEQ = 2**63 - 1  # a daemon's seq counts messages from 0: a value outside 0..MAX_SEQ is no tactiled message

_HEAD_TYPES: tuple[tuple[str, type], ...] = (("v", int), ("seq", int), ("sensor", str), ("type", str))


def _checked(frames: list[bytes]) -> str | tuple[str, dict[str, Any]]:
    """(topic, map) of ``frames`` if its head is a tactiled message's, else why it is not (one line, naming its topic):
    the body is unpacked once, here."""
    import msgpack

    where = frames[0][:80].decode("utf-8", "replace") if frames else "(no frames)"
    if len(frames) != 2:
        return f"{where}: {len(frames)} frames, not 2"
    try:
        body = msgpack.unpackb(frames[1], raw=False, strict_map_key=False)
    except (ValueError, TypeError, RecursionError, msgpack.UnpackException) as exc:
        return f"{where}: body is not msgpack: {str(exc)[:80]}"
    if not isinstance(body, dict):
        return f"{where}: body is not a map"
    for name, kind in _HEAD_TYPES:
        value = body.get(name)
        if not isinstance(value, kind) or isinstance(value, bool):
            return f"{where}: {name} is {type(value).__name__ if name in body else 'missing'}, not {kind.__name__}"
    if not 0 <= body["seq"] <= MAX_SEQ:
        return f"{where}: seq {body['seq']} is outside 0..{MAX_SEQ}"
    return frames[0].decode("utf-8", "replace"), body


class _Filter:
    """Which messages a subscriber takes: ``prefixes`` for its SUB socket, and :meth:`wants`, the exact test a prefix cannot
    make (``roughness/finger1`` is also a prefix of ``roughness/finger10``).

    ``topics``: the kinds (None: every one); ``sensor``: that sensor's messages only, of the kinds given or of every kind
    in :data:`schema.TOPICS`.
    """

    def __init__(self, topics: Sequence[str] | None, sensor: str | None) -> None:
        kinds = list(topics) if topics else []
        for kind in kinds:
            if kind not in schema.TOPICS:
                raise UsageError(f"unknown topic {kind!r}; choose from {', '.join(schema.TOPICS)}")
        if sensor:
            self._exact: frozenset[str] | None = frozenset(schema.topic(kind, sensor) for kind in kinds or schema.TOPICS)
            self.prefixes = sorted(t.encode() for t in self._exact)
        else:
            self._exact = None
            self.prefixes = [kind.encode() for kind in kinds] or [b""]
        self._starts = tuple(self.prefixes)

    def wants(self, topic: bytes) -> bool:
        """Whether a message of ``topic`` (its first frame) is one of those asked for."""
        return topic.startswith(self._starts) if self._exact is None else topic.decode("utf-8", "replace") in self._exact


def _left_ms(deadline: float) -> int:
    """Milliseconds to ``deadline`` (host monotonic clock), 0 once it has passed: what is already queued is still taken."""
    return max(0, int((deadline - time.monotonic()) * 1000))


def _endpoints(endpoints: str | Sequence[str]) -> list[str]:
    return [endpoints] if isinstance(endpoints, str) else list(endpoints)


def _secure(sock: Any, curve: tuple[str, str] | None) -> None:
    """CURVE: ``curve`` = (daemon's public certificate file, this client's secret certificate file); :class:`UsageError`
    naming the file if one cannot be read or is not a ZeroMQ certificate (``tactiled curve-keys`` makes them)."""
    if curve is None:
        return
    server_public, _ = _certificate(curve[0])
    public, secret = _certificate(curve[1])
    if not secret:
        raise UsageError(f"{curve[1]}: holds no secret key")
    for name, key, file in (("curve_serverkey", server_public, curve[0]), ("curve_publickey", public, curve[1]),
                            ("curve_secretkey", secret, curve[1])):
        try:
            setattr(sock, name, key)
        except zmq.ZMQError:
            raise UsageError(f"{file}: not a valid CURVE key (make certificates with tactiled curve-keys)") from None


def _certificate(path: str) -> tuple[bytes, bytes | None]:
    """(public key, secret key or None) of the ZeroMQ certificate file ``path``, or :class:`UsageError` naming it."""
    import zmq.auth

    if not os.path.isfile(path):
        raise UsageError(f"{path}: no such certificate file" if not os.path.exists(path) else f"{path}: not a certificate file")
    try:
        return zmq.auth.load_certificate(path)
    except OSError as exc:
        raise UsageError(f"{path}: cannot read the certificate: {exc.strerror or exc}") from None
    except ValueError:
        raise UsageError(f"{path}: not a ZeroMQ certificate (no public-key; make them with tactiled curve-keys)") from None


class Subscriber(_Tracker):
    """Async subscriber: ``async with Subscriber(endpoint) as sub: async for msg in sub``."""

    def __init__(self, endpoints: str | Sequence[str], topics: Sequence[str] | None = None, sensor: str | None = None,
                 timeout: float | None = None, context: zmq.asyncio.Context | None = None, curve: tuple[str, str] | None = None) -> None:
        super().__init__()
        self.curve = curve
        self.endpoints = _endpoints(endpoints)
        self._filter = _Filter(topics, sensor)
        self.prefixes = self._filter.prefixes
        self.timeout = timeout
        self._context = context or zmq.asyncio.Context.instance()
        self._socket: zmq.asyncio.Socket | None = None

    async def __aenter__(self) -> Subscriber:
        sock = self._context.socket(zmq.SUB)
        sock.setsockopt(zmq.LINGER, 0)
        _secure(sock, self.curve)
        for p in self.prefixes:
            sock.setsockopt(zmq.SUBSCRIBE, p)
        for e in self.endpoints:
            connect(sock, e)
        self._socket = sock
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._socket is not None:
            self._socket.close(linger=0)
            self._socket = None

    async def receive(self, timeout: float | None = None) -> schema.Message:
        """The next message; :class:`NoData` after ``timeout`` (default: the subscriber's) seconds of silence."""
        if self._socket is None:
            raise UsageError("receive() before 'async with Subscriber(...)' (or after it ended)")
        t = self.timeout if timeout is None else timeout
        deadline = None if t is None else time.monotonic() + t
        while True:
            if deadline is not None and not await self._socket.poll(_left_ms(deadline)):
                raise NoData(f"no message from {', '.join(self.endpoints)} for {t} s")
            frames = await self._socket.recv_multipart()
            if self._filter.wants(frames[0]) and (msg := self.accept(frames)) is not None:
                return msg

    def __aiter__(self) -> AsyncIterator[schema.Message]:
        return self

    async def __anext__(self) -> schema.Message:
        return await self.receive()


class BlockingSubscriber(_Tracker):
    """Blocking subscriber for scripts: ``with BlockingSubscriber(endpoint) as sub: for msg in sub``."""

    def __init__(self, endpoints: str | Sequence[str], topics: Sequence[str] | None = None, sensor: str | None = None,
                 timeout: float | None = None, context: zmq.Context[Any] | None = None, curve: tuple[str, str] | None = None) -> None:
        super().__init__()
        self.endpoints = _endpoints(endpoints)
        self.timeout = timeout
        self._socket = (context or zmq.Context.instance()).socket(zmq.SUB)
        self._socket.setsockopt(zmq.LINGER, 0)
        self._filter = _Filter(topics, sensor)
        _secure(self._socket, curve)
        for p in self._filter.prefixes:
            self._socket.setsockopt(zmq.SUBSCRIBE, p)
        for e in self.endpoints:
            connect(self._socket, e)

    def receive(self, timeout: float | None = None) -> schema.Message:
        """The next message; :class:`NoData` after ``timeout`` (default: the subscriber's) seconds of silence."""
        t = self.timeout if timeout is None else timeout
        deadline = None if t is None else time.monotonic() + t
        while True:
            if deadline is not None and not self._socket.poll(_left_ms(deadline)):
                raise NoData(f"no message from {', '.join(self.endpoints)} for {t} s")
            frames = self._socket.recv_multipart()
            if self._filter.wants(frames[0]) and (msg := self.accept(frames)) is not None:
                return msg

    def __iter__(self) -> Iterator[schema.Message]:
        while True:
            yield self.receive()

    def close(self) -> None:
        """Close the socket at once (messages not yet received are dropped)."""
        self._socket.close(linger=0)

    def __enter__(self) -> BlockingSubscriber:
        return self

    def __exit__(self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None) -> None:
        self.close()
