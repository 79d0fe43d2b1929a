"""``tactiled record``: serial frames → a recording file, with every lost sample listed, streamed to disk.

:class:`RecordingSink` (used by ``record`` and ``run --record``) writes the samples to a journal beside the output
(tactiled/files/journal.py) as they come, committed (written and fsynced) every :data:`COMMIT_S` of wall time by a
writer thread, so the caller never waits on the disk. Memory stays bounded. On a clean stop the journal becomes
the ``.npz`` and is removed; after a kill or a power cut ``tactiled recover`` turns it into the ``.npz``.
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

from tactiled.board.clockmap import rate_mismatch
from tactiled.board.frames import DecoderStats, Frame
from tactiled.board.serialsource import DISCONNECTED, ByteSource, SerialSource, check_port
from tactiled.config import Config
from tactiled.errors import OutputError
from tactiled.files.journal import MIN_LOST_ROWS, JournalWriter, encode_chunk, encode_header, is_locked, journal_path, recover
from tactiled.files.outputs import check_output
from tactiled.files.recording import check_label_option, fsync_dir, lost_rows_budget
from tactiled.run.ingest import Batch
from tactiled.run.stream import Stream
from tactiled.signals import STOP_SIGNALS

log = logging.getLogger(__name__)

COMMIT_S = 0.5  # the commit period, s of wall time: about what a kill or a power cut can lose
MAX_CHUNK_BYTES = 4 << 20  # a chunk is committed at this size at the latest
SILENT_AFTER_S = 5.0  # record says once that the port has given nothing to record for this long (host time) from the start
GIVE_UP_AFTER_S = 30.0  # ... and stops (no file, exit 1) when it has given nothing by --seconds plus this long (host time)
RATE_AFTER_S = 5.0  # the recorder measures the board's sample rate over this long from its first samples (rate_mismatch)
RATE_MIN_S = 1.0  # ... or, a recording that ends sooner, over what it had when it ends, if at least this long
QUEUE_BYTES = 64 << 20  # samples waiting for the writer (a disk stalled 13 min at 20 kHz x 2 channels); beyond, frames are lost, counted


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

    :meth:`add` only queues the frame (cheap: a lock and an append; never blocks); every :data:`COMMIT_S` a
    writer thread takes what is queued, places each frame at its position (``frame.index`` - the first frame's
    index: gaps become lost ranges, never stored) and commits it as chunks of at most ``commit_s`` of sensor
    time. With ``limit``, rows from position ``limit`` on are ignored and :attr:`done` turns True (also when a gap
    crosses the limit: the recording then ends at its last row received). A write error
    (a full disk) stops the writing: :attr:`error` says so in one line, the journal keeps every chunk committed
    before, ``on_error`` is called with the line.

    A gap is a lost range (two numbers in the journal, zero rows in the ``.npz``), however long, as long as the
    recording can hold it: the lost rows of a recording may not exceed what ``tactiled recover`` writes for a journal
    of its size (:func:`~tactiled.files.recording.lost_rows_budget`: one per byte stored, at least
    :data:`~tactiled.files.journal.MIN_LOST_ROWS`, 14 min at 20 kHz). A gap beyond that (a 2**31 jump from a hostile
    or broken board) ends the recording before it, never spliced and never written as gigabytes of zeros:
    :attr:`done` turns True, :attr:`ended_by_gap` holds the gap (also in the recording's ``meta``), and a warning
    says so.

    :meth:`mark_disconnected` marks where the host lost the sensor's port (the recording's ``disconnected`` key), in
    order with the rows, through the journal.
    """

    def __init__(self, out: str | Path, *, fs: float, channels: int, volts_per_count: float, label: str | None = None,
                 meta: dict[str, Any] | None = None, limit: int | None = None, force: bool = False,
                 counters: Callable[[], dict[str, int]] | None = None, on_error: Callable[[str], None] | None = None,
                 commit_s: float = COMMIT_S) -> None:
        check_output(out, force)
        self.out = Path(out)
        self.force = force
        self.journal = claim_journal(out)
        self.channels = channels
        self.fs = fs
        self.limit = limit
        self.first_index: int | None = None
        self.restarts = 0
        self.channel_errors = 0
        self.queue_dropped = 0  # samples dropped because the writer fell behind (listed as lost)
        self.ended_by_gap = 0  # the gap (samples) that ended the recording: more lost rows than it may hold
        self._gaps = 0  # lost rows queued so far (gaps between the rows queued)
        self._stored = 0  # bytes of samples queued so far
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
        # (position, samples) the writer has not taken yet; samples None: the port was lost at that position
        self._batch: list[tuple[int, npt.NDArray[np.int16] | None]] = []
        self._marked = -1  # the position of the newest disconnection marked
        self._queued = 0  # their bytes (bounded by QUEUE_BYTES)
        self._lock = threading.Lock()
        self._finishing = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"journal:{self.journal.name}", daemon=True)
        self._thread.start()

    @property
    def done(self) -> bool:
        """True once ``limit`` rows have been queued, or a gap the recording cannot hold ended it."""
        return bool(self.ended_by_gap) or (self.limit is not None and self._end >= self.limit)

    def add(self, frame: Frame | Batch) -> None:
        """Queue one decoded frame or batch (never blocks; one the writer has no room for is lost, and counted)."""
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
            if position >= self.limit:  # a gap across the end: nothing more is recorded
                self._end = self.limit
                return
            samples = samples[: self.limit - position]
        if not samples.shape[0]:
            return
        gap = max(0, position - self._end)
        if gap and self._gaps + gap > lost_rows_budget(self._stored, MIN_LOST_ROWS):
            self.ended_by_gap = gap
            log.warning("%s: the index jumped %d samples (%.1f s) ahead at row %d: more lost rows than a recording of %d rows may hold; "
                        "the recording ends there (the gap is counted)", self.out, gap, gap / self.fs, self._end, self._end)
            return
        with self._lock:
            if self._queued + samples.nbytes > QUEUE_BYTES:
                self.queue_dropped += samples.shape[0]
                return
            self._queued += samples.nbytes
            self._batch.append((position, samples))
        self._end = position + samples.shape[0]
        self._gaps += gap
        self._stored += samples.nbytes

    def mark_disconnected(self) -> None:
        """The host lost the sensor's port after the rows added so far: their end is marked (the recording's ``disconnected``
        key), in order with the rows. Nothing is marked before the first row (nothing to end), once the recording is done or
        failed, or twice at one position (two reports with no row between)."""
        if self.error is not None or self.done or self.first_index is None or self._end == self._marked:
            return
        self._marked = self._end
        with self._lock:
            self._batch.append((self._end, None))

    def _run(self) -> None:
        start = end = 0  # the next chunk's first row; the row after the newest placed
        pending: list[npt.NDArray[np.int16]] = []
        lost: list[tuple[int, int]] = []
        marks: list[int] = []  # disconnections at positions start .. end
        nbytes = 0
        final = False
        while not final and self.error is None:
            final = self._finishing.wait(self._commit_s)  # the commit period (wall time), not synchronisation
            with self._lock:
                batch, self._batch, self._queued = self._batch, [], 0
            for position, samples in batch:  # positions increase (the decoder's indices); add() keeps no empty rows
                if samples is None:  # a disconnection after the rows placed (position == end)
                    marks.append(position)
                    continue
                if position > end:
                    lost.append((end, position - end))
                pending.append(samples)
                nbytes += samples.nbytes
                end = position + samples.shape[0]
                if end - start >= self._commit_rows or nbytes >= MAX_CHUNK_BYTES:  # bounded chunks, even after a burst
                    start = self._commit(start, end, pending, lost, marks)
                    pending, lost, marks, nbytes = [], [], [], 0
            if end > start or marks:  # marks after the last chunk: a chunk of no rows carries them
                start = self._commit(start, end, pending, lost, marks)
                pending, lost, marks, nbytes = [], [], [], 0

    def _commit(self, start: int, end: int, pending: list[npt.NDArray[np.int16]], lost: list[tuple[int, int]], marks: list[int]) -> int:
        """Append rows ``start .. end`` (and the disconnections ``marks`` there) as one chunk; returns where the next chunk
        starts (``end``, or ``start`` after an error)."""
        if self.error is not None:
            return start
        # a chunk of rows ends on a row received; one of no rows only carries marks
        received = np.concatenate(pending) if pending else np.zeros((0, self.channels), dtype=np.int16)
        given = self._counters()
        counters = {**given, "restarts": self.restarts, "channel_errors": given.get("channel_errors", 0) + self.channel_errors,
                    "samples_dropped_writer_behind": self.queue_dropped}
        assert self.first_index is not None
        try:
            self._writer.append(encode_chunk(start, self.first_index + start, end - start, lost, counters, received, marks))
        except OSError as exc:
            kept = (f"kept in the journal: tactiled recover {self.journal} -o {self.out}" if os.path.lexists(self.journal)
                    else self._kept(self.out))
            self.error = f"{self.journal}: {exc.strerror or exc}: capture stopped after {self._rows / self.fs:.3f} s, {kept}"
            if self._on_error is not None:
                self._on_error(self.error)
            return start
        self._rows = end
        self._lost += sum(n for _, n in lost)
        return end

    def finish(self, extra_meta: dict[str, Any] | None = None) -> SinkResult:
        """Commit what is queued, then write ``out`` from the journal and remove the journal.

        ``out`` is checked again first (:func:`~tactiled.files.outputs.check_output`): a non-regular file is never written
        or replaced, and a file that appeared since the start only with ``force``.

        ``extra_meta`` (default: the ``counters`` callable's final values) is merged into the recording's meta.

        On a write error (now or before) the journal is kept and :attr:`SinkResult.error` says how to recover it.
        """
        self._finishing.set()
        self._thread.join()
        self._writer.close()
        if self.error is not None:
            return SinkResult(self._rows, self._lost, self.error)
        try:
            check_output(self.out, self.force)  # again: a file (or a device) may have appeared there since the start
        except OutputError as exc:
            return SinkResult(self._rows, self._lost, f"{exc}; {self._kept('OUT.npz')}")
        meta = self._counters() if extra_meta is None else extra_meta
        if self.ended_by_gap:
            meta = {**meta, "ended_by_gap": self.ended_by_gap}
        try:
            recover(self.journal, self.out, meta, allow_empty=True)
        except OSError as exc:
            return SinkResult(self._rows, self._lost, f"{self.out}: cannot write: {exc.strerror or exc}; {self._kept(self.out)}")
        os.unlink(self.journal)
        fsync_dir(self.journal.parent)
        return SinkResult(self._rows, self._lost)

    def _kept(self, out: str | Path) -> str:
        """Where the capture is after a failure, for the end of its one line: the journal and how to recover it into ``out``
        while the journal exists; else that it is lost (its folder removed while recording took the journal with it)."""
        if os.path.lexists(self.journal):
            return f"the capture is kept in {self.journal}: tactiled recover {self.journal} -o {out}"
        return f"the journal {self.journal} no longer exists (its folder was removed while recording?): the capture is lost"

    def discard(self) -> None:
        """End a sink that was given no row (:attr:`first_index` None): its writer stops, its journal (a header only) is
        removed, and ``out`` is neither written nor touched, so a file already there stays as it was."""
        assert self.first_index is None, "a sink with rows is finished (finish), never discarded"
        self._finishing.set()
        self._thread.join()
        self._writer.close()
        os.unlink(self.journal)
        fsync_dir(self.journal.parent)


@dataclass
class RecordSummary:
    """What :func:`record` did: seconds (of sensor time) and samples saved, samples lost, CRC failures, reconnects, and a write error;
    and, for a recording of no sample (nothing written: :meth:`nothing_line`), what the port gave instead."""

    seconds: float
    samples: int
    samples_lost: int
    crc_errors: int
    reconnects: int
    error: str | None = None  # the capture stopped on a write error (the journal keeps what was written)
    channel_errors: int = 0  # intact frames of another channel count, skipped
    port: str = ""
    wall_s: float = 0.0  # how long the port was read, s of host time
    seen: str = ""  # what the port gave when no sample was recorded (:func:`port_seen`)

    def line(self) -> str:
        """One line for the user: seconds, samples, lost, CRC failures and reconnects (and frames skipped for their channel count)."""
        skipped = f", {self.channel_errors} frames of another channel count skipped" if self.channel_errors else ""
        return (f"recorded {self.seconds:.3f} s: {self.samples} samples, {self.samples_lost} lost, "
                f"{self.crc_errors} CRC failures, {self.reconnects} reconnects{skipped}")

    def nothing_line(self, out: str | Path) -> str:
        """The one line of a recording of no sample (no file written): the port, how long it was read, what it gave."""
        return f"{out}: nothing recorded, no file written: {self.port}, read for {self.wall_s:.1f} s: {self.seen}"


def port_seen(bytes_read: int, stats: DecoderStats, channels: int, foreign: int = 0, discarded_at_start: int = 0) -> str:
    """What a port gave that held no sample to record, in a few words: no bytes, bytes with no valid sensor frame, or
    frames of another channel count (``foreign``, when known) than ``channels`` (sensor.channels)."""
    stale = f" ({discarded_at_start} stale bytes discarded at the open)" if discarded_at_start else ""
    if stats.channel_errors:
        board = f"the board sends {foreign} channels, " if foreign else ""
        return f"{stats.channel_errors} frames of another channel count skipped ({board}sensor.channels is {channels})"
    if not bytes_read:
        return f"no bytes{stale} (is the board on and streaming, and is this its port?)"
    failures = "".join(f", {n} {what}" for n, what in ((stats.crc_errors, "CRC failures"), (stats.bad_headers, "bad headers")) if n)
    return f"{bytes_read} bytes but no valid sensor frame{failures}{stale} (another device, or another baud rate than sensor.baudrate?)"


def link_counters(stats: DecoderStats, source: ByteSource | None) -> dict[str, int]:
    """What the serial link did, for a recording's ``meta``: CRC failures, bytes discarded, reconnects, foreign-channel frames,
    duplicated frames dropped, stale bytes dropped at the first open."""
    return {"crc_errors": stats.crc_errors, "bytes_discarded": stats.bytes_discarded, "reconnects": source.reconnects if source else 0,
            "channel_errors": stats.channel_errors, "duplicate_frames": stats.duplicates,
            "discarded_at_start": source.discarded_at_start if source else 0}



def record(config: Config, seconds: float, out: str | Path, *, label: str | None = None, force: bool = False) -> RecordSummary:
    """Record ``seconds`` of sensor time from ``config.sensor``'s port into ``out``; SIGINT, SIGTERM or SIGHUP stops early and saves.

    The bytes go through the daemon's ingest core (a :class:`~tactiled.run.stream.Stream` that decodes only): frames of
    another channel count are counted and skipped, and a forward jump of the index (an unplug, however long, as long as the
    board's counter can say how many) is a lost range of that length in the recording, never a splice: the rows after it
    keep their sensor time (``--seconds`` counts sensor time, the gap included). Only a board restart (the index back,
    not a repeated frame) continues the rows, and is counted in ``meta["restarts"]``. Each loss of the port is marked
    after the rows read before it (the recording's ``disconnected``), so a replay ends a slide there as the daemon does.

    The port and the output path are checked first (:class:`~tactiled.errors.DeviceError`,
    :class:`~tactiled.errors.OutputError`); a write error during the capture stops it and is returned in
    :attr:`RecordSummary.error`, the journal keeping what was written. Stop signals stay caught until the recording
    is saved, so a second Ctrl-C never leaves a half-written file.

    A port that gives no sample to record for :data:`SILENT_AFTER_S` of host time from the start (no bytes, bytes with no
    valid frame, frames of another channel count) is said once, naming the port and what it gave, and one that has given
    none by ``seconds`` + :data:`GIVE_UP_AFTER_S` stops the recording (a scripted session never hangs); a recording that ends
    with no sample is not written (a file already at ``out`` stays as it was): :attr:`RecordSummary.samples` is 0 and
    :meth:`RecordSummary.nothing_line` says what the port gave.
    """
    s = config.sensor
    check_label_option(label)  # else the file would not load (docs/recordings.md): said before the port opens
    check_port(s.port)
    # the reader thread's bytes with the time of the read that returned their last byte (host monotonic, s), in order with
    # None: the port was lost there
    chunks: queue.Queue[tuple[bytes, float] | None] = queue.Queue()
    stream = Stream(config, analyse=False)
    source: SerialSource | None = None

    def counters() -> dict[str, int]:
        return link_counters(stream.stats, source)

    sink = RecordingSink(out, fs=s.fs, channels=s.channels, volts_per_count=s.volts_per_count, label=label,
                         meta={"sensor": s.id, "port": s.port}, limit=max(1, round(seconds * s.fs)), force=force, counters=counters)

    def on_bytes(data: bytes) -> None:  # on the reader thread, where read_at is valid
        assert source is not None
        chunks.put((data, source.read_at(len(data) - 1)))

    def on_state(state: str, detail: str) -> None:  # on the reader thread: bytes read before may still be queued
        if state == DISCONNECTED:
            log.warning("%s: %s", s.port, detail)
            chunks.put(None)

    channels_said = rate_said = False  # each said once
    bytes_read = 0
    # the rate's start: when samples first came, the index's advance by then (samples and lost: an unplug or dropped frames
    # are not a slower board), and the restarts and reconnects by then (either begins the measurement again)
    first: tuple[float, int, tuple[int, int]] | None = None
    latest: tuple[float, int] | None = None  # the last (read time, index advance) since ``first``: a shorter recording's rate

    def take(item: tuple[bytes, float] | None) -> None:
        nonlocal channels_said, rate_said, first, latest, bytes_read
        if item is None:  # the port went away after the bytes taken so far: what the decoder holds goes in first
            for batch in stream.held():
                sink.add(batch)
            sink.mark_disconnected()
            return
        data, read_at = item
        bytes_read += len(data)
        for batch in stream.feed_bytes(data).batches:
            sink.add(batch)
        if stream.stats.channel_errors and not channels_said:  # nothing of such a board is recorded: say so at once, not at the end
            channels_said = True
            log.warning("%s", stream.ingest.decoder.channel_mismatch(s.id))
        if rate_said:
            return
        st = stream.stats
        # measured by when the bytes were read, not when they were taken off the queue (a lag would look like a rate)
        now, n, epoch = read_at, st.samples + st.samples_lost, (st.restarts, source.reconnects if source is not None else 0)
        if n and (first is None or first[2] != epoch):
            first, latest = (now, n, epoch), None
        elif first is not None:
            latest = (now, n)
        if first is not None and now - first[0] >= RATE_AFTER_S:  # sensor.fs is written into the recording
            say_rate(now, n)

    def say_rate(now: float, n: int) -> None:
        """The board's rate from ``first`` to (read time ``now``, index advance ``n``), said once if far from sensor.fs."""
        nonlocal rate_said
        assert first is not None
        rate_said = True
        line = rate_mismatch(s.id, (n - first[1]) / (now - first[0]), s.fs)
        if line:
            log.warning("%s", line)

    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in STOP_SIGNALS}  # a flag: never interrupts a write
    try:
        c = config.serial
        source = SerialSource(s.port, on_bytes, on_state, baudrate=s.baudrate, retry_initial_s=c.retry_initial_s, retry_max_s=c.retry_max_s,
                              read_interval_s=c.read_interval_s)
        source.start()
        started = time.monotonic()
        silent_said = False
        log.info("recording %s -> %s (Ctrl-C stops and saves)", s.port, out)
        try:
            while not sink.done and sink.error is None and not stop.is_set():
                waited = time.monotonic() - started
                if sink.first_index is None and waited >= seconds + GIVE_UP_AFTER_S:  # a script's record never hangs
                    log.warning("%s: nothing to record after %.0f s (--seconds %g and %.0f s more): stopping", s.port, waited, seconds,
                                GIVE_UP_AFTER_S)
                    break
                if not silent_said and sink.first_index is None and waited >= SILENT_AFTER_S:
                    silent_said = True  # once: a port that gives nothing to record is said, not waited on in silence
                    log.warning("%s: nothing to record after %.0f s: %s; still waiting, at most %.0f s more (Ctrl-C stops)", s.port,
                                SILENT_AFTER_S, port_seen(bytes_read, stream.stats, s.channels,
                                                          stream.ingest.decoder.foreign_channels or 0, source.discarded_at_start),
                                seconds + GIVE_UP_AFTER_S - waited)
                try:
                    item = chunks.get(timeout=0.1)  # the stop flag's polling period
                except queue.Empty:
                    continue
                take(item)
            if stop.is_set():
                log.info("stopped by a signal: saving what was captured")
        finally:
            source.stop()
        while not chunks.empty():
            take(chunks.get_nowait())
        for batch in stream.finish().batches:
            sink.add(batch)
        if not rate_said and first is not None and latest is not None and latest[0] - first[0] >= RATE_MIN_S:
            say_rate(*latest)  # a recording shorter than RATE_AFTER_S
        wall_s = time.monotonic() - started
        if sink.first_index is None and sink.error is None:  # not one sample: no file (an empty recording is no recording)
            sink.discard()
            result = SinkResult(0, 0)
        else:
            result = sink.finish()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    stats = stream.stats
    seen = "" if result.samples else port_seen(bytes_read, stats, s.channels, stream.ingest.decoder.foreign_channels or 0,
                                               source.discarded_at_start)
    return RecordSummary(result.samples / s.fs, result.samples, result.samples_lost, stats.crc_errors, source.reconnects, result.error,
                         stats.channel_errors, port=s.port, wall_s=wall_s, seen=seen)
