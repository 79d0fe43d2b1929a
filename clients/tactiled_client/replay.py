"""Replay a recorded session through the subscriber's interface, or onto a socket as the daemon would.

A controller switches from live to file by changing one constructor::

    async with Subscriber("tcp://127.0.0.1:7350", topics=["roughness"]) as sub:    # live
    async with Replay("session.tlog", topics=["roughness"]) as sub:                # recorded
        async for msg in sub:
            ...

``speed``: 1.0 replays at the recorded pace, 2.0 twice as fast, None as fast as possible. ``receive(timeout=)``
raises :class:`NoData` when the next message is further away than the timeout in recorded time (whatever the speed:
a 4 s silence in the session is one NoData of a 3 s timeout, after 1.5 s of wall time at speed 2), and
:class:`EndOfLog` (a :class:`NoData`) at the end of the file, where ``async for`` and ``for`` simply stop.
``latest(max_age_s)`` measures ages on the recorded clock. Files: :mod:`tactiled_client.log`.

Receive times that are no clock readings (not finite, beyond ``log.MAX_TIME_S``; in a session log going back more than
``log.BACK_S`` or jumping more than ``log.MAX_GAP_S``) are not clamped: the replay stops there with one :class:`LogError`
naming the byte (or line), as for any other fault in the file, after every message before it. No single wait is
longer than :data:`MAX_WAIT_S` (a tiny ``speed`` would otherwise overflow ``time.sleep``).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable, Iterator, Sequence
from pathlib import Path
from types import TracebackType

from tactiled_client import schema
from tactiled_client.endpoints import allow_ipv6, remove_socket_file
from tactiled_client.errors import EndOfLog, NoData, UsageError
from tactiled_client.log import Entry, LogReader
from tactiled_client.subscriber import _Filter, _Tracker

__all__ = ["BlockingReplay", "Replay", "publish"]

MAX_WAIT_S = 1e9  # s: the longest one wait of a replay (time.sleep overflows past ~9.2e9 s; this is already for ever)


class _Player(_Tracker):
    """What both replays share: the file's entries filtered as a SUB socket would, and the recorded clock."""

    def __init__(self, path: str | Path, topics: Sequence[str] | None, sensor: str | None, timeout: float | None, speed: float | None) -> None:
        super().__init__()
        if speed is not None and not speed > 0:
            raise UsageError(f"speed must be > 0 or None (as fast as possible), got {speed}")
        self.path = Path(path)
        self.timeout = timeout
        self.speed = speed
        self.reader = LogReader(self.path)
        self._filter = _Filter(topics, sensor)
        self._entries: Iterator[Entry] | None = None
        self._pending: Entry | None = None
        self._origin: tuple[float, float] | None = None  # (recorded time, wall time) of the first message
        self._recorded_now = 0.0

    def _open(self) -> None:
        self._entries = iter(self.reader)

    def _next(self) -> Entry | None:
        if self._entries is None:
            raise UsageError(f"receive() before entering the replay of {self.path} ('async with' / 'with')")
        if self._pending is None:
            self._pending = next((e for e in self._entries if self._filter.wants(e.topic.encode())), None)
        return self._pending

    def _start(self, entry: Entry) -> None:
        """The replay's clock starts at its first message (recorded time ``entry.time_mono``, wall time now)."""
        if self._origin is None:
            self._origin = (entry.time_mono, time.monotonic())
            self._recorded_now = entry.time_mono

    def _wait(self, entry: Entry) -> float:
        """Seconds of wall time until ``entry`` is due (0 when replaying as fast as possible)."""
        self._start(entry)
        if self.speed is None:
            return 0.0
        return _bounded((entry.time_mono - self.now()) / self.speed)

    def _plan(self, timeout: float | None) -> tuple[float, float | None]:
        """(seconds of wall time to wait, the recorded seconds of silence if the wait ends in silence, else None) before the
        next message; :class:`EndOfLog` if none is left.

        The timeout is in recorded time, as a live subscriber's is in the daemon's: a silence longer than it is a
        :class:`NoData` at every speed (waiting ``timeout / speed`` of wall time, none when as fast as possible), and the
        replay's clock moves on by the timeout.
        """
        t = self.timeout if timeout is None else timeout
        entry = self._next()
        if entry is None:
            raise self._end()
        self._start(entry)
        ahead = entry.time_mono - self.now()  # recorded seconds until it is due
        if t is not None and ahead > t:
            if self.speed is None:
                self._recorded_now += t
                return 0.0, t
            return _bounded(t / self.speed), t
        return (0.0 if self.speed is None else _bounded(ahead / self.speed)), None

    def _deliver(self) -> schema.Message | None:
        """The pending entry's message (None: skipped as malformed, see :meth:`_Tracker.accept`)."""
        entry = self._pending
        if entry is None:
            raise UsageError("nothing to deliver")  # only reached after _next gave an entry
        self._pending = None
        self._recorded_now = entry.time_mono
        return self.accept(entry.frames(), entry.time_unix, entry.time_mono)  # arrived when it was due: a late delivery ages it

    def _silence(self, t: float) -> NoData:
        return NoData(f"{self.path}: no message for {t:g} s of recorded time")

    @property
    def truncated(self) -> str | None:
        """Once the replay has ended: a one-line note if the file ended inside a message (a recording cut short, by a
        crash or a copy), else None."""
        return self.reader.truncated

    def _end(self) -> EndOfLog:
        return EndOfLog(f"{self.path}: end of file after {self.reader.count} messages")

    def now(self) -> float:
        """The recorded clock: the recorded time of the replay's position, s."""
        if self._origin is None or self.speed is None:
            return self._recorded_now
        return self._origin[0] + (time.monotonic() - self._origin[1]) * self.speed


def _bounded(wait: float) -> float:
    """``wait`` (s of wall time) within [0, :data:`MAX_WAIT_S`]."""
    return min(max(0.0, wait), MAX_WAIT_S)


class Replay(_Player):
    """Async replay of a recorded session with :class:`tactiled_client.Subscriber`'s interface."""

    def __init__(self, path: str | Path, topics: Sequence[str] | None = None, sensor: str | None = None, timeout: float | None = None,
                 speed: float | None = 1.0) -> None:
        super().__init__(path, topics, sensor, timeout, speed)

    async def __aenter__(self) -> Replay:
        self._open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        self._entries = None

    async def receive(self, timeout: float | None = None) -> schema.Message:
        """The next message, at its time; :class:`NoData` if it is further than ``timeout`` away, :class:`EndOfLog` at the end."""
        while True:
            wait, silence = self._plan(timeout)
            if wait > 0:
                await asyncio.sleep(wait)
            if silence is not None:
                raise self._silence(silence)
            if (msg := self._deliver()) is not None:
                return msg

    def __aiter__(self) -> AsyncIterator[schema.Message]:
        return self

    async def __anext__(self) -> schema.Message:
        try:
            return await self.receive()
        except EndOfLog:
            raise StopAsyncIteration from None


class BlockingReplay(_Player):
    """Blocking replay with :class:`tactiled_client.BlockingSubscriber`'s interface: ``with BlockingReplay(path) as sub: for msg in sub``."""

    def __init__(self, path: str | Path, topics: Sequence[str] | None = None, sensor: str | None = None, timeout: float | None = None,
                 speed: float | None = 1.0) -> None:
        super().__init__(path, topics, sensor, timeout, speed)
        self._open()

    def receive(self, timeout: float | None = None) -> schema.Message:
        """The next message, at its time; :class:`NoData` if it is further than ``timeout`` away, :class:`EndOfLog` at the end."""
        while True:
            wait, silence = self._plan(timeout)
            if wait > 0:
                time.sleep(wait)
            if silence is not None:
                raise self._silence(silence)
            if (msg := self._deliver()) is not None:
                return msg

    def __iter__(self) -> Iterator[schema.Message]:
        while True:
            try:
                yield self.receive()
            except EndOfLog:
                return

    def entries(self) -> Iterator[Entry]:
        """The file's messages as recorded (topic, body bytes, receive times), paced and filtered, without parsing them."""
        while (entry := self._next()) is not None:
            wait = self._wait(entry)
            if wait > 0:
                time.sleep(wait)
            self._pending = None
            self._recorded_now = entry.time_mono
            yield entry

    def close(self) -> None:
        """End the replay: :meth:`receive` raises UsageError afterwards."""
        self._entries = None

    def __enter__(self) -> BlockingReplay:
        return self

    def __exit__(self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None) -> None:
        self.close()


def publish(path: str | Path, endpoint: str, *, speed: float | None = 1.0, topics: Sequence[str] | None = None, sensor: str | None = None,
            wait_subscriber_s: float = 0.0, warn: Callable[[str], None] | None = None) -> int:
    """Publish a recorded session on ``endpoint`` (bound) as the daemon would: the same topics and two-frame msgpack framing,
    a fresh gapless ``seq`` per topic, ``time_unix`` when sent. Waits up to ``wait_subscriber_s`` for a first subscriber. Returns the messages sent.

    ``warn`` is told, in one line, when the file ends inside a record (a killed recorder: every message before it is sent)."""
    import zmq

    from tactiled_client.log import check_body

    player = BlockingReplay(path, topics, sensor, None, speed)
    sock: zmq.Socket[bytes] = zmq.Context.instance().socket(zmq.XPUB)
    sock.setsockopt(zmq.LINGER, 2000)
    allow_ipv6(sock, endpoint)
    try:
        sock.bind(endpoint)
    except zmq.ZMQError as exc:
        sock.close(linger=0)
        raise UsageError(f"--publish {endpoint}: {exc}") from None
    sent: dict[str, int] = {}
    try:
        if wait_subscriber_s > 0 and sock.poll(int(wait_subscriber_s * 1000)):
            sock.recv()  # the first subscription
        for entry in player.entries():
            body = check_body(entry.body, f"{path}: {entry.where}" if entry.where else str(path))
            body["seq"] = sent.get(entry.topic, 0)
            body["time_unix"] = time.time()  # sent now, as the daemon stamps what it sends (a subscriber ages labels by it)
            sent[entry.topic] = body["seq"] + 1
            sock.send_multipart([entry.topic.encode(), schema.pack(body)])
    finally:
        remove_socket_file(endpoint)
        sock.close()
    if player.reader.truncated and warn is not None:
        warn(player.reader.truncated)
    return sum(sent.values())
