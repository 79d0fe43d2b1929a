"""Record what a subscriber receives to a session log (:mod:`tactiled_client.log`), every topic and field exactly."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path

from tactiled_client.errors import UsageError
from tactiled_client.log import LogWriter
from tactiled_client.subscriber import _endpoints, _prefixes, _secure

__all__ = ["record"]

DRAIN_MS = 200  # on stop, keep recording until the socket has been quiet this long (messages already in flight)


def record(endpoints: str | Sequence[str], out: str | Path, *, seconds: float | None = None, topics: Sequence[str] | None = None,
           sensor: str | None = None, curve: tuple[str, str] | None = None, stop: Callable[[], bool] | None = None,
           overwrite: bool = False, on_message: Callable[[int], None] | None = None) -> int:
    """Subscribe to ``endpoints`` and append every message to ``out`` until ``seconds`` have passed or ``stop()`` is true.

    Each message is written with its receive times as it arrives (a killed recorder loses nothing before the
    last message); when told to stop, what is already in flight is still recorded (until :data:`DRAIN_MS` of quiet).
    ``on_message(count)`` is called after each one. Returns the number of messages recorded.
    """
    import zmq

    if seconds is not None and not seconds > 0:
        raise UsageError(f"--seconds must be > 0, got {seconds}")
    sock: zmq.Socket[bytes] = zmq.Context.instance().socket(zmq.SUB)
    sock.setsockopt(zmq.LINGER, 0)
    try:
        _secure(sock, curve)
        for p in _prefixes(topics, sensor):
            sock.setsockopt(zmq.SUBSCRIBE, p)
        for e in _endpoints(endpoints):
            try:
                sock.connect(e)
            except zmq.ZMQError as exc:
                raise UsageError(f"{e}: {exc}") from None
        deadline = None if seconds is None else time.monotonic() + seconds
        with LogWriter(out, overwrite=overwrite) as log:

            def take() -> None:
                frames = sock.recv_multipart()
                if len(frames) == 2:  # else not a tactiled message
                    log.write(frames, time.monotonic(), time.time())
                    if on_message is not None:
                        on_message(log.count)

            while not (stop is not None and stop()):
                left = 0.1 if deadline is None else min(0.1, deadline - time.monotonic())
                if left <= 0:
                    break
                if sock.poll(int(left * 1000) + 1):
                    take()
            while sock.poll(DRAIN_MS):  # what is already on the wire when told to stop
                take()
            return log.count
    finally:
        sock.close(linger=0)
