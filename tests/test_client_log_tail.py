"""A session log that ends in zeros (a power cut: the file system kept the file's length but not its last data) reads every
record before them and is reported truncated there, with how many zero bytes; zeros followed by data, or after a record
that is damaged before them, are still corruption."""

from __future__ import annotations

import struct
import subprocess
import sys
from pathlib import Path

import msgpack
import pytest
from tactiled_client import BlockingReplay, LogError, schema
from tactiled_client.log import HEADER, RECORD, LogReader, LogWriter

from tests.conftest import REPO


def _log(path: Path, n: int = 5) -> list[int]:
    """A session log of ``n`` status messages (each record a few hundred bytes); the byte each record starts at, then the size."""
    starts = []
    with LogWriter(path) as log:
        for seq in range(n):
            starts.append(path.stat().st_size)
            body = msgpack.packb({"v": schema.SCHEMA_VERSION, "seq": seq, "sensor": "s0", "type": "status", "level": [0.5] * 40,
                                  "state": "idle"}, use_bin_type=True)  # ends in a non-zero byte
            log.write([b"status/s0", body], 100.0 + seq, 1.7e9 + seq)
    return [*starts, path.stat().st_size]


def _zero(path: Path, start: int, end: int | None = None, extra: int = 0) -> None:
    """Zeros over bytes [start, end) of ``path`` (to its end by default), then ``extra`` more zero bytes."""
    data = bytearray(path.read_bytes())
    stop = len(data) if end is None else end
    data[start:stop] = bytes(stop - start)
    path.write_bytes(bytes(data) + bytes(extra))


def _read(path: Path) -> tuple[list[int], str | None]:
    reader = LogReader(path)
    return [msgpack.unpackb(e.body)["seq"] for e in reader], reader.truncated


def test_zeros_after_the_last_record_are_a_truncated_file_not_a_corrupt_one(tmp_path: Path) -> None:
    """It was 'record is not msgpack' at the first zero (an all-zero record header declares 0 bytes, CRC 0): replay stopped
    with exit 2."""
    path = tmp_path / "cut.tlog"
    starts = _log(path)
    _zero(path, starts[-1], extra=4096)
    seqs, note = _read(path)
    assert seqs == [0, 1, 2, 3, 4]
    assert note == (f"{path}: ends at byte {starts[-1]}: 4096 zero bytes to the end of the file after its last complete record (a power "
                    "cut: the file kept its length, not its last data); read the messages before it")
    with BlockingReplay(path, speed=None) as rep:
        assert [m.seq for m in rep] == [0, 1, 2, 3, 4] and rep.malformed == 0
    res = subprocess.run([sys.executable, "-m", "tactiled_client", "replay", str(path), "--json"], capture_output=True, text=True,
                         timeout=60, cwd=REPO)
    assert res.returncode == 0 and len(res.stdout.splitlines()) == 5 and res.stderr == f"warning: {note}\n", res.stderr


@pytest.mark.parametrize("into", [3, RECORD.size + 40, "end"])
def test_zeros_from_inside_the_last_records_reach_the_end(into: int | str, tmp_path: Path) -> None:
    """The lost blocks begin inside a record (its header, its payload), and later records are all zeros: every record
    before that one is read, and the file is truncated at its start. ``end``: only the last record's last bytes are zeros."""
    path = tmp_path / "cut.tlog"
    starts = _log(path)
    damaged = starts[3]
    zeros_from = starts[-1] - 5 if into == "end" else damaged + int(into)
    if into == "end":
        damaged = starts[4]
    _zero(path, zeros_from)
    zeros_from = len(path.read_bytes().rstrip(b"\x00"))  # earlier if the bytes before were zeros already (a length's high bytes)
    seqs, note = _read(path)
    assert seqs == list(range(4 if into == "end" else 3))
    assert note is not None and note.startswith(f"{path}: ends at byte {damaged}: {starts[-1] - zeros_from} zero bytes to the end of "
                                                f"the file in the record there, from byte {zeros_from} (a power cut"), note


def test_fewer_zero_bytes_than_a_record_header_after_the_last_record(tmp_path: Path) -> None:
    path = tmp_path / "cut.tlog"
    starts = _log(path, 2)
    _zero(path, starts[-1], extra=5)
    seqs, note = _read(path)
    assert seqs == [0, 1] and note is not None and note.startswith(f"{path}: ends at byte {starts[-1]}: 5 zero bytes"), note


def test_zeros_followed_by_data_are_corruption(tmp_path: Path) -> None:
    """Damage in the middle is never skipped: zero records between good ones, a zeroed block inside a record that is
    not the last."""
    path = tmp_path / "mid.tlog"
    starts = _log(path)
    data = path.read_bytes()
    path.write_bytes(data[:starts[2]] + bytes(4096) + data[starts[2]:])
    with pytest.raises(LogError, match=f"^{path}: byte {starts[2]}: record of 0 bytes \\(corrupt\\)$"):
        _read(path)
    _log(path := tmp_path / "block.tlog")
    _zero(path, starts[1] + RECORD.size + 20, starts[2] - 10)
    with pytest.raises(LogError, match=f"^{path}: byte {starts[1]}: record fails its CRC-32 \\(corrupt\\)$"):
        _read(path)


def test_zeros_do_not_excuse_a_record_damaged_before_them(tmp_path: Path) -> None:
    """A last record with a flipped byte before the zeros, and a record in the middle whose length field now reaches into the
    zeros (its payload, complete before them, is a whole msgpack object): both corrupt, as without the zeros."""
    path = tmp_path / "flip.tlog"
    starts = _log(path)
    data = bytearray(path.read_bytes())
    data[starts[4] + RECORD.size + 30] ^= 0xFF
    path.write_bytes(bytes(data) + bytes(4096))
    with pytest.raises(LogError, match=f"^{path}: byte {starts[4]}: record fails its CRC-32"):
        _read(path)
    _log(path := tmp_path / "length.tlog")
    data = bytearray(path.read_bytes() + bytes(4096))
    length, crc = RECORD.unpack_from(data, starts[2])
    struct.pack_into("<I", data, starts[2], len(data) - starts[2] - RECORD.size - 100)  # its end 100 bytes before the file's
    path.write_bytes(bytes(data))
    with pytest.raises(LogError, match=f"^{path}: byte {starts[2]}: record fails its CRC-32"):
        _read(path)
    assert HEADER and length > 0 and crc  # the record it replaced was a real one
