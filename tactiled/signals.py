"""Process signals and systemd: which signals stop a capture or the daemon, and the notify socket (readiness, watchdog)."""

from __future__ import annotations

import logging
import os
import signal
import socket
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

log = logging.getLogger(__name__)

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)  # a recorder stops on any; the daemon reloads its model on SIGHUP


def sd_notify(message: str) -> None:
    """Send ``message`` (``READY=1``, ``WATCHDOG=1``, ``STOPPING=1``) to systemd's notify socket, if there is one (Type=notify)."""
    path = os.environ.get("NOTIFY_SOCKET")
    if not path:
        return
    if path.startswith("@"):
        path = "\0" + path[1:]
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.setblocking(False)  # never wait on the notify socket: a full queue must not stall the event loop
        try:
            sock.connect(path)
            sock.send(message.encode())
        except OSError as exc:  # BlockingIOError (the queue is full) among them: this notification is dropped
            log.warning("sd_notify failed: %s", exc)


@contextmanager
def sigterm_as_exit(signals: tuple[signal.Signals, ...] = (signal.SIGTERM,)) -> Iterator[None]:
    """Within the block, SIGTERM (and any other of ``signals``: the demo adds SIGHUP, its terminal closed) raises
    ``SystemExit(128 + signal)`` like Ctrl-C raises KeyboardInterrupt, so ``finally`` clauses run (a parent that starts
    processes stops them instead of leaving them orphaned)."""
    def handler(signum: int, frame: FrameType | None) -> None:
        raise SystemExit(128 + signum)

    previous = {sig: signal.signal(sig, handler) for sig in signals}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
