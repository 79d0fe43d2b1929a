"""The recording journal: the append-only form a recorder streams to disk (docs/recordings.md, "The journal").

A journal is a header then chunks, each self-delimiting and guarded by a CRC-32::

    header  b"TACTJNL\\x01" | u32 n | n bytes of JSON (fs, channels, volts_per_count, label, meta) | u32 CRC-32
    chunk   b"TJCK" | u32 n | body (n bytes) | u32 CRC-32 of everything before it in the chunk
    body    i64 position | i64 index | i64 rows | u32 g | u32 s | g x (i64 position, i64 count) lost ranges
            | s bytes of JSON (counters) | (rows - lost) x C int16 little-endian samples

All integers little-endian. A chunk covers the rows ``position .. position + rows`` of the recording; its lost
ranges (absolute positions) are not stored, its samples are the other rows in order. The counters JSON may hold
:data:`DISCONNECTED_KEY`: the positions (absolute, in ``position .. position + rows``, ends included) where the host lost
the sensor's port, the recording's ``disconnected`` key; a chunk of no rows carries only such marks. :class:`JournalWriter`
appends whole chunks and fsyncs each; :func:`read_journal` checks every chunk and drops the ones that fail
(a torn last chunk after a kill or a power cut), in time linear in the journal's size, and :func:`recover` turns a
journal into a normal recording without holding the samples in memory. A journal whose chunks declare more lost rows
than its size can justify (:func:`~tactiled.files.recording.lost_rows_budget`) is refused before anything is written.
"""

from __future__ import annotations

import binascii
import json
import mmap
import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
import numpy.typing as npt

from tactiled.board.frames import MAX_CHANNELS
from tactiled.errors import RecordingError
from tactiled.files.npzio import MAX_FILE_BYTES, load_json_bounded
from tactiled.files.recording import (
    MAX_FS,
    MIN_FS,
    Recording,
    StreamedArray,
    first_index_problem,
    fsync_dir,
    largest_magnitude,
    lost_rows_budget,
    peak_problem,
    save_recording,
    surface_name_problem,
    validate_arrays,
    volts_per_count_problem,
)
from tactiled.readable import file_problem

MAGIC = b"TACTJNL\x01"
CHUNK_MAGIC = b"TJCK"
VERSION = 1
MAX_HEADER_BYTES = 2 << 20  # JSON header: meta is at most 1 MB (docs/recordings.md)
MAX_CHUNK_BYTES = 64 << 20  # far above what a writer makes (0.5 s or 4 MiB of samples): anything longer is corrupt
SUFFIX = ".journal"
_u32 = struct.Struct("<I")
_body = struct.Struct("<qqqII")
_range = struct.Struct("<qq")
ZERO_BLOCK = 1 << 16  # rows of zeros written at a time for lost rows
MAX_JOURNAL_BYTES = MAX_FILE_BYTES  # a journal is streamed, never held: the limit of every tactiled file
MIN_LOST_ROWS = 1 << 24  # lost rows recover writes for any journal (14 min at 20 kHz); more only for a journal of more bytes
DISCONNECTED_KEY = "disconnected"  # in a chunk's counters JSON: the positions where the port was lost (not a counter: never in meta)


def journal_path(out: str | Path) -> Path:
    """Where a recorder writing ``out`` keeps its journal: ``out`` + ``.journal``."""
    return Path(f"{out}{SUFFIX}")


def encode_header(fs: float, channels: int, volts_per_count: float, label: str | None, meta: dict[str, Any]) -> bytes:
    """The journal's header bytes."""
    text = json.dumps({"format": "tactiled-journal", "version": VERSION, "fs": fs, "channels": channels,
                       "volts_per_count": volts_per_count, "label": label, "meta": meta}, sort_keys=True).encode()
    head = MAGIC + _u32.pack(len(text)) + text
    return head + _u32.pack(binascii.crc32(head))


def encode_chunk(position: int, index: int, rows: int, lost: list[tuple[int, int]], counters: dict[str, int],
                 samples: npt.NDArray[np.int16], disconnected: list[int] | None = None) -> bytes:
    """One chunk: rows ``position .. position + rows``; ``samples`` (rows - lost, C) are the rows not in ``lost``;
    ``disconnected``: increasing positions in ``position .. position + rows`` where the port was lost (none: not written)."""
    text = json.dumps({**counters, DISCONNECTED_KEY: disconnected} if disconnected else counters, sort_keys=True).encode()
    body = (_body.pack(position, index, rows, len(lost), len(text)) + b"".join(_range.pack(p, c) for p, c in lost) + text
            + np.ascontiguousarray(samples, dtype="<i2").tobytes())
    head = CHUNK_MAGIC + _u32.pack(len(body)) + body
    return head + _u32.pack(binascii.crc32(head))


class JournalWriter:
    """Appends chunks to a new journal file; each :meth:`append` is written whole and fsynced before it returns.

    The file is created exclusively (an existing journal is never overwritten) and locked (``flock``) while open,
    so another recorder cannot claim it. A failed append (a full disk) truncates the file back to its last
    complete chunk and raises the ``OSError``: the journal stays recoverable.
    """

    def __init__(self, path: str | Path, header: bytes) -> None:
        import fcntl

        self.path = Path(path)
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666)
        fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        self.size = 0
        self.chunks = 0
        try:
            self._write(header)
            fsync_dir(self.path.parent)  # the journal's name survives a power cut too
        except OSError:
            self.close()
            os.unlink(self.path)
            raise
        self.size = len(header)

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self._fd, view):]
        os.fsync(self._fd)

    def append(self, chunk: bytes) -> None:
        """Write ``chunk`` and fsync; on ``OSError`` cut the file back to the last whole chunk, then raise."""
        try:
            self._write(chunk)
        except OSError:
            os.ftruncate(self._fd, self.size)  # never grows the file: works on a full disk
            raise
        self.size += len(chunk)
        self.chunks += 1

    def close(self) -> None:
        """Close the file, releasing its lock; closing again does nothing."""
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


def is_locked(path: str | Path) -> bool:
    """True if a live writer holds ``path`` (its ``flock``). Opened without blocking: a FIFO there (nothing a recorder writes)
    would otherwise wait for a writer for ever."""
    import fcntl

    fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC | os.O_NONBLOCK)
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
    return False


@dataclass
class Chunk:
    """One intact chunk: where its samples lie in the file and which rows it covers."""

    position: int
    index: int
    rows: int
    lost: list[tuple[int, int]]
    counters: dict[str, int]
    offset: int  # of the samples in the file
    stored: int  # rows stored (rows - lost)
    disconnected: list[int] = field(default_factory=list)  # positions where the port was lost, increasing, inside the chunk


@dataclass
class JournalScan:
    """What :func:`read_journal` found: the header, the intact chunks in order, and what it dropped."""

    path: Path
    fs: float
    channels: int
    volts_per_count: float
    label: str | None
    meta: dict[str, Any]
    chunks: list[Chunk] = field(default_factory=list)
    dropped_chunks: int = 0  # chunks that failed their length or CRC check, or overlapped an earlier one
    dropped_bytes: int = 0  # bytes not in an intact chunk (a torn last chunk, garbage, a tail of zeros)
    size: int = 0

    @property
    def rows(self) -> int:
        """Rows from position 0 to the last intact chunk's end, lost rows included (0 without chunks)."""
        return self.chunks[-1].position + self.chunks[-1].rows if self.chunks else 0

    @property
    def first_index(self) -> int:
        """Sensor sample index of row 0 (0 without chunks)."""
        return self.chunks[0].index - self.chunks[0].position if self.chunks else 0

    def lost(self) -> npt.NDArray[np.int64]:
        """(g, 2) lost ranges (position, count): the chunks' own and the rows no intact chunk covers, merged."""
        ranges: list[list[int]] = []
        end = 0
        for c in self.chunks:
            for p, n in [(end, c.position - end), *c.lost]:
                if n <= 0:
                    continue
                if ranges and ranges[-1][0] + ranges[-1][1] == p:
                    ranges[-1][1] += n
                else:
                    ranges.append([p, n])
            end = c.position + c.rows
        return np.asarray(ranges, dtype=np.int64).reshape(-1, 2)

    def disconnected(self) -> npt.NDArray[np.int64]:
        """(d,) positions where the port was lost: the chunks' marks in order, each position once (the recording's key)."""
        marks = [p for c in self.chunks for p in c.disconnected]
        return np.unique(np.asarray(marks, dtype=np.int64))

    def blocks(self) -> Iterator[npt.NDArray[np.int16]]:
        """All rows in order, lost ones as zeros, a chunk's worth at a time (bounded memory)."""
        zeros = np.zeros((ZERO_BLOCK, self.channels), dtype="<i2")
        end = 0
        with open(self.path, "rb") as fh:
            for c in self.chunks:
                yield from _zero_rows(zeros, c.position - end)
                fh.seek(c.offset)
                stored = np.frombuffer(_read_exact(fh, 2 * self.channels * c.stored), dtype="<i2").reshape(c.stored, self.channels)
                at = c.position
                taken = 0
                for p, n in c.lost:
                    yield stored[taken:taken + p - at]
                    taken += p - at
                    yield from _zero_rows(zeros, n)
                    at = p + n
                yield stored[taken:]
                end = c.position + c.rows


def _zero_rows(zeros: npt.NDArray[np.int16], n: int) -> Iterator[npt.NDArray[np.int16]]:
    while n > 0:
        yield zeros[:n]
        n -= min(n, zeros.shape[0])


def _read_exact(fh: IO[bytes], n: int) -> bytes:
    data = fh.read(n)
    if len(data) != n:
        raise RecordingError(f"{getattr(fh, 'name', '?')}: changed while being read")
    return data


def _header(path: Path, fh: IO[bytes]) -> dict[str, Any]:
    head = fh.read(len(MAGIC) + 4)
    if len(head) < len(MAGIC) + 4 or not head.startswith(MAGIC):
        raise RecordingError(f"{path}: not a tactiled journal (no {MAGIC[:7].decode()} header)")
    (n,) = _u32.unpack_from(head, len(MAGIC))
    if n > MAX_HEADER_BYTES:
        raise RecordingError(f"{path}: header: {n} bytes, more than {MAX_HEADER_BYTES}")
    text = fh.read(n)
    crc = fh.read(4)
    if len(text) != n or len(crc) != 4 or binascii.crc32(head + text) != _u32.unpack(crc)[0]:
        raise RecordingError(f"{path}: header: torn or corrupt (CRC-32 mismatch)")
    try:  # the same bounds as a recording's meta, so what recovers also loads
        obj = load_json_bounded(text.decode(), "header")
    except ValueError as exc:  # not UTF-8, too large, too deep, or not JSON
        raise RecordingError(f"{path}: {exc}") from None
    if not isinstance(obj, dict) or obj.get("format") != "tactiled-journal" or obj.get("version") != VERSION:
        raise RecordingError(f"{path}: header: not a version {VERSION} tactiled journal")
    return obj


def _header_values(path: Path, h: dict[str, Any]) -> tuple[float, int, float]:
    """(fs in Hz, channels, volts_per_count) of the journal header ``h``, each checked as a recording's is: a JSON number
    (not a boolean, and channels an integer, not 2.9) in range; :class:`RecordingError` names ``path`` and the key."""
    for key in ("fs", "channels", "volts_per_count"):
        if key not in h:
            raise RecordingError(f"{path}: header: {key}: missing (required)")
        value = h[key]
        if isinstance(value, bool) or not isinstance(value, int if key == "channels" else (int, float)):
            raise RecordingError(f"{path}: header: {key}: must be {'an integer' if key == 'channels' else 'a number'}, got {json.dumps(value):.80}")
    fs, channels, vpc = float(h["fs"]), int(h["channels"]), float(h["volts_per_count"])
    if not (np.isfinite(fs) and MIN_FS <= fs <= MAX_FS):
        raise RecordingError(f"{path}: header: fs: must be in [{MIN_FS:g}, {MAX_FS:g}] Hz, got {fs}")
    if not 1 <= channels <= MAX_CHANNELS:
        raise RecordingError(f"{path}: header: channels: must be in [1, {MAX_CHANNELS}], got {channels}")
    if problem := volts_per_count_problem(vpc):
        raise RecordingError(f"{path}: header: volts_per_count: {problem}")
    return fs, channels, vpc


def read_journal(path: str | Path) -> JournalScan:
    """Check every chunk of the journal at ``path``; intact ones are kept, the others counted as dropped.

    A chunk that fails its length or CRC check is skipped and the next chunk marker is looked for after it, so
    one damaged chunk costs only its own rows (listed as lost). Raises :class:`RecordingError` for a missing
    file, one that is not a regular file of at most :data:`MAX_JOURNAL_BYTES`, or a bad header.
    """
    path = Path(path)
    problem = file_problem(path, MAX_JOURNAL_BYTES)
    if problem is not None:
        raise RecordingError(f"{path}: {problem}")
    try:
        fh = open(path, "rb")  # noqa: SIM115 (closed below)
    except OSError as exc:
        raise RecordingError(f"{path}: {exc.strerror}") from None
    with fh:
        h = _header(path, fh)
        fs, channels, vpc = _header_values(path, h)
        label, meta = h.get("label"), h.get("meta") or {}
        if not isinstance(meta, dict):
            raise RecordingError(f"{path}: header: meta: must be a JSON object")
        problem = None if label is None else surface_name_problem(str(label))
        if problem:  # what recovers must load
            raise RecordingError(f"{path}: header: label: {problem}")
        scan = JournalScan(path, fs, channels, vpc, None if label is None else str(label), meta, size=os.fstat(fh.fileno()).st_size)
        start = fh.tell()
        if start < scan.size:
            with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as data:
                _scan_chunks(scan, data, start)
    return scan


def _scan_chunks(scan: JournalScan, data: mmap.mmap, pos: int) -> None:
    """Every chunk of ``data`` from ``pos`` into ``scan``, in time linear in the bytes of any journal a recorder wrote (each
    byte CRC-checked once; in a hostile file, the chunks that would end in its zero tail may be checked more).

    An intact chunk is kept (if it does not overlap the ones before) and skipped whole. A marker whose declared length
    ends on the next marker or at the end of the file frames a chunk even if its CRC fails (damaged inside): it is
    dropped and skipped whole. A chunk that ends where only zeros follow (a power cut leaves them after the last write),
    or the file's last marker's whatever follows it, is kept if intact, where that tail made it a damaged one; if not
    intact it is not trusted. Any other marker is not trusted: the next marker is looked for one byte on.
    """
    size = len(data)
    zeros = _zeros_from(data, pos)  # where the zeros that end the file begin (size: none)
    last = data.rfind(CHUNK_MAGIC, pos)  # the file's last marker that declares a chunk in range (not "TJCK" in samples)
    while last >= pos and _declared_at(data, last) is None:
        last = data.rfind(CHUNK_MAGIC, pos, last + 3)
    while pos < size:
        n = _declared_at(data, pos)
        end = pos + 8 + (n or 0) + 4
        framed = n is not None and (end == size or data[end:end + 4] == CHUNK_MAGIC)  # damaged or not, skipped whole
        if n is not None and (framed or pos == last or end >= zeros):  # a tail chunk is kept only if intact
            chunk = _chunk_at(data, pos, n, scan.channels)
            if chunk is not None and chunk.position >= scan.rows:
                scan.chunks.append(chunk)
                pos = end
                continue
        nxt = end if framed else data.find(CHUNK_MAGIC, pos + 1)
        scan.dropped_bytes += (nxt if nxt >= 0 else size) - pos
        if nxt < 0 and pos >= zeros:  # zeros to the end: never written (a power cut), no chunk lost
            break
        scan.dropped_chunks += 1
        if nxt < 0:
            break
        pos = nxt


def _zeros_from(data: mmap.mmap, start: int, step: int = 1 << 16) -> int:
    """Where the run of zero bytes that ends ``data`` begins, at ``start`` at the earliest (``len(data)``: it ends in another
    byte). Reads back from the end, ``step`` bytes at a time."""
    stop = len(data)
    while stop > start:
        lo = max(start, stop - step)
        kept = data[lo:stop].rstrip(b"\0")
        if kept:
            return lo + len(kept)
        stop = lo
    return start


def _declared_at(data: mmap.mmap, pos: int) -> int | None:
    """The body length the chunk marker at ``pos`` declares, if there is a marker and its chunk fits in ``data``."""
    if data[pos:pos + 4] != CHUNK_MAGIC or pos + 8 > len(data):
        return None
    (n,) = _u32.unpack_from(data, pos + 4)
    return n if _body.size <= n <= MAX_CHUNK_BYTES and pos + 8 + n + 4 <= len(data) else None


def _chunk_at(data: mmap.mmap, pos: int, n: int, channels: int) -> Chunk | None:
    """The intact chunk of body length ``n`` at ``pos``, or None (CRC or structure wrong)."""
    body = data[pos + 8:pos + 8 + n]
    if binascii.crc32(body, binascii.crc32(data[pos:pos + 8])) != _u32.unpack_from(data, pos + 8 + n)[0]:
        return None
    position, index, rows, g, s = _body.unpack_from(body)
    at = _body.size + 16 * g
    if at + s > n:  # more lost ranges or counters than the chunk holds
        return None
    lost = [_range.unpack_from(body, _body.size + 16 * i) for i in range(g)]
    try:
        counters = json.loads(body[at:at + s])
    except (ValueError, RecursionError):
        return None
    stored = rows - sum(c for _, c in lost)
    end = position
    for p, c in lost:  # inside the chunk, in order, not overlapping
        if p < end or c <= 0 or p + c > position + rows:
            return None
        end = p + c
    if position < 0 or stored < 0 or n - at - s != 2 * channels * stored or not isinstance(counters, dict):
        return None
    marks = counters.pop(DISCONNECTED_KEY, [])
    if not (isinstance(marks, list) and all(type(p) is int and position <= p <= position + rows for p in marks)
            and marks == sorted(marks)):
        return None
    return Chunk(position, index, rows, lost, counters, pos + 8 + at + s, stored, marks)


@dataclass
class Recovered:
    """What :func:`recover` wrote and dropped."""

    samples: int
    samples_lost: int
    chunks: int
    dropped_chunks: int
    dropped_bytes: int
    fs: float

    def line(self) -> str:
        """One line for the user: samples recovered (seconds, lost), chunks, and what was dropped."""
        dropped = (f"dropped {self.dropped_chunks} damaged or torn chunk(s), {self.dropped_bytes} bytes" if self.dropped_chunks
                   else f"nothing dropped but {self.dropped_bytes} zero bytes after the last "
                        + ("chunk" if self.chunks else "header") if self.dropped_bytes
                   else "nothing dropped")
        return (f"recovered {self.samples} samples ({self.samples / self.fs:.3f} s, {self.samples_lost} lost) "
                f"from {self.chunks} chunks; {dropped}")


def recover(journal: str | Path, out: str | Path, extra_meta: dict[str, Any] | None = None, allow_empty: bool = False) -> Recovered:
    """Write the recording held by ``journal`` to ``out`` (.npz, docs/recordings.md), streaming the samples.

    The recording's ``meta`` is the header's plus the last intact chunk's counters and ``extra_meta``; its ``disconnected``
    the marks of the intact chunks.
    Raises :class:`RecordingError` if the journal has no intact chunk (unless ``allow_empty``: a recording of
    no samples, what a recorder stopped before the first frame writes), or if a live recorder holds it (its lock).
    """
    try:
        locked = is_locked(journal)
    except OSError:  # missing or unreadable: read_journal says which, in its own words
        locked = False
    if locked:  # what it holds so far is not the recording, and removing it (as after a recovery) loses the recorder's
        raise RecordingError(f"{journal}: in use by a running recorder (it holds the journal's lock), which writes its recording "
                             "itself when it stops; nothing written")
    scan = read_journal(journal)
    implied = scan.rows - sum(c.stored for c in scan.chunks)
    budget = lost_rows_budget(scan.size, MIN_LOST_ROWS)
    if implied > budget:
        raise RecordingError(f"{journal}: declares {scan.rows} rows, {implied} of them lost, in {scan.size} bytes: more than the {budget} lost "
                             f"rows a journal of that size may imply (one per byte, at least {MIN_LOST_ROWS}); nothing written")
    if not scan.chunks and not allow_empty:
        raise RecordingError(f"{journal}: no intact chunk: nothing to recover"
                             + (f" ({scan.dropped_bytes} bytes dropped)" if scan.dropped_bytes else ""))
    meta = {**scan.meta, **(scan.chunks[-1].counters if scan.chunks else {}), **(extra_meta or {})}
    rec = _checked(scan, meta)
    save_recording(out, rec, StreamedArray((scan.rows, scan.channels), np.dtype("<i2"), _peak_checked(scan)))
    return Recovered(scan.rows, int(rec.lost[:, 1].sum()), len(scan.chunks), scan.dropped_chunks, scan.dropped_bytes, scan.fs)


def _checked(scan: JournalScan, meta: dict[str, Any]) -> Recording:
    """The recording ``scan`` makes with ``meta``, but for its samples (a (0, C) int16 placeholder), checked by
    :func:`~tactiled.files.recording.validate_arrays` as loading the file would check it, so recover never writes what
    load refuses; :class:`RecordingError` names the journal. The samples' magnitude is checked as they are written
    (:func:`_peak_checked`). Raises before anything is written."""
    if problem := first_index_problem(scan.first_index, scan.rows):
        raise RecordingError(f"{scan.path}: first_index (a chunk's index less its position): {problem}; nothing written")
    # every row, as zeros of no memory (a stride of 0): the checks of lost, disconnected against the rows; not the values
    rows = np.lib.stride_tricks.as_strided(np.zeros(scan.channels, dtype=np.int16), (scan.rows, scan.channels), (0, 2))
    arrays: dict[str, Any] = {"samples": rows, "fs": np.float64(scan.fs), "volts_per_count": np.float64(scan.volts_per_count),
                              "first_index": np.int64(scan.first_index), "lost": scan.lost(), "disconnected": scan.disconnected(),
                              "meta": np.str_(json.dumps(meta, sort_keys=True))}
    if scan.label is not None:
        arrays["label"] = np.str_(scan.label)
    try:
        rec = validate_arrays(scan.path, arrays)
    except RecordingError as exc:
        raise RecordingError(f"{exc}; nothing written") from None
    rec.samples = np.zeros((0, scan.channels), dtype=np.int16)
    return rec


def _peak_checked(scan: JournalScan) -> Iterator[npt.NDArray[np.int16]]:
    """``scan``'s blocks, each checked against the volts a recording may reach (counts x volts_per_count at most
    :data:`~tactiled.files.recording.MAX_VOLTS`): a :class:`RecordingError` naming the journal stops the write, which then
    leaves nothing (:func:`~tactiled.files.recording.atomic_savez`)."""
    for block in scan.blocks():
        if block.size and (problem := peak_problem(largest_magnitude(block) * scan.volts_per_count)):
            raise RecordingError(f"{scan.path}: samples: {problem}; nothing written")
        yield block
