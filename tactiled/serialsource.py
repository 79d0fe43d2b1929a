"""Serial ingest on pyserial, in a reader thread.

A plain thread (not an asyncio serial adapter) because it keeps reading while the event
loop is busy, needs nothing beyond pyserial, and owns the reconnect loop: on unplug it
reports the disconnection once, retries with capped exponential backoff, and resumes when
the device path comes back (possibly a new pty behind the same symlink). Bytes go to
``on_bytes`` and state changes to ``on_state``; both are called from the reader thread,
so an asyncio user wraps them with ``loop.call_soon_threadsafe``.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable

import serial

from tactiled.errors import DeviceError

log = logging.getLogger(__name__)

PRESENCE_POLL_S = 0.01
CONNECTED = "connected"
DISCONNECTED = "disconnected"


class KeepInputSerial(serial.Serial):
    """pyserial flushes a port's input when it opens it; after a replug that throws away intact frames
    the board sent before the open (3 680 samples over three reconnects in the soak, measured)."""

    _opening = False

    def open(self) -> None:
        self._opening = True
        try:
            super().open()
        finally:
            self._opening = False

    def reset_input_buffer(self) -> None:
        if not self._opening:
            super().reset_input_buffer()


def check_port(path: str) -> None:
    """Raise :class:`DeviceError` naming ``path`` if it cannot be opened now."""
    if "://" in path:
        return
    if not os.path.exists(path):
        raise DeviceError(f"{path}: no such serial device")
    try:
        port = serial.Serial(path, timeout=0)
    except (serial.SerialException, OSError) as exc:
        raise DeviceError(f"{path}: cannot open serial device: {exc}") from None
    port.close()


class SerialSource:
    """Reads ``path`` in a thread until :meth:`stop`; counts :attr:`reconnects`."""

    def __init__(
        self,
        path: str,
        on_bytes: Callable[[bytes], None],
        on_state: Callable[[str, str], None] | None = None,
        *,
        baudrate: int = 1_000_000,
        retry_initial_s: float = 0.05,
        retry_max_s: float = 2.0,
        read_interval_s: float = 0.01,
        read_size: int = 1 << 20,
    ) -> None:
        self.path = path
        self.reconnects = 0
        self.connected = False
        self._on_bytes = on_bytes
        self._on_state = on_state or (lambda state, detail: None)
        self._baudrate = baudrate
        self._retry = (retry_initial_s, retry_max_s)
        self._read_size = read_size
        self._read_interval = read_interval_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"serial:{path}", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        self._thread.join(timeout)

    def _open(self) -> serial.Serial:
        # non-blocking reads, one per read_interval_s (see _run): waking per frame cost
        # 36 % of a core at 1 000 frames/s, a timed read still woke per chunk (11 %), measured
        if "://" in self.path:  # pyserial URL handlers (loop://, socket://, ...)
            return serial.serial_for_url(self.path, baudrate=self._baudrate, timeout=0)
        return KeepInputSerial(self.path, baudrate=self._baudrate, timeout=0)

    def _run(self) -> None:
        delay = self._retry[0]
        ever_connected = False
        reported_down = False
        while not self._stop.is_set():
            try:
                port = self._open()
            except (serial.SerialException, OSError, ValueError) as exc:
                if not reported_down:
                    log.warning("%s: cannot open: %s; retrying", self.path, exc)
                    self._on_state(DISCONNECTED, str(exc))
                    reported_down = True
                if "://" not in self.path and not os.path.exists(self.path):
                    # absent device: look for it every PRESENCE_POLL_S (a stat costs nothing), so a replug
                    # is opened before its ~44 ms of tty buffer overflows; back off only on failing opens
                    self._stop.wait(PRESENCE_POLL_S)
                    continue
                self._stop.wait(delay)  # capped backoff between retries, not synchronisation
                delay = min(delay * 2, self._retry[1])
                continue
            if ever_connected:
                self.reconnects += 1
            ever_connected = True
            reported_down = False
            delay = self._retry[0]
            self.connected = True
            self._on_state(CONNECTED, self.path)
            try:
                while not self._stop.wait(self._read_interval):  # the read period, not synchronisation
                    data = port.read(max(1, min(port.in_waiting, self._read_size)))
                    if data:
                        self._on_bytes(data)
            except (serial.SerialException, OSError) as exc:
                log.warning("%s: disconnected: %s", self.path, exc)
                self.connected = False
                self._on_state(DISCONNECTED, str(exc))
                reported_down = True
            finally:
                self.connected = False
                port.close()
