"""Serial ingest: a reader thread that wakes once per read period and hands over large batches.

pyserial only opens and configures the port; the thread then reads the file descriptor with
non-blocking ``os.read`` once per ``read_interval_s`` (taking everything the kernel holds) and
hands the bytes to the asyncio event loop at most once per :attr:`SerialSource.hand_over_s` (the daemon's
batch), so the loop wakes per batch, not per read. The consumer may change ``hand_over_s`` at any
time from the loop (a plain float the reader reads once per read: no lock); the daemon lengthens it
while no slide can be in progress (``serial.rest_batch_s``), which spares the loop most of its
wake-ups at rest, and shortens it again as soon as one may be. Measured on the loaded 2-core machine: a
wake-up costs 190 µs of CPU through ``asyncio.sleep``, 120 µs through ``call_later`` and 65 µs
in a plain thread (see docs/benchmarks.md). Nothing on the serial side runs on the loop, so
it can never block it.

The source survives everything: on unplug it reports the disconnection once, polls for the
device path every ``PRESENCE_POLL_S`` (a stat costs nothing; a replug is opened before the new
tty's ~44 ms of buffer overflows), backs off between failing opens, and resumes when the
path comes back (possibly a new pty behind the same symlink), keeping what the new tty holds.
The first open in the source's life instead reads and drops what the port already holds
(:attr:`SerialSource.discarded_at_start`, bytes): stale frames sent before anyone read the port,
then a gap to the fresh ones, would count as thousands of lost samples at start. Any other
exception in the reader is reported in one line, counted in :attr:`SerialSource.errors`, and the source
reconnects; an exception in the consumer (``on_bytes``) is reported and counted too, and
reading goes on. :attr:`SerialSource.alive_at` is the last time the reader loop ran (the
daemon's watchdog heartbeat).

Bytes go to ``on_bytes`` (awaited if it returns an awaitable), state changes to
``on_state(state, detail)``, in order, on the event loop (:meth:`SerialSource.run`) or, for
blocking users (``record``: :meth:`SerialSource.start` / :meth:`SerialSource.stop`), on the
reader thread. ``tee``: a binary file that receives every byte read, exactly (a raw capture
for ``tactiled replay x.bin``).

Each item handed over keeps the time of every read it joins (:class:`Reads`): while ``on_bytes`` runs,
:meth:`SerialSource.read_at` gives the host monotonic time of the read that returned a byte of it. That, not
:attr:`SerialSource.arrival` (the newest read, which may be seconds after the bytes being consumed when the
consumer lags), is when those bytes arrived: what a clock map of the board's sample index is fed with.

The loop always turns: :meth:`SerialSource.run` yields to the event loop after every item it hands
over, so status, the watchdog and signals are served between them however fast items queue up.
:attr:`SerialSource.behind` says how long the oldest bytes read but not yet consumed have waited
(the consumer uses it to shed work); the bytes waiting are bounded by ``max_backlog_bytes``: a read
that would exceed it is dropped and counted in :attr:`SerialSource.shed_bytes` (the decoder then
counts the samples in it as lost), so input that costs more to consume than it takes to arrive
cannot grow the daemon without bound.
"""

from __future__ import annotations

import asyncio
import bisect
import contextlib
import errno
import inspect
import itertools
import logging
import os
import select
import stat
import threading
import time
from collections import deque
from collections.abc import Awaitable, Callable, Iterable
from typing import Protocol

import serial

from tactiled.errors import DeviceError

log = logging.getLogger(__name__)

PRESENCE_POLL_S = 0.01
READ_CHUNK = 1 << 16  # bytes asked of one os.read: a tty hands out at most ~4 kB per call, and a 1 MiB request cost 18 us of
# allocation per read against 3.5 us (measured, bench_ingest's pty), 100 times a second
MAX_BACKLOG_BYTES = 4 << 20  # bytes read but not yet consumed: beyond this, new reads are dropped (counted) until the loop catches up
CONNECTED = "connected"
DISCONNECTED = "disconnected"
_END: tuple[str, str] = ("end", "")  # SerialSource.run's queue: the reader thread has ended (compared by identity)


class Tee(Protocol):
    """Where a copy of every byte read goes (a raw capture: :class:`tactiled.files.capture.CaptureWriter`); its writes must
    not raise, or the reader takes the error for the port's."""

    def write(self, data: bytes, /) -> object:
        """Append ``data``, the bytes of one read."""

    def flush(self) -> object:
        """What is buffered, to its file."""


class Reads:
    """Bytes read, and when: ``data`` joins one or more reads; read ``k`` returned ``data[ends[k - 1]:ends[k]]`` (from 0 for
    the first) at host monotonic time ``times[k]``. What the reader thread hands over (a few reads a hand-over: cheap)."""

    __slots__ = ("data", "ends", "times")

    def __init__(self, data: bytes, ends: list[int], times: list[float]) -> None:
        self.data, self.ends, self.times = data, ends, times

    @classmethod
    def join(cls, parts: list[bytes], times: list[float]) -> Reads:
        """One item of the reads ``parts``, read at ``times`` (one a part)."""
        if len(parts) == 1:
            return cls(parts[0], [len(parts[0])], times)
        return cls(b"".join(parts), list(itertools.accumulate(map(len, parts))), times)

    def time_at(self, offset: int) -> float:
        """When the byte at ``offset`` of :attr:`data` was read (host monotonic, s); past the end: the last read's time."""
        return self.times[min(bisect.bisect_right(self.ends, offset), len(self.times) - 1)]


_NOTHING = Reads(b"", [0], [0.0])  # what read_at answers from before any bytes were handed over


class KeepInputSerial(serial.Serial):
    """pyserial flushes a port's input when it opens it; after a replug that throws away intact frames
    the board sent before the open (3 680 samples over three reconnects in the soak, measured)."""

    _opening = False

    def open(self) -> None:
        """Open the port as pyserial does, but keep the bytes already in its input buffer."""
        self._opening = True
        try:
            super().open()
        finally:
            self._opening = False

    def _reset_input_buffer(self) -> None:  # what pyserial (>= 3.5) calls from open(); reset_input_buffer() goes through it too
        if not self._opening:
            super()._reset_input_buffer()  # type: ignore[misc]


NOT_A_TTY = "not a serial port (a tty)"


def check_port(path: str) -> None:
    """Raise :class:`DeviceError` naming ``path`` if it cannot be opened now (a URL: opened and closed again, so a
    ``socket://`` bridge sees one connection more); a path that is not a serial port (a regular file, a folder, a device
    that is not a terminal) is said so plainly (:func:`not_a_tty`)."""
    if "://" in path:
        try:
            serial.serial_for_url(path, timeout=0).close()
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"{path}: cannot open: {str(exc).removeprefix(f'Could not open port {path}: ')}") from None
        return
    if not os.path.exists(path):
        raise DeviceError(f"{path}: no such serial device")
    kind = not_a_tty(path)
    if kind is not None:
        raise DeviceError(f"{path}: {NOT_A_TTY}: {kind}")
    try:  # keeping its input: pyserial's open would empty it, and the reader's count of stale bytes would miss what it held
        port = KeepInputSerial(path, timeout=0, exclusive=True)
    except (serial.SerialException, OSError) as exc:
        why = open_error(exc, path)
        raise DeviceError(f"{path}: {why}" if why.startswith(NOT_A_TTY) else f"{path}: cannot open serial device: {why}") from None
    port.close()


def not_a_tty(path: str) -> str | None:
    """What ``path`` is when it cannot be a serial port, without opening it ("a regular file of 12 bytes", "a folder", ...);
    None for a character device (a tty, or one that only opening can tell from one) or a path that cannot be examined."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    mode = st.st_mode
    if stat.S_ISCHR(mode):
        return None
    if stat.S_ISREG(mode):
        return f"a regular file of {st.st_size} bytes"
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a named pipe"
    if stat.S_ISSOCK(mode):
        return "a socket"
    if stat.S_ISBLK(mode):
        return "a block device"
    return "not a character device"


def open_error(exc: BaseException, path: str | None = None) -> str:
    """Why a port did not open, for the user: pyserial's lock failure (ports are opened exclusively) and a ``path`` that is
    not a terminal (pyserial: "Could not configure port: (25, 'Inappropriate ioctl for device')") said plainly."""
    if "exclusively lock" in str(exc):
        return "another process has it open (a running daemon or recorder?): a port has one reader, or each gets part of its bytes"
    if path is not None and (kind := not_a_tty(path)) is not None:
        return f"{NOT_A_TTY}: {kind}"
    if getattr(exc, "errno", None) == errno.ENOTTY or "Inappropriate ioctl for device" in str(exc):
        return f"{NOT_A_TTY}: a character device that is not a terminal"
    return str(exc)


class Disconnected(OSError):
    """The device went away (a tty read returned end of file)."""


class SerialSource:
    """Reads ``path`` in a thread until cancelled (:meth:`run`) or stopped (:meth:`start` / :meth:`stop`); counts :attr:`reconnects`."""

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
        tee: Tee | None = None,
        hand_over_s: float = 0.0,
        max_backlog_bytes: int = MAX_BACKLOG_BYTES,
    ) -> None:
        self.path = path
        self.reconnects = 0
        self.errors = 0  # unexpected reader exceptions (each reported, then reconnected)
        self.connected = False
        self.arrival = 0.0  # host monotonic time of the newest bytes read (not of the bytes being consumed: read_at)
        self.alive_at = time.monotonic()  # the reader loop's heartbeat
        self._on_bytes = on_bytes
        self._on_state = on_state or (lambda state, detail: None)
        self._baudrate = baudrate
        self._retry = (retry_initial_s, retry_max_s)
        self._read_size = read_size
        self._read_interval = read_interval_s
        self._tee = tee
        self.hand_over_s = hand_over_s  # run(): bytes go to the loop at most this often, s (the loop may change it at any time)
        self._url = "://" in path
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.shed_bytes = 0  # bytes read but dropped before the consumer saw them (the backlog was full)
        self.discarded_at_start = 0  # bytes the port held when first opened, read and dropped (stale: sent before anyone read)
        self._max_backlog = max_backlog_bytes
        self._backlog = 0  # bytes handed to the loop and not yet consumed (run only)
        self._backlog_lock = threading.Lock()
        self._waiting: deque[float] = deque()  # read times of the items queued and not yet consumed (on the loop)
        self._current = _NOTHING  # the item being consumed (or the last one)

    @property
    def behind(self) -> float:
        """Seconds the oldest bytes read but not yet consumed have waited (0: nothing waiting; :meth:`run` only)."""
        return time.monotonic() - self._waiting[0] if self._waiting else 0.0

    def read_at(self, offset: int) -> float:
        """When the byte at ``offset`` of the bytes ``on_bytes`` is consuming was read (host monotonic, s): the time of the read
        that returned it, however long the bytes then waited to be consumed (call it from ``on_bytes``)."""
        return self._current.time_at(offset)

    # ---- blocking users: callbacks on the reader thread ------------------------------------

    def start(self) -> None:
        """Read in a thread until :meth:`stop`; ``on_bytes`` and ``on_state`` are called from that thread."""
        def deliver(item: Reads | tuple[str, str]) -> None:
            if isinstance(item, tuple):
                self._on_state(*item)
            else:
                self._consume(item)

        self._thread = threading.Thread(target=self._reader, args=(deliver, False), name=f"serial:{self.path}", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the reader thread of :meth:`start`, waiting up to ``timeout`` s for it to end."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def _consume(self, item: Reads) -> Awaitable[None] | None:
        self._current = item
        try:
            return self._on_bytes(item.data)
        except Exception as exc:  # a failing consumer must not take the reader down: reported, counted, reading goes on
            self._consumer_failed(exc)
            return None

    def _consumer_failed(self, exc: BaseException) -> None:
        self.errors += 1
        log.error("%s: processing the bytes read failed: %s: %s", self.path, type(exc).__name__, exc)

    # ---- asyncio users: bytes handed over to the loop -----------------------------------------

    async def run(self) -> None:
        """Read until cancelled, handing bytes to the loop at most once per :attr:`hand_over_s`; never returns otherwise.

        Yields to the loop after each item, whatever the queue holds, so no backlog can starve the loop's other tasks.
        """
        loop = asyncio.get_running_loop()
        queue: asyncio.Queue[Reads | tuple[str, str]] = asyncio.Queue()
        self._stop.clear()

        def arrive(read_at: float, item: Reads | tuple[str, str]) -> None:  # on the loop
            if isinstance(item, Reads):
                self._waiting.append(read_at)
            queue.put_nowait(item)

        def hand(item: Reads | tuple[str, str]) -> None:  # on the reader thread
            if isinstance(item, Reads):
                with self._backlog_lock:
                    if self._backlog + len(item.data) > self._max_backlog:
                        self.shed_bytes += len(item.data)
                        return
                    self._backlog += len(item.data)
            loop.call_soon_threadsafe(arrive, time.monotonic(), item)

        async def take(item: Reads | tuple[str, str]) -> None:
            if isinstance(item, tuple):
                self._on_state(*item)
                return
            try:
                result = self._consume(item)
                if inspect.isawaitable(result):
                    try:
                        await result
                    except Exception as exc:  # as in _consume: the daemon keeps running
                        self._consumer_failed(exc)
            finally:
                self._waiting.popleft()
                with self._backlog_lock:
                    self._backlog -= len(item.data)

        def read() -> None:  # the reader thread: once it ends (request_stop), what it held is queued, then the end
            try:
                self._reader(hand, True)
            finally:
                loop.call_soon_threadsafe(queue.put_nowait, _END)

        self._thread = threading.Thread(target=read, name=f"serial:{self.path}", daemon=True)
        self._thread.start()
        try:
            while (item := await queue.get()) is not _END:
                await take(item)
                if not queue.empty():  # (an empty queue's get() waits: the loop turns there, without an extra turn here)
                    await asyncio.sleep(0)  # the loop turns between items, however many are queued
        finally:
            self._stop.set()
            await asyncio.to_thread(self._thread.join, 5.0)

    def request_stop(self) -> None:
        """Stop reading: :meth:`run` hands over what the reader holds (already in a raw capture), then returns (thread-safe)."""
        self._stop.set()

    # ---- the reader thread ----------------------------------------------------------------------

    def _reader(self, deliver: Callable[[Reads | tuple[str, str]], None], batched: bool) -> None:
        down_reported = False
        barren = self._retry[0]  # the wait before reopening a port that failed before it gave a byte (doubling to retry_max_s)
        while not self._stop.is_set():
            port: serial.Serial | None = None
            try:
                port = self._connect(deliver, down_reported)
                if port is None:
                    return
                down_reported = False
                self._read_loop(port, deliver, batched)
            except (serial.SerialException, OSError) as exc:
                self.connected = False
                deliver((DISCONNECTED, f"disconnected: {exc}"))
                down_reported = True
                if self._read_any:  # a replug is reopened at once: the new tty's buffer fills from the first frame
                    barren = self._retry[0]
                else:  # opens, then fails at once (a bridge that closes each connection): not a tight loop
                    self._stop.wait(barren)  # backoff, not synchronisation
                    barren = min(barren * 2, self._retry[1])
            except Exception as exc:  # the reader must survive anything: reported, counted, reconnected
                self.errors += 1
                self.connected = False
                deliver((DISCONNECTED, f"reader error {type(exc).__name__}: {exc}; reconnecting"))
                down_reported = True
                self._stop.wait(self._retry[1])  # back off before reopening, not synchronisation
            finally:
                self.connected = False
                if port is not None:
                    with contextlib.suppress(Exception):
                        port.close()
                if self._tee is not None:
                    with contextlib.suppress(Exception):
                        self._tee.flush()

    def _connect(self, deliver: Callable[[Reads | tuple[str, str]], None], reported: bool) -> serial.Serial | None:
        delay = self._retry[0]
        while not self._stop.is_set():
            self.alive_at = time.monotonic()
            if not self._url and not os.path.exists(self.path):
                if not reported:
                    deliver((DISCONNECTED, f"waiting for the device ({self.path}: no such file)"))
                    reported = True
                self._stop.wait(PRESENCE_POLL_S)  # polling for the device to appear, not synchronisation
                continue
            try:
                port = self._open()
            except (serial.SerialException, OSError, ValueError, OverflowError) as exc:
                if not reported:
                    deliver((DISCONNECTED, f"cannot open: {open_error(exc, None if self._url else self.path)}; retrying"))
                    reported = True
                self._stop.wait(delay)  # capped backoff between failing opens, not synchronisation
                delay = min(delay * 2, self._retry[1])
                continue
            detail = self.path
            if self._ever_connected:
                self.reconnects += 1  # a replug: what the new tty holds are intact frames, kept
            else:
                self.discarded_at_start = self._discard_waiting(port)
                if self.discarded_at_start:
                    detail += f", {self.discarded_at_start} stale bytes discarded (sent before the port was opened)"
            self._ever_connected = True
            self.connected = True
            deliver((CONNECTED, detail))
            return port
        return None

    _ever_connected = False
    _read_any = False  # the connection being read has given bytes

    def _open(self) -> serial.Serial:
        if self._url:  # pyserial URL handlers (loop://, socket://, ...)
            return serial.serial_for_url(self.path, baudrate=self._baudrate, timeout=0)
        # exclusive: a second reader of one port (a recorder beside the daemon) would take half of each one's bytes
        return KeepInputSerial(self.path, baudrate=self._baudrate, timeout=0, exclusive=True)

    def _discard_waiting(self, port: serial.Serial) -> int:
        """Read and drop what a tty holds now (pyserial's URL handlers hold nothing stale); returns how many bytes.

        Reading counts them all, where ``in_waiting`` sees only the line discipline's 4 kB. At most ``MAX_BACKLOG_BYTES``, so a
        device streaming faster than this reads cannot hold it; a failing read stops it (the read loop then meets it again).
        """
        if self._url:
            return 0
        fd = port.fileno()
        os.set_blocking(fd, False)
        n = 0
        with contextlib.suppress(OSError):
            buf = bytearray(READ_CHUNK)
            while n < self._max_backlog and (chunk := _read_all(fd, self._read_size, buf)):
                n += len(chunk)
        return n

    def _read_loop(self, port: serial.Serial, deliver: Callable[[Reads | tuple[str, str]], None], batched: bool) -> None:
        """Read once per read period; hand what was read on every read (``batched`` False) or once per :attr:`hand_over_s`."""
        fd = port_fd(port)
        if fd is not None:
            os.set_blocking(fd, False)
        tee, interval, stop = self._tee, self._read_interval, self._stop
        self._read_any = False
        held: list[bytes] = []
        held_at: list[float] = []  # when each of held was read
        buf = bytearray(READ_CHUNK)
        handed = time.monotonic()
        try:
            # one read per period: waking per frame cost 36 % of a core at 1 000 frames/s (measured)
            # time.sleep, not stop.wait: an Event wait with a timeout allocates a lock and a Condition waiter per call
            while not stop.is_set():
                time.sleep(interval)  # the read period, not synchronisation
                now = self.alive_at = time.monotonic()
                data = _read_all(fd, self._read_size, buf) if fd is not None else port.read(self._read_size)  # timeout 0: what has come
                if data:
                    self.arrival, self._read_any = now, True
                    if tee is not None:
                        tee.write(data)
                    held.append(data)
                    held_at.append(now)
                if held and (not batched or now - handed >= self.hand_over_s):
                    deliver(Reads.join(held, held_at))
                    held, held_at, handed = [], [], now
        finally:
            if held:  # what was read before a disconnect still goes on
                deliver(Reads.join(held, held_at))


def port_fd(port: serial.SerialBase) -> int | None:
    """The file descriptor to read ``port`` by: a tty's, or a ``socket://`` port's socket (pyserial's socket ``read()`` drops
    what it gathered when it meets the close, and says 1 byte is waiting whatever has come); None for the URL handlers that
    have none (``loop://``, ``rfc2217://``: their ``fileno`` is io's, which raises), read through ``read()``."""
    try:
        return int(port.fileno())
    except (OSError, AttributeError):  # io.UnsupportedOperation is an OSError
        return None


def _read_all(fd: int, limit: int, buf: bytearray) -> bytes:
    """Everything the kernel holds for ``fd`` (non-blocking), up to ``limit`` bytes; raises :class:`Disconnected` on end of file.

    Reads into ``buf`` (the caller's, reused) and copies out what came: ``os.read(fd, n)`` allocates ``n`` bytes and shrinks
    them to what the kernel had, and 64 kB allocations shrunk to ~1 kB a hundred times a second fragmented the reader
    thread's heap (glibc's ``malloc_stats``: a thread arena's system bytes grew 0.8 MB in 7 minutes while its in-use bytes
    stayed near 70 kB; docs/benchmarks.md).
    """
    parts: list[bytes] = []
    total = 0
    view = memoryview(buf)
    while total < limit:
        want = view[: min(len(buf), limit - total)]
        try:
            n = os.readv(fd, [want])
        except BlockingIOError:
            break
        except OSError:  # the port went (EIO) after bytes of this call: they go on, and the next call meets the error
            if parts:
                break
            raise
        if not n:
            # a tty with VMIN = VTIME = 0 reads nothing when it has nothing; after a hangup it polls readable yet reads nothing
            if parts or not select.select([fd], [], [], 0)[0]:
                break
            n = os.readv(fd, [want])  # readable: data that just came, or the hangup
            if not n:
                raise Disconnected("device reports readiness to read but returned no data (unplugged?)")
        parts.append(bytes(want[:n]))
        total += n  # and read again: a tty hands out at most 4095 bytes a read, whatever waits behind them
    return parts[0] if len(parts) == 1 else b"".join(parts)


class ByteSource(Protocol):
    """What the daemon reads from: :class:`SerialSource`, or :class:`MemorySource` in tests."""

    connected: bool
    reconnects: int
    errors: int
    arrival: float  # the newest read's host monotonic time, s (not the bytes being consumed: read_at)
    alive_at: float
    shed_bytes: int
    discarded_at_start: int
    hand_over_s: float  # how often the source hands bytes to the loop, s (the consumer may change it; a memory source ignores it)

    @property
    def behind(self) -> float:
        """Seconds the oldest bytes read but not yet consumed have waited (0: keeping up)."""

    def read_at(self, offset: int) -> float:
        """Host monotonic time (s) of the read that returned byte ``offset`` of the bytes being consumed (from ``on_bytes``)."""

    async def run(self) -> None:
        """Read until cancelled, stopped or the source ends, handing bytes to ``on_bytes`` and state changes to ``on_state``."""

    def request_stop(self) -> None:
        """End :meth:`run` soon, once what was read has been handed over."""


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
        self.shed_bytes = 0
        self.discarded_at_start = 0
        self.behind = 0.0  # a memory source hands over one chunk at a time: never behind
        self.hand_over_s = 0.0  # ignored: one chunk per step
        self._chunks = chunks
        self._on_bytes = on_bytes
        self._on_state = on_state or (lambda state, detail: None)
        self._period = period_s
        self._stopping = False

    def read_at(self, offset: int) -> float:
        """When the chunk being consumed was handed over (one read a chunk), s."""
        return self.arrival

    def request_stop(self) -> None:
        """End :meth:`run` before the next chunk."""
        self._stopping = True

    async def run(self) -> None:
        """Report connected, hand each chunk to ``on_bytes`` (awaited if it returns an awaitable) ``period_s`` apart, then report disconnected."""
        self.connected = True
        self._on_state(CONNECTED, "memory")
        for data in self._chunks:
            if self._stopping:
                break
            await asyncio.sleep(self._period)  # pacing (0: just yield to the loop), not synchronisation
            self.alive_at = self.arrival = time.monotonic()
            result = self._on_bytes(data)
            if inspect.isawaitable(result):
                await result
        self.connected = False
        self._on_state(DISCONNECTED, "end of stream")
