"""Serial ingest: the port's file descriptor read from the asyncio event loop.

pyserial only opens and configures the port (in a worker thread: an open may block); the
bytes are then read with non-blocking ``os.read`` once per ``read_interval_s``, from the
event loop itself: no reader thread, no thread hop per read. Every read takes all the
kernel holds, so nothing on the serial side blocks the loop for longer than one read.

The source survives everything: on unplug it reports the disconnection once, polls for the
device path every ``PRESENCE_POLL_S`` (a stat costs nothing; a replug is opened before the new
tty's ~44 ms of buffer overflows), backs off between failing opens, and resumes when the
path comes back (possibly a new pty behind the same symlink). Any other exception in the
reader is reported in one line, counted in :attr:`SerialSource.errors`, and the source
reconnects. :attr:`SerialSource.alive_at` is the last time the reader loop ran (the
daemon's watchdog heartbeat).

Bytes go to ``on_bytes`` (awaited if it returns an awaitable), state changes to
``on_state(state, detail)``. ``tee``: a binary file that receives every byte read,
exactly (a raw capture for ``tactiled replay x.bin``). Blocking users (``record``) call
:meth:`SerialSource.start` / :meth:`SerialSource.stop`, which run the same loop in a thread.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import os
import select
import threading
import time
from collections.abc import Awaitable, Callable, Iterable
from typing import BinaryIO

import serial

from tactiled.errors import DeviceError

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


class Disconnected(OSError):
    """The device went away (a tty read returned end of file)."""


class SerialSource:
    """Reads ``path`` until cancelled (:meth:`run`) or stopped (:meth:`start` / :meth:`stop`); counts :attr:`reconnects`."""

    def __init__(
        self,
        path: str,
        on_bytes: Callable[[bytes], Awaitable[None] | None],
        on_state: Callable[[str, str], None] | None = None,
        *,
        baudrate: int = 1_000_000,
        retry_initial_s: float = 0.05,
        retry_max_s: float = 2.0,
        read_interval_s: float = 0.01,
        read_size: int = 1 << 20,
        tee: BinaryIO | None = None,
    ) -> None:
        self.path = path
        self.reconnects = 0
        self.errors = 0  # unexpected reader exceptions (each reported, then reconnected)
        self.connected = False
        self.arrival = 0.0  # host monotonic time of the newest bytes read
        self.alive_at = time.monotonic()  # the reader loop's heartbeat
        self._on_bytes = on_bytes
        self._on_state = on_state or (lambda state, detail: None)
        self._baudrate = baudrate
        self._retry = (retry_initial_s, retry_max_s)
        self._read_size = read_size
        self._read_interval = read_interval_s
        self._tee = tee
        self._url = "://" in path
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopped: asyncio.Event | None = None
        self._started = threading.Event()

    # ---- blocking users: the same loop in a thread ----------------------------------------

    def start(self) -> None:
        """Run :meth:`run` in a thread of its own until :meth:`stop`."""
        self._thread = threading.Thread(target=lambda: asyncio.run(self._until_stopped()), name=f"serial:{self.path}", daemon=True)
        self._thread.start()
        self._started.wait(5.0)

    def stop(self, timeout: float = 2.0) -> None:
        if self._loop is not None and self._stopped is not None:
            with contextlib.suppress(RuntimeError):  # the loop already ended
                self._loop.call_soon_threadsafe(self._stopped.set)
        if self._thread is not None:
            self._thread.join(timeout)

    async def _until_stopped(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stopped = asyncio.Event()
        self._started.set()
        task = asyncio.create_task(self.run())
        await self._stopped.wait()
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task

    # ---- the reader -----------------------------------------------------------------------

    async def run(self) -> None:
        """Read until cancelled; never returns otherwise and never raises (but CancelledError)."""
        down_reported = False
        while True:
            port: serial.Serial | None = None
            try:
                port = await self._connect(down_reported)
                down_reported = False
                await self._read_loop(port)
            except asyncio.CancelledError:
                raise
            except (serial.SerialException, OSError) as exc:
                self._down(f"disconnected: {exc}")
                down_reported = True
            except Exception as exc:  # the reader must survive anything: reported, counted, reconnected
                self.errors += 1
                self._down(f"reader error {type(exc).__name__}: {exc}; reconnecting")
                down_reported = True
                await asyncio.sleep(self._retry[1])  # back off before reopening, not synchronisation
            finally:
                self.connected = False
                if port is not None:
                    with contextlib.suppress(Exception):
                        port.close()
                if self._tee is not None:
                    self._tee.flush()

    def _down(self, detail: str) -> None:
        self.connected = False
        self._on_state(DISCONNECTED, detail)

    async def _connect(self, reported: bool) -> serial.Serial:
        delay = self._retry[0]
        while True:
            self.alive_at = time.monotonic()
            if not self._url and not os.path.exists(self.path):
                if not reported:
                    self._down(f"waiting for the device ({self.path}: no such file)")
                    reported = True
                await asyncio.sleep(PRESENCE_POLL_S)  # polling for the device to appear, not synchronisation
                continue
            try:
                port = await asyncio.to_thread(self._open)  # an open can block (USB): never on the loop
            except (serial.SerialException, OSError, ValueError, OverflowError) as exc:
                if not reported:
                    self._down(f"cannot open: {exc}; retrying")
                    reported = True
                await asyncio.sleep(delay)  # capped backoff between failing opens, not synchronisation
                delay = min(delay * 2, self._retry[1])
                continue
            if self._ever_connected:
                self.reconnects += 1
            self._ever_connected = True
            self.connected = True
            self._on_state(CONNECTED, self.path)
            return port

    _ever_connected = False

    def _open(self) -> serial.Serial:
        if self._url:  # pyserial URL handlers (loop://, socket://, ...)
            return serial.serial_for_url(self.path, baudrate=self._baudrate, timeout=0)
        return KeepInputSerial(self.path, baudrate=self._baudrate, timeout=0)

    async def _read_loop(self, port: serial.Serial) -> None:
        fd = None if self._url else port.fileno()
        if fd is not None:
            os.set_blocking(fd, False)
        on_bytes, tee, interval = self._on_bytes, self._tee, self._read_interval
        while True:
            # one read per period: waking per frame cost 36 % of a core at 1 000 frames/s (measured)
            await asyncio.sleep(interval)  # the read period, not synchronisation
            now = self.alive_at = time.monotonic()
            data = _read_all(fd, self._read_size) if fd is not None else port.read(max(1, min(port.in_waiting, self._read_size)))
            if not data:
                continue
            self.arrival = now
            if tee is not None:
                tee.write(data)
            result = on_bytes(data)
            if inspect.isawaitable(result):
                await result


def _read_all(fd: int, limit: int) -> bytes:
    """Everything the kernel holds for ``fd`` (non-blocking), up to ``limit`` bytes; raises :class:`Disconnected` on end of file."""
    parts: list[bytes] = []
    total = 0
    while total < limit:
        try:
            chunk = os.read(fd, limit - total)
        except BlockingIOError:
            break
        if not chunk:
            # a tty with VMIN = VTIME = 0 reads nothing when it has nothing; after a hangup it polls readable yet reads nothing
            if parts or not select.select([fd], [], [], 0)[0]:
                break
            chunk = os.read(fd, limit - total)  # readable: data that just came, or the hangup
            if not chunk:
                raise Disconnected("device reports readiness to read but returned no data (unplugged?)")
        parts.append(chunk)
        total += len(chunk)
        if len(chunk) < 4096:  # the kernel had no more (a tty hands out at most its buffer per read)
            break
    return parts[0] if len(parts) == 1 else b"".join(parts)


class MemorySource:
    """A finite byte source for tests and replays: ``chunks`` handed to ``on_bytes`` one per step, then :meth:`run` returns.

    ``period_s``: wait this long before each chunk (0: as fast as the consumer takes them).
    """

    def __init__(self, chunks: Iterable[bytes], on_bytes: Callable[[bytes], Awaitable[None] | None],
                 on_state: Callable[[str, str], None] | None = None, *, period_s: float = 0.0) -> None:
        self.connected = False
        self.reconnects = 0
        self.errors = 0
        self.arrival = 0.0
        self.alive_at = time.monotonic()
        self._chunks = chunks
        self._on_bytes = on_bytes
        self._on_state = on_state or (lambda state, detail: None)
        self._period = period_s

    async def run(self) -> None:
        self.connected = True
        self._on_state(CONNECTED, "memory")
        for data in self._chunks:
            await asyncio.sleep(self._period)  # pacing (0: just yield to the loop), not synchronisation
            self.alive_at = self.arrival = time.monotonic()
            result = self._on_bytes(data)
            if inspect.isawaitable(result):
                await result
        self.connected = False
        self._on_state(DISCONNECTED, "end of stream")
