"""Session logs: what a subscriber received, on disk, and the files that replay like one.

The log format (``.tlog``; docs/messages.md, "Session logs") is a 16-byte header, ``TACTILEDLOG`` and a
zero byte, the format version (uint16 little-endian, 1) and two zero bytes, then one record per received
message::

    uint32 length, uint32 CRC-32 of the payload (both little-endian) | payload: msgpack [recv_mono, recv_unix, topic, body]

``recv_mono`` and ``recv_unix`` are the host's monotonic and wall clocks (s) when the message arrived, ``topic``
the first frame (str) and ``body`` the second, the msgpack map exactly as the daemon sent it (bin). Each record
is written with one ``write`` as it arrives, so a recorder killed at any moment leaves every message before the
last complete; a reader replays up to there and says where the file ends. So it does when zeros end the file (a power
cut: the file system kept the file's length but not its last data), saying how many; zeros followed by more data are
corruption (:meth:`LogReader._zeroed`). :class:`LogWriter` refuses
(:class:`RecordRefused`, nothing written) what :class:`LogReader` would refuse: a record over :data:`MAX_RECORD`
bytes, a body that is not a msgpack map, a receive time that is no clock reading.

Receive times: each must be a finite number of seconds within :data:`MAX_TIME_S` of 0 (in every kind of file), and in a
session log ``recv_mono`` (a recorder's monotonic clock) may not go back more than :data:`BACK_S` nor jump more than
:data:`MAX_GAP_S` past the record before it. Anything else is one :class:`LogError` naming the byte, line or MCAP
message: the replay's pacing would otherwise sleep for ever, or overflow ``time.sleep``.

:func:`open_log` also reads the files tactiled writes: an MCAP file's ``roughness`` channels (needs the
``mcap`` package: ``pip install 'tactiled-client[mcap]'``) and ``tactiled replay --json`` lines (each slide's
provisional labels, then its final one). Memory stays bounded by one record; nothing is ever unpickled.
"""

from __future__ import annotations

import contextlib
import json
import os
import stat
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, NoReturn

import msgpack

from tactiled_client import schema
from tactiled_client.errors import ClientError, LogError, RecordRefused
from tactiled_client.mcapbound import inflation_problem

MAGIC = b"TACTILEDLOG\x00"
VERSION = 1
HEADER = MAGIC + struct.pack("<H", VERSION) + b"\x00\x00"
RECORD = struct.Struct("<II")  # payload length, CRC-32
MAX_RECORD = 64 << 20  # bytes of one record's payload (a samples message of 0.1 s at 8 channels is ~16 kB)
MAX_LINE = 16 << 20  # bytes of one replay --json line
MCAP_MAGIC = b"\x89MCAP0\r\n"
MAX_MCAP_BYTES = 2 << 30  # bytes an MCAP file's records may inflate to (tactiled's own MCAP recordings: the same bound as an .npz)
MAX_TIME_S = 1e10  # s: no clock reading is further from 0 (a monotonic clock counts from boot; unix time reaches it in 2286)
BACK_S = 1.0  # s a session log's recv_mono may go back between records (a monotonic clock never does)
MAX_GAP_S = 30 * 86400.0  # s a session log's recv_mono may jump between records (a recorder hearing nothing for a month)
NOT_REGULAR = "not a regular file (a device or FIFO is never written)"  # what a recorder says of such a path, as tactiled record does


@dataclass(frozen=True)
class Entry:
    """One message of a session: when it arrived (s, host monotonic and wall clocks), its topic and its msgpack body."""

    time_mono: float
    time_unix: float
    topic: str
    body: bytes
    where: str = field(default="", compare=False)  # its place in the file: "byte 84", "line 3" or "<channel> message 7"

    def frames(self) -> list[bytes]:
        """The two ZeroMQ frames the message came in."""
        return [self.topic.encode(), self.body]


class WriteFailed(ClientError, OSError):
    """The machine refused a write to a session log (a full disk, a file-size limit, an I/O error): recording stops, the
    log holds every record before, whole. ``count``: how many."""

    def __init__(self, path: Path, strerror: str, count: int) -> None:
        super().__init__(f"{path}: {strerror}: recording stopped after {count} messages, every one kept (replay reads them)")
        self.count = count


class LogWriter:
    """Append received messages to a session log, each with one ``write`` (crash-safe; see the module docstring).

    Only a regular file is written (:data:`NOT_REGULAR`: a device or a FIFO at the path is refused, before it is opened and
    again after, so a FIFO never blocks the open). A write the machine refuses raises :class:`WriteFailed`, the file cut back
    to its last whole record."""

    def __init__(self, path: str | Path, *, overwrite: bool = False) -> None:
        self.path = Path(path)
        self._last_mono: float | None = None
        self._fd: int | None = None
        self._size = 0  # bytes of whole records (and the header) written
        self.count = 0
        if _special(self.path):
            raise LogError(f"{self.path}: {NOT_REGULAR}")
        flags = os.O_WRONLY | os.O_CREAT | os.O_NONBLOCK | (os.O_TRUNC if overwrite else os.O_EXCL)  # O_NONBLOCK: a FIFO never blocks
        try:
            fd = os.open(self.path, flags, 0o644)
        except FileExistsError:
            raise LogError(f"{self.path}: exists (overwrite it with --force)") from None
        except OSError as exc:
            raise LogError(f"{self.path}: cannot write: {exc.strerror}") from None
        if not stat.S_ISREG(os.fstat(fd).st_mode):  # one appeared there since the check
            os.close(fd)
            raise LogError(f"{self.path}: {NOT_REGULAR}")
        os.set_blocking(fd, True)
        self._fd = fd
        self._append(HEADER)

    def _append(self, data: bytes) -> None:
        """Write ``data`` whole, or raise :class:`WriteFailed` with the file cut back to what was whole before."""
        if self._fd is None:
            raise LogError(f"{self.path}: already closed")
        view = memoryview(data)
        try:
            while view:
                view = view[os.write(self._fd, view):]
        except OSError as exc:
            with contextlib.suppress(OSError):  # never grows the file: works on a full disk, and under a file-size limit
                os.ftruncate(self._fd, self._size)
            self._failed(exc)
        self._size += len(data)

    def _failed(self, exc: OSError) -> NoReturn:
        """Close the file (unsynced: the machine refused it) and raise :class:`WriteFailed`."""
        fd, self._fd = self._fd, None
        if fd is not None:
            with contextlib.suppress(OSError):
                os.close(fd)
        raise WriteFailed(self.path, exc.strerror or str(exc), self.count) from None

    def write(self, frames: list[bytes], time_mono: float, time_unix: float) -> None:
        """Append one received two-frame message with its receive times (s); :class:`RecordRefused`, nothing written, for
        a message :class:`LogReader` would refuse (see the module docstring), so that every later record stays readable;
        :class:`WriteFailed` if the machine refuses the write."""
        topic = frames[0].decode("utf-8", "replace")
        fault = _times_fault(time_mono, time_unix, self._last_mono) or _map_fault(bytes(frames[1]))
        if fault is not None:
            raise RecordRefused(self.path, f"{topic[:80]}: {fault}")
        payload = msgpack.packb([time_mono, time_unix, topic, bytes(frames[1])], use_bin_type=True)
        if len(payload) > MAX_RECORD:
            raise RecordRefused(self.path, f"{topic[:80]}: a record of {len(payload)} bytes, more than the {MAX_RECORD} a record may hold")
        self._append(RECORD.pack(len(payload), zlib.crc32(payload)) + payload)
        self._last_mono = time_mono
        self.count += 1

    def close(self) -> None:
        """Flush to disk and close (:class:`WriteFailed` if the machine refuses the flush: a full disk may say so only now)."""
        if self._fd is not None:
            try:
                os.fsync(self._fd)
            except OSError as exc:
                self._failed(exc)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class LogReader:
    """The messages of a session log, tactiled MCAP file or ``replay --json`` output, in file order (:class:`Entry`).

    Iterate once. ``truncated``: after iterating, a one-line note if the file ended inside a record (what a
    killed recorder leaves) or in zeros (what a power cut leaves); every complete message before it was read. Anything
    else wrong is a :class:`LogError` naming the file and the byte or line.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.truncated: str | None = None
        self.count = 0
        if not self.path.exists():
            raise LogError(f"{self.path}: no such file")
        if _special(self.path):  # before opening: a FIFO would block the open, /dev/zero never ends
            raise LogError(f"{self.path}: not a regular file")
        try:
            with open(self.path, "rb") as fh:
                head = fh.read(len(HEADER))
        except OSError as exc:
            raise LogError(f"{self.path}: cannot read: {exc.strerror or exc}") from None
        if head.startswith(MAGIC):
            version = struct.unpack("<H", head[len(MAGIC):len(MAGIC) + 2])[0] if len(head) >= len(MAGIC) + 2 else None
            if version != VERSION:
                raise LogError(f"{self.path}: session log version {version}, this client reads version {VERSION} (upgrade tactiled-client)")
            self.kind = "log"
        elif head.startswith(MCAP_MAGIC):
            self.kind = "mcap"
        elif head.lstrip()[:1] == b"{":
            self.kind = "json"
        else:
            raise LogError(f"{self.path}: not a session log, an MCAP file or tactiled replay --json output")

    def __iter__(self) -> Iterator[Entry]:
        entries = {"log": self._log, "mcap": self._mcap, "json": self._json}[self.kind]()
        last: float | None = None
        for entry in entries:
            fault = _times_fault(entry.time_mono, entry.time_unix, last if self.kind == "log" else None)
            if fault is not None:
                raise self._fail(entry.where, fault)
            last = entry.time_mono
            self.count += 1
            yield entry

    def _fail(self, where: str, what: str) -> LogError:
        return LogError(f"{self.path}: {where}: {what}")

    def _log(self) -> Iterator[Entry]:
        size = self.path.stat().st_size
        with open(self.path, "rb") as fh:
            fh.seek(len(HEADER))
            while True:
                at = fh.tell()
                head = fh.read(RECORD.size)
                if not head:
                    return
                cut = f"{self.path}: ends inside a record at byte {at} (a recorder stopped mid-write); read the messages before it"
                if len(head) < RECORD.size:
                    self.truncated = self._zeroed(fh, at, size, at + 1) or cut  # zeros alone after the last record, or a cut
                    return
                length, crc = RECORD.unpack(head)
                if length > MAX_RECORD:
                    raise self._fail(f"byte {at}", f"record declares {length} bytes, more than the {MAX_RECORD} a record may hold")
                if at + RECORD.size + length > size:
                    self.truncated = cut
                    return
                payload = fh.read(length)
                if zlib.crc32(payload) != crc or not length:
                    self.truncated = self._zeroed(fh, at, size, at + RECORD.size + length)
                    if self.truncated:
                        return
                    raise self._fail(f"byte {at}", "record fails its CRC-32 (corrupt)" if length else "record of 0 bytes (corrupt)")
                yield self._entry(at, payload)

    def _zeroed(self, fh: IO[bytes], at: int, size: int, end: int) -> str | None:
        """The :attr:`truncated` note if the bad record at byte ``at``, declared to end at byte ``end``, is explained by zeros
        to the end of the file, else None (corrupt).

        What a power cut leaves: the file kept its length but its last data blocks read back as zeros, from a block
        boundary to the end. The zeros explain the record if they begin before ``end`` (they reach into it) and the bytes
        of its payload before them hold no complete msgpack object (they are the start of one the zeros cut off). Zeros
        after a record that is complete before them, or followed by non-zero data, are damage, never skipped. A last record
        damaged before zeros that were its own data cannot be told from one the zeros cut: it is called truncated too (it is
        the last either way: nothing after it is skipped)."""
        zeros = _zeros_from(fh, at, size)
        if zeros >= end:
            return None
        prefix = b""
        if zeros > at + RECORD.size:
            fh.seek(at + RECORD.size)
            prefix = fh.read(zeros - at - RECORD.size)
        unpacker = msgpack.Unpacker(raw=False, strict_map_key=False, max_buffer_size=MAX_RECORD)
        unpacker.feed(prefix)
        try:
            unpacker.unpack()
        except msgpack.OutOfData:
            where = "after its last complete record" if zeros == at else f"in the record there, from byte {zeros}"
            return (f"{self.path}: ends at byte {at}: {size - zeros} zero bytes to the end of the file {where} (a power cut: the file "
                    "kept its length, not its last data); read the messages before it")
        except (ValueError, msgpack.UnpackException, TypeError, RecursionError):
            return None
        return None

    def _entry(self, at: int, payload: bytes) -> Entry:
        try:
            rec = msgpack.unpackb(payload, raw=False, strict_map_key=False)
        except (ValueError, msgpack.UnpackException, TypeError) as exc:
            raise self._fail(f"byte {at}", f"record is not msgpack: {exc}") from None
        ok = (isinstance(rec, list) and len(rec) == 4 and all(isinstance(t, (int, float)) for t in rec[:2]) and isinstance(rec[2], str)
              and isinstance(rec[3], bytes))
        if not ok:
            raise self._fail(f"byte {at}", "record is not [recv_mono, recv_unix, topic, body]")
        check_body(rec[3], f"{self.path}: byte {at}")
        return Entry(float(rec[0]), float(rec[1]), rec[2], rec[3], f"byte {at}")

    def _mcap(self) -> Iterator[Entry]:
        try:
            from mcap.exceptions import McapError
            from mcap.reader import make_reader
        except ImportError:
            raise LogError(f"{self.path}: reading MCAP needs the mcap package: pip install 'tactiled-client[mcap]'") from None
        with open(self.path, "rb") as fh:
            try:
                problem = inflation_problem(fh, MAX_MCAP_BYTES)
                if problem is not None:
                    raise LogError(f"{self.path}: {problem}")
                for _schema, channel, message in make_reader(fh).iter_messages(log_time_order=True):
                    parts = channel.topic.strip("/").split("/")
                    if len(parts) != 3 or parts[0] != "tactiled" or parts[2] != schema.ROUGHNESS:
                        continue  # samples and ground-truth slides are not wire messages
                    where = f"{channel.topic} message {message.sequence}"
                    if channel.message_encoding != "json":
                        raise LogError(f"{self.path}: {channel.topic} holds {channel.message_encoding or 'unnamed'}-encoded messages, not JSON: "
                                       "a ROS 2 bag? replay reads tactiled's JSON MCAP export")
                    body = _json_map(message.data, f"{self.path}: {where}")
                    t = message.log_time / 1e9
                    yield Entry(t, t, schema.topic(schema.ROUGHNESS, parts[1]), _pack(body, f"{self.path}: {where}"), where)
            except LogError:
                raise
            except (McapError, ValueError, KeyError, EOFError, OSError, struct.error) as exc:  # what the mcap reader raises on a bad file
                raise LogError(f"{self.path}: not a readable MCAP file: {type(exc).__name__}: {exc}") from None

    def _json(self) -> Iterator[Entry]:
        """Each line's provisional labels (at ``t_start + used_s``), then its final one (at ``t_stop``). A field these times
        come from that is not a number of seconds, or ``provisional`` not a list of maps, is a :class:`LogError` naming the
        line and the field."""
        wire = schema.Roughness.wire_fields()
        with open(self.path, "rb") as fh:
            for number, line in enumerate(_lines(fh, self.path), 1):
                if not line.strip():
                    continue
                at = f"line {number}"
                where = f"{self.path}: {at}"
                obj = _json_map(line, where)
                final = {k: v for k, v in obj.items() if k in wire}
                topic = schema.topic(schema.ROUGHNESS, str(final.get("sensor", "")))
                start = _seconds(final, "t_start", 0.0, where)
                provisional = obj.get("provisional") or []
                if not isinstance(provisional, list):
                    raise LogError(f"{where}: provisional: {type(provisional).__name__}, not a list")
                for i, p in enumerate(provisional):
                    if not isinstance(p, dict):
                        raise LogError(f"{where}: provisional[{i}]: {type(p).__name__}, not a map")
                    t = start + _seconds(p, "used_s", 0.0, f"{where}: provisional[{i}]")
                    early = {**final, **{k: v for k, v in p.items() if k in wire}, "final": False, "t_stop": t,
                             "stop_mono": None, "stop_unix": None}  # the end of what it used, not the slide's
                    window = final.get("window")
                    if isinstance(p.get("stop"), int) and isinstance(window, list) and window:
                        early["window"] = [window[0], p["stop"]]  # from the slide's first window to the end of its last one used
                    yield Entry(t, t, topic, _pack(early, where), at)
                t = _seconds(final, "t_stop", start, where)
                yield Entry(t, t, topic, _pack(final, where), at)


def _zeros_from(fh: IO[bytes], at: int, size: int, chunk: int = 1 << 16) -> int:
    """Where the run of zero bytes that ends the file (``size`` bytes) begins, at byte ``at`` at the earliest (``size``: the
    last byte is not zero). Reads back from the end, ``chunk`` bytes at a time, until a non-zero byte or ``at``."""
    stop = size
    while stop > at:
        start = max(at, stop - chunk)
        fh.seek(start)
        data = fh.read(stop - start)
        kept = data.rstrip(b"\x00")
        if kept:
            return start + len(kept)
        stop = start
    return at


def _special(path: Path) -> bool:
    """Whether something other than a regular file is at ``path`` (a device, a FIFO, a folder, a socket; a symbolic link is
    followed): a FIFO would block its opening, /dev/zero never ends, /dev/null keeps nothing (tactiled's equivalent,
    ``tactiled.files.outputs.check_output``, is not importable here: the client library installs alone)."""
    return path.exists() and not path.is_file()


def _lines(fh: IO[bytes], path: Path) -> Iterator[bytes]:
    while True:
        line = fh.readline(MAX_LINE + 1)
        if not line:
            return
        if len(line) > MAX_LINE:
            raise LogError(f"{path}: a line longer than {MAX_LINE} bytes")
        yield line


def _is_time(value: Any) -> bool:
    """Whether ``value`` is a number of seconds a clock can read: finite, within :data:`MAX_TIME_S` of 0, not a bool (NaN
    fails the comparison too)."""
    return not isinstance(value, bool) and isinstance(value, (int, float)) and abs(value) <= MAX_TIME_S


def _seconds(obj: dict[str, Any], name: str, default: float, where: str) -> float:
    """``obj[name]`` as seconds (``default`` when absent, null or 0), or :class:`LogError` naming ``where`` and the field if
    it is not a finite number within :data:`MAX_TIME_S`."""
    value = obj.get(name)
    if value is None:
        return default
    if not _is_time(value):
        shown = f"a {type(value).__name__}" if isinstance(value, (dict, list)) else json.dumps(value)[:40]
        raise LogError(f"{where}: {name}: {shown} is not a time in seconds (a number within {MAX_TIME_S:g})")
    return float(value) or default


def _pack(body: dict[str, Any], where: str) -> bytes:
    """The msgpack body of a message read from JSON, or :class:`LogError` if JSON held what msgpack cannot (an integer
    beyond 64 bits)."""
    try:
        return schema.pack(body)
    except (OverflowError, ValueError, TypeError) as exc:
        raise LogError(f"{where}: a value msgpack cannot hold: {str(exc)[:80]}") from None


def _times_fault(time_mono: float, time_unix: float, last_mono: float | None) -> str | None:
    """Why a record's receive times are no clock readings (one phrase), or None; ``last_mono``: the record before's
    ``recv_mono`` in a session log (its monotonic clock neither goes back more than :data:`BACK_S` nor jumps more than
    :data:`MAX_GAP_S`), None to check the values alone."""
    for name, t in (("recv_mono", time_mono), ("recv_unix", time_unix)):
        if not _is_time(t):
            return f"{name} {t!r:.40} is not a clock reading (a number of seconds within {MAX_TIME_S:g})"
    if last_mono is not None:
        step = time_mono - last_mono
        if step < -BACK_S:
            return f"recv_mono goes back {-step:g} s from the record before (a recorder's monotonic clock never does)"
        if step > MAX_GAP_S:
            return f"recv_mono jumps {step:g} s past the record before (more than {MAX_GAP_S:g} s: not one recording)"
    return None


def _json_map(data: bytes, where: str) -> dict[str, Any]:
    try:
        obj = json.loads(data)
    except (ValueError, RecursionError) as exc:
        raise LogError(f"{where}: not JSON: {str(exc)[:80]}") from None
    if not isinstance(obj, dict):
        raise LogError(f"{where}: not a JSON object")
    return obj


def check_body(body: bytes, where: str) -> dict[str, Any]:
    """The decoded message map of ``body``, or :class:`LogError` (not msgpack, too deep, not a map). A schema version
    newer than this client's is read as the live subscriber reads it: fields are only added, unknown ones go to ``extra``."""
    obj = _unpack_map(body)
    if isinstance(obj, str):
        raise LogError(f"{where}: {obj}")
    return obj


def _unpack_map(body: bytes) -> dict[str, Any] | str:
    """The decoded map of a message body, or why it is none (one phrase: not msgpack, nested too deep, not a map)."""
    try:
        obj = msgpack.unpackb(body, raw=False, strict_map_key=False)
    except (ValueError, msgpack.UnpackException, TypeError, RecursionError) as exc:
        return f"message body is not msgpack: {exc}"
    if not isinstance(obj, dict):
        return "message body is not a map"
    return obj


def _map_fault(body: bytes) -> str | None:
    """Why ``body`` is not a message map a reader takes (see :func:`_unpack_map`), or None. A schema version newer than this
    client's is no fault: every reader takes it (see :func:`check_body`)."""
    obj = _unpack_map(body)
    return obj if isinstance(obj, str) else None

