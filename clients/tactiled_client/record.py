"""Record what a subscriber receives to a session log (:mod:`tactiled_client.log`), every topic and field exactly.

A message no reader could read back (:class:`~tactiled_client.errors.RecordRefused`: over ``log.MAX_RECORD`` bytes, a body
that is not a msgpack map) is not written: it is counted and said (``on_refused``), and recording goes on. The SUB
socket takes no frame over ``log.MAX_RECORD`` bytes (``zmq.MAXMSGSIZE``), so a publisher cannot make the recorder hold
more than that per frame; libzmq drops the connection of a peer that sends one and, for that error, never reconnects it:
the recorder does (:class:`_Redialer`), and says so. What that publisher sent between the oversize message and the
reconnect is lost (its ``seq`` shows the gap on replay).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import zmq
from zmq.utils.monitor import recv_monitor_message

from tactiled_client.endpoints import connect
from tactiled_client.errors import RecordRefused, UsageError
from tactiled_client.log import MAX_RECORD, LogWriter
from tactiled_client.subscriber import _endpoints, _Filter, _secure

__all__ = ["record"]

DRAIN_MS = 200  # on stop, keep recording until the socket has been quiet this long (messages already in flight) ...
DRAIN_MAX_S = 1.0  # ... but never longer than this after the stop: a publisher that never pauses must not keep the recorder alive
RETRY_GRACE_S = 0.1  # libzmq announces its own reconnect (CONNECT_RETRIED) at once after a DISCONNECTED; none this long after: it gave up


class _Redialer:
    """Reconnect the endpoints libzmq dropped for a protocol error (a frame over ``zmq.MAXMSGSIZE``) and gave up on.

    Watches the socket's monitor: a connection that had completed its handshake, is DISCONNECTED, and is not followed
    within :data:`RETRY_GRACE_S` by libzmq's own CONNECT_RETRIED (what a publisher that went away gets) is connected again,
    and ``on_drop`` told in one line. A connection refused during its handshake (CURVE) is left alone: redialling it would
    only be refused again.
    """

    def __init__(self, sock: zmq.Socket[bytes], endpoints: list[str], on_drop: Callable[[str], None]) -> None:
        self._sock = sock
        self._endpoints = endpoints
        self._on_drop = on_drop
        self.monitor: Any = sock.get_monitor_socket(zmq.EVENT_HANDSHAKE_SUCCEEDED | zmq.EVENT_DISCONNECTED | zmq.EVENT_CONNECT_RETRIED)
        self._up: set[str] = set()
        self._dropped: dict[str, float] = {}  # endpoint -> when its DISCONNECTED was read (host monotonic clock)

    def check(self) -> None:
        """Read the monitor's events, and redial each endpoint dropped longer than :data:`RETRY_GRACE_S` ago that libzmq
        is not reconnecting."""
        while self.monitor.poll(0):
            event = recv_monitor_message(self.monitor)
            endpoint = event["endpoint"].decode("utf-8", "replace")
            if event["event"] == zmq.EVENT_HANDSHAKE_SUCCEEDED:
                self._up.add(endpoint)
            elif event["event"] == zmq.EVENT_DISCONNECTED and endpoint in self._up:
                self._up.discard(endpoint)
                self._dropped[endpoint] = time.monotonic()
            elif event["event"] == zmq.EVENT_CONNECT_RETRIED:
                self._dropped.pop(endpoint, None)
        now = time.monotonic()
        for endpoint, when in list(self._dropped.items()):
            if now - when >= RETRY_GRACE_S:
                del self._dropped[endpoint]
                self._redial(endpoint)

    def _redial(self, endpoint: str) -> None:
        """Connect ``endpoint`` again (every endpoint if libzmq named it otherwise than it was given)."""
        for e in [endpoint] if endpoint in self._endpoints else self._endpoints:
            with contextlib.suppress(zmq.ZMQError):  # already gone with its session
                self._sock.disconnect(e)
            self._sock.connect(e)
        self._on_drop(f"{endpoint}: its connection was dropped for a message over {MAX_RECORD} bytes (or a frame that is not "
                      "ZeroMQ's) and made again; what it sent meanwhile is lost")

    def close(self) -> None:
        """Stop monitoring and close the monitor socket."""
        try:
            self._sock.disable_monitor()
        finally:
            self.monitor.close(linger=0)


def record(endpoints: str | Sequence[str], out: str | Path, *, seconds: float | None = None, topics: Sequence[str] | None = None,
           sensor: str | None = None, curve: tuple[str, str] | None = None, stop: Callable[[], bool] | None = None,
           overwrite: bool = False, on_message: Callable[[int], None] | None = None,
           on_refused: Callable[[str], None] | None = None) -> int:
    """Subscribe to ``endpoints`` and append every message to ``out`` until ``seconds`` have passed or ``stop()`` is true.

    Each message is written with its receive times as it arrives (a killed recorder loses nothing before the
    last message); when told to stop, what is already in flight is still recorded (until :data:`DRAIN_MS` of quiet,
    at most :data:`DRAIN_MAX_S`); after ``seconds``, only what has already arrived.
    ``on_message(count)`` is called after each one; ``on_refused(why)`` (one line) for each message not recorded because no
    reader could read it back, and each connection dropped for an oversize message (see the module docstring). Returns
    the number of messages recorded. ``out`` must be a regular file (:class:`~tactiled_client.errors.LogError` before
    recording otherwise); a write the machine refuses (a full disk, a file-size limit) ends the recording with
    :class:`~tactiled_client.log.WriteFailed`, every message before it kept whole.
    """
    if seconds is not None and not seconds > 0:
        raise UsageError(f"--seconds must be > 0, got {seconds}")
    told = on_refused if on_refused is not None else (lambda why: None)
    sock: zmq.Socket[bytes] = zmq.Context.instance().socket(zmq.SUB)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.MAXMSGSIZE, MAX_RECORD)  # per frame: a larger one could never be a record (and would be held whole)
    redialer: _Redialer | None = None
    try:
        wanted = _Filter(topics, sensor)
        _secure(sock, curve)
        for p in wanted.prefixes:
            sock.setsockopt(zmq.SUBSCRIBE, p)
        redialer = _Redialer(sock, _endpoints(endpoints), told)
        for e in _endpoints(endpoints):
            connect(sock, e)
        deadline = None if seconds is None else time.monotonic() + seconds
        poller = zmq.Poller()
        poller.register(sock, zmq.POLLIN)
        poller.register(redialer.monitor, zmq.POLLIN)
        with LogWriter(out, overwrite=overwrite) as log:

            def take() -> None:
                frames = sock.recv_multipart()
                if len(frames) != 2:  # not a tactiled message: no record could hold it
                    topic = frames[0][:80].decode("utf-8", "replace") if frames else "(no frames)"
                    told(f"{topic}: {len(frames)} frames, not 2")
                    return
                if not wanted.wants(frames[0]):  # another sensor's
                    return
                try:
                    log.write(frames, time.monotonic(), time.time())
                except RecordRefused as exc:
                    told(exc.reason)
                    return
                if on_message is not None:
                    on_message(log.count)

            stopped = False
            while True:
                if stop is not None and stop():
                    stopped = True
                    break
                left = 0.1 if deadline is None else min(0.1, deadline - time.monotonic())
                if left <= 0:
                    break
                if sock in dict(poller.poll(int(left * 1000) + 1)):
                    take()
                redialer.check()
            # what has already arrived, and when told to stop what is still on the wire: a bounded drain (a steady publisher
            # never leaves DRAIN_MS of quiet: draining until it did ran a 1 s recording for 410 s, deaf to signals)
            end = time.monotonic() + (DRAIN_MAX_S if stopped else 0.0)
            queued = int(sock.getsockopt(zmq.RCVHWM)) or 1000  # at most a full queue once the drain's time is up
            while queued > 0:
                left_ms = int((end - time.monotonic()) * 1000)
                if not sock.poll(max(0, min(DRAIN_MS, left_ms))):
                    break
                take()
                if left_ms <= 0:
                    queued -= 1
            return log.count
    finally:
        if redialer is not None:
            redialer.close()
        sock.close(linger=0)
