"""``tactiled record``: serial frames → a recording file, with every lost sample listed, streamed to disk.

:class:`RecordingSink` (used by ``record`` and ``run --record``) writes the samples to a journal beside the output
(tactiled/journal.py) as they come, committed (written and fsynced) at least every :data:`COMMIT_S` of wall time
or of sensor time, whichever comes first, from a writer thread so the caller never waits on the disk. Memory stays
bounded. On a clean stop the journal becomes the ``.npz`` and is removed; after a kill or a power cut
``tactiled recover`` turns it into the ``.npz``.
"""

from __future__ import annotations

import logging
import os
import queue
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from tactiled.errors import OutputError
from tactiled.frames import Frame, FrameDecoder
from tactiled.journal import JournalWriter, encode_chunk, encode_header, is_locked, journal_path, recover
from tactiled.recording import fsync_dir
from tactiled.serialsource import DISCONNECTED, SerialSource, check_port

log = logging.getLogger(__name__)

COMMIT_S = 0.5  # the most that a kill or a power cut can lose, in wall time or sensor time (s)
MAX_CHUNK_BYTES = 4 << 20  # a chunk is committed at this size at the latest
QUEUE_FRAMES = 8192  # frames waiting for the writer (8 s of 20-sample frames at 20 kHz); beyond, frames are lost, counted
_TICK = object()


def check_output(out: str | Path, force: bool) -> None:
    """Raise :class:`OutputError` naming ``out`` unless a file can be written there (and, without ``force``, none exists)."""
    out = Path(out)
    folder = out.parent
    if not folder.exists():
        raise OutputError(f"{out}: folder {folder} does not exist")
    if not folder.is_dir():
        raise OutputError(f"{out}: {folder} is not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputError(f"{out}: folder {folder} is not writable")
    if out.is_dir():
        raise OutputError(f"{out}: is a folder")
    if out.exists() and not force:
        raise OutputError(f"{out}: exists (--force overwrites it)")


def claim_journal(out: str | Path) -> Path:
    """The journal path for ``out``; a journal left there by a recorder that did not finish is renamed aside, never overwritten."""
    journal = journal_path(out)
    if not journal.exists():
        return journal
    if is_locked(journal):
        raise OutputError(f"{journal}: in use by another recorder")
    n = 1
    while Path(f"{journal}.{n}").exists():
        n += 1
    aside = Path(f"{journal}.{n}")
    os.rename(journal, aside)
    log.warning("%s: left by a recorder that did not finish; kept as %s (tactiled recover %s -o OUT.npz)", journal, aside, aside)
    return journal


@dataclass
class SinkResult:
    """What a :class:`RecordingSink` kept: rows (samples, lost included) and, if it failed, the one-line reason."""

    samples: int
    samples_lost: int
    error: str | None = None


class RecordingSink:
    """Decoded frames → the journal of ``out``, then ``out`` itself at :meth:`finish`.

    :meth:`add` only queues the frame (cheap, any thread, never blocks); a writer thread places it at its
    position (``frame.index`` - the first frame's index: gaps become lost ranges, never stored), and commits a
    chunk every :data:`COMMIT_S`. With ``limit``, rows from position ``limit`` on are ignored and :attr:`done`
    turns True. A write error (a full disk) stops the writing: :attr:`error` says so in one line, the journal
    keeps every chunk committed before, ``on_error`` is called with the line.
    """

    def __init__(self, out: str | Path, *, fs: float, channels: int, volts_per_count: float, label: str | None = None,
                 meta: dict[str, Any] | None = None, limit: int | None = None, force: bool = False,
                 counters: Callable[[], dict[str, int]] | None = None, on_error: Callable[[str], None] | None = None,
                 commit_s: float = COMMIT_S) -> None:
        check_output(out, force)
        self.out = Path(out)
        self.journal = claim_journal(out)
        self.channels = channels
        self.fs = fs
        self.limit = limit
        self.first_index: int | None = None
        self.restarts = 0
        self.channel_errors = 0
        self.queue_dropped = 0  # samples dropped because the writer fell behind (listed as lost)
        self.error: str | None = None
        self._counters = counters or dict
        self._on_error = on_error
        self._commit_s = commit_s
        self._commit_rows = max(1, round(commit_s * fs))
        self._end = 0  # position after the newest row queued
        self._rows = 0  # rows committed
        self._lost = 0  # lost rows committed
        header = encode_header(fs, channels, volts_per_count, label, {**(meta or {}), "recorded_at": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
        try:
            self._writer = JournalWriter(self.journal, header)
        except OSError as exc:
            raise OutputError(f"{self.journal}: cannot create: {exc.strerror or exc}") from None
        self._queue: queue.Queue[tuple[int, npt.NDArray[np.int16]] | None] = queue.Queue(QUEUE_FRAMES)
        self._thread = threading.Thread(target=self._run, name=f"journal:{self.journal.name}", daemon=True)
        self._thread.start()

    @property
    def done(self) -> bool:
        """True once ``limit`` rows have been queued."""
        return self.limit is not None and self._end >= self.limit

    @property
    def rows(self) -> int:
        """Rows queued so far (lost ones included)."""
        return self._end

    def add(self, frame: Frame) -> None:
        """Queue one decoded frame (never blocks; a frame the writer has no room for is lost, and counted)."""
        if self.error is not None or self.done:
            return
        samples = frame.samples
        if samples.shape[1] != self.channels:
            self.channel_errors += 1
            log.warning("frame at %d has %d channels, expected %d: skipped", frame.index, samples.shape[1], self.channels)
            return
        if self.first_index is None:
            self.first_index = frame.index
        self.restarts += frame.restart
        position = frame.index - self.first_index
        if self.limit is not None:
            samples = samples[: max(0, self.limit - position)]
        if not samples.shape[0]:
            return
        try:
            self._queue.put_nowait((position, samples))
        except queue.Full:
            self.queue_dropped += samples.shape[0]
            return
        self._end = position + samples.shape[0]

    def _run(self) -> None:
        pending: list[npt.NDArray[np.int16]] = []
        lost: list[tuple[int, int]] = []
        start = end = nbytes = 0
        opened = 0.0
        while True:
            timeout = None if not pending and not lost else max(0.0, opened + self._commit_s - time.monotonic())
            try:
                item: object = self._queue.get(timeout=timeout)
            except queue.Empty:
                item = _TICK
            if self.error is not None:
                if item is None:
                    return
                continue
            if isinstance(item, tuple):
                position, samples = item
                if position < end:  # never happens with the decoder's indices; keep positions increasing anyway
                    samples, position = samples[end - position:], end
                if samples.shape[0]:
                    if not pending and not lost:
                        opened = time.monotonic()
                    if position > end:
                        lost.append((end, position - end))
                    pending.append(samples)
                    nbytes += samples.nbytes
                    end = position + samples.shape[0]
            due = item is None or time.monotonic() >= opened + self._commit_s or end - start >= self._commit_rows or nbytes >= MAX_CHUNK_BYTES
            if end > start and due:
                received = np.concatenate(pending) if pending else np.zeros((0, self.channels), dtype=np.int16)
                counters = {**self._counters(), "restarts": self.restarts, "channel_errors": self.channel_errors,
                            "samples_dropped_writer_behind": self.queue_dropped}
                assert self.first_index is not None
                chunk = encode_chunk(start, self.first_index + start, end - start, lost, counters, received)
                try:
                    self._writer.append(chunk)
                except OSError as exc:
                    self.error = (f"{self.journal}: {exc.strerror or exc}: capture stopped after {self._rows / self.fs:.3f} s, "
                                  f"kept in the journal: tactiled recover {self.journal} -o {self.out}")
                    if self._on_error is not None:
                        self._on_error(self.error)
                    pending, lost = [], []
                    if item is None:
                        return
                    continue
                self._rows = end
                self._lost += sum(n for _, n in lost)
                start, pending, lost, nbytes = end, [], [], 0
            if item is None:
                return

    def finish(self, extra_meta: dict[str, Any] | None = None) -> SinkResult:
        """Commit what is queued, then write ``out`` from the journal and remove the journal.

        On a write error (now or before) the journal is kept and :attr:`SinkResult.error` says how to recover it.
        """
        self._queue.put(None)
        self._thread.join()
        self._writer.close()
        if self.error is not None:
            return SinkResult(self._rows, self._lost, self.error)
        try:
            recover(self.journal, self.out, extra_meta, allow_empty=True)
        except OSError as exc:
            return SinkResult(self._rows, self._lost, f"{self.out}: cannot write: {exc.strerror or exc}; the capture is kept in "
                                                      f"{self.journal}: tactiled recover {self.journal} -o {self.out}")
        os.unlink(self.journal)
        fsync_dir(self.journal.parent)
        return SinkResult(self._rows, self._lost)


@dataclass
class RecordSummary:
    seconds: float
    samples: int
    samples_lost: int
    crc_errors: int
    reconnects: int
    error: str | None = None  # the capture stopped on a write error (the journal keeps what was written)

    def line(self) -> str:
        return (f"recorded {self.seconds:.3f} s: {self.samples} samples, {self.samples_lost} lost, "
                f"{self.crc_errors} CRC failures, {self.reconnects} reconnects")


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def record(port: str, seconds: float, out: str | Path, *, fs: float, channels: int, volts_per_count: float,
           label: str | None = None, baudrate: int = 1_000_000, retry_max_s: float = 2.0,
           meta: dict[str, Any] | None = None, force: bool = False) -> RecordSummary:
    """Record ``seconds`` of sensor time from ``port`` into ``out``; SIGINT, SIGTERM or SIGHUP stops early and saves.

    The port and the output path are checked first (:class:`~tactiled.errors.DeviceError`,
    :class:`~tactiled.errors.OutputError`); a write error during the capture stops it and is returned in
    :attr:`RecordSummary.error`, the journal keeping what was written.
    """
    check_port(port)
    chunks: queue.Queue[bytes | None] = queue.Queue()
    decoder = FrameDecoder()
    source: SerialSource | None = None

    def counters() -> dict[str, int]:
        return {"crc_errors": decoder.stats.crc_errors, "bytes_discarded": decoder.stats.bytes_discarded,
                "reconnects": source.reconnects if source else 0}

    sink = RecordingSink(out, fs=fs, channels=channels, volts_per_count=volts_per_count, label=label,
                         meta={**(meta or {}), "port": port}, limit=max(1, round(seconds * fs)), force=force, counters=counters)

    def on_state(state: str, detail: str) -> None:
        if state == DISCONNECTED:
            log.warning("%s: %s", port, detail)

    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in STOP_SIGNALS}  # a flag: never interrupts a write
    source = SerialSource(port, chunks.put, on_state, baudrate=baudrate, retry_max_s=retry_max_s)
    source.start()
    log.info("recording %s -> %s (Ctrl-C stops and saves)", port, out)
    try:
        while not sink.done and sink.error is None and not stop.is_set():
            try:
                data = chunks.get(timeout=0.1)  # the stop flag's polling period
            except queue.Empty:
                continue
            for frame in decoder.feed(data or b""):
                sink.add(frame)
        if stop.is_set():
            log.info("stopped by a signal: saving what was captured")
    finally:
        source.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    while not chunks.empty():
        for frame in decoder.feed(chunks.get_nowait() or b""):
            sink.add(frame)
    for frame in decoder.flush():
        sink.add(frame)
    result = sink.finish(counters())
    return RecordSummary(result.samples / fs, result.samples, result.samples_lost, decoder.stats.crc_errors, source.reconnects, result.error)
