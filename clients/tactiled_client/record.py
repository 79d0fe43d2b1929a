"""Record what a subscriber receives to a session log (:mod:`tactiled_client.log`), every topic and field exactly."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path

from tactiled_client.errors import UsageError
from tactiled_client.log import LogWriter
from tactiled_client.subscriber import _endpoints, _Filter, _secure

__all__ = ["record"]

DRAIN_MS = 200  # on stop, keep recording until the socket has been quiet this long (messages already in flight) ...
DRAIN_MAX_S = 1.0  # ... but never longer than this after the stop: a publisher that never pauses must not keep the recorder alive


def record(endpoints: str | Sequence[str], out: str | Path, *, seconds: float | None = None, topics: Sequence[str] | None = None,
           sensor: str | None = None, curve: tuple[str, str] | None = None, stop: Callable[[], bool] | None = None,
           overwrite: bool = False, on_message: Callable[[int], None] | None = None) -> int:
    """Subscribe to ``endpoints`` and append every message to ``out`` until ``seconds`` have passed or ``stop()`` is true.

    Each message is written with its receive times as it arrives (a killed recorder loses nothing before the
    last message); when told to stop, what is already in flight is still recorded (until :data:`DRAIN_MS` of quiet,
    at most :data:`DRAIN_MAX_S`); after ``seconds``, only what has already arrived.
    ``on_message(count)`` is called after each one. Returns the number of messages recorded.
    """
    import zmq

    if seconds is not None and not seconds > 0:
        raise UsageError(f"--seconds must be > 0, got {seconds}")
    sock: zmq.Socket[bytes] = zmq.Context.instance().socket(zmq.SUB)
    sock.setsockopt(zmq.LINGER, 0)
    try:
        wanted = _Filter(topics, sensor)
        _secure(sock, curve)
        for p in wanted.prefixes:
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
                if len(frames) == 2 and wanted.wants(frames[0]):  # else not a tactiled message, or another sensor's
                    log.write(frames, time.monotonic(), time.time())
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
                if sock.poll(int(left * 1000) + 1):
                    take()
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
        sock.close(linger=0)
