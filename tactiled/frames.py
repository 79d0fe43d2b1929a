"""The fingertip ADC's serial frames (docs/sensor-frames.md), sans-IO.

:class:`FrameDecoder` takes bytes and returns frames; it does no I/O, so serial, replay
and tests only hand it bytes. It never trusts a sync word without the CRC: a frame whose
header is out of range or whose CRC fails is not a frame, and the decoder drops one byte
and hunts for the next sync word, so a corrupted frame costs only that frame.

The 32-bit sample index is unwrapped into a 64-bit one. A forward jump counts the samples
lost; a jump back by less than ``duplicate_window`` samples is a duplicated frame (dropped
and counted); a larger jump back is a board restart: counted, flagged on the frame, and the
host's timeline continues from where it was (the samples lost across a restart are unknown).
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

SYNC = b"\xa5\x5a"
VERSION = 1
HEADER_SIZE = 10
CRC_SIZE = 2
MAX_CHANNELS = 8
MAX_COUNT = 1024
_WRAP = 1 << 32
_HALF = 1 << 31
_header = struct.Struct("<BBHI")
_crc = struct.Struct("<H")


def crc16(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF); ``crc16(b"123456789") == 0x29B1``."""
    return binascii.crc_hqx(data, 0xFFFF)


def frame_size(channels: int, count: int) -> int:
    """Bytes in one frame of ``count`` samples of ``channels`` channels."""
    return HEADER_SIZE + 2 * channels * count + CRC_SIZE


def encode_frame(index: int, samples: npt.ArrayLike) -> bytes:
    """One frame: ``samples`` (N, C) int16 counts whose first sample has sensor index ``index``.

    ``index`` is taken modulo 2**32 as the board does.
    """
    arr = np.asarray(samples)
    if arr.ndim != 2 or not (1 <= arr.shape[1] <= MAX_CHANNELS) or not (1 <= arr.shape[0] <= MAX_COUNT):
        raise ValueError(f"samples must have shape (N, C) with N in 1..{MAX_COUNT}, C in 1..{MAX_CHANNELS}; got {arr.shape}")
    count, channels = arr.shape
    body = _header.pack(VERSION, channels, count, index % _WRAP) + arr.astype("<i2", copy=False).tobytes()
    return SYNC + body + _crc.pack(crc16(body))


def encode_frames(first_index: int, samples: npt.ArrayLike, count: int = 20) -> bytes:
    """Frames of ``count`` samples each for a (n, C) block, as the fingertip firmware sends them."""
    arr = np.asarray(samples)
    return b"".join(
        encode_frame(first_index + i, arr[i:i + count]) for i in range(0, arr.shape[0], count)
    )


@dataclass(slots=True)
class Frame:
    """One decoded frame.

    ``index``: 64-bit unwrapped index of the first sample on the host's timeline;
    ``samples``: (N, C) int16 ADC counts (a read-only view);
    ``lost``: samples missing just before this frame (index gap);
    ``restart``: the board restarted just before this frame.
    """

    index: int
    samples: npt.NDArray[np.int16]
    lost: int = 0
    restart: bool = False


@dataclass
class DecoderStats:
    """What the decoder saw and threw away, since it was made."""

    frames: int = 0
    samples: int = 0
    crc_errors: int = 0
    bad_headers: int = 0
    truncated: int = 0  # incomplete frames at the end of a finite stream (flush)
    bytes_discarded: int = 0
    samples_lost: int = 0
    restarts: int = 0
    duplicates: int = 0


class FrameDecoder:
    """Sans-IO decoder: ``feed(bytes) -> list[Frame]``; counters in :attr:`stats`."""

    def __init__(self, duplicate_window: int = 65536) -> None:
        self._buf = b""
        self._next: int | None = None  # host (64-bit) index expected next
        self._next32 = 0  # the board's 32-bit index expected next
        self._duplicate_window = duplicate_window
        self.stats = DecoderStats()

    @property
    def next_index(self) -> int | None:
        """The unwrapped index the next frame should start at (None before the first frame)."""
        return self._next

    @property
    def pending(self) -> int:
        """Bytes held back waiting for the rest of a frame."""
        return len(self._buf)

    def flush(self) -> list[Frame]:
        """End of stream: decode what is left, treating an incomplete frame as garbage.

        A corrupted count field can make the decoder wait for more bytes than will come;
        at the end of a finite stream that must not hold back the good frames after it.
        """
        out = self._decode(final=True)
        self.stats.bytes_discarded += len(self._buf)
        self._buf = b""
        return out

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame]:
        """Decode what ``data`` completes; partial frames are kept for the next call."""
        self._buf = self._buf + bytes(data) if self._buf else bytes(data)
        return self._decode(final=False)

    def _decode(self, final: bool) -> list[Frame]:
        buf = self._buf
        n = len(buf)
        pos = 0
        out: list[Frame] = []
        stats = self.stats
        unpack_header = _header.unpack_from
        unpack_crc = _crc.unpack_from
        crc_hqx = binascii.crc_hqx
        while n - pos >= HEADER_SIZE + CRC_SIZE + 2:
            if buf[pos] != 0xA5 or buf[pos + 1] != 0x5A:
                j = buf.find(SYNC, pos + 1)
                if j < 0:
                    # keep a trailing 0xA5: it may be the first half of a sync word
                    j = n - 1 if buf[n - 1] == 0xA5 else n
                stats.bytes_discarded += j - pos
                pos = j
                continue
            version, channels, count, index32 = unpack_header(buf, pos + 2)
            if version != VERSION or not (1 <= channels <= MAX_CHANNELS) or not (1 <= count <= MAX_COUNT):
                stats.bad_headers += 1
                stats.bytes_discarded += 1
                pos += 1
                continue
            total = HEADER_SIZE + 2 * channels * count + CRC_SIZE
            if n - pos < total:
                if not final:
                    break
                stats.truncated += 1  # at the end of the stream, an incomplete frame is not a frame
                stats.bytes_discarded += 1
                pos += 1
                continue
            end = pos + total - CRC_SIZE
            if crc_hqx(buf[pos + 2:end], 0xFFFF) != unpack_crc(buf, end)[0]:
                stats.crc_errors += 1
                stats.bytes_discarded += 1
                pos += 1
                continue
            samples = np.frombuffer(buf, dtype="<i2", count=channels * count, offset=pos + HEADER_SIZE)
            pos += total
            frame = self._place(index32, samples.reshape(count, channels))
            if frame is not None:
                out.append(frame)
        self._buf = buf[pos:]
        return out

    def _place(self, index32: int, samples: npt.NDArray[np.int16]) -> Frame | None:
        stats = self.stats
        count = samples.shape[0]
        expected = self._next
        lost = 0
        restart = False
        if expected is None:
            index = index32
        else:
            delta = (index32 - self._next32) % _WRAP
            if delta < _HALF:
                lost = delta
                index = expected + delta
            elif _WRAP - delta <= self._duplicate_window:
                stats.duplicates += 1
                return None
            else:
                restart = True
                stats.restarts += 1
                index = expected
        stats.frames += 1
        stats.samples += count
        stats.samples_lost += lost
        self._next = index + count
        self._next32 = (index32 + count) % _WRAP
        return Frame(index, samples, lost, restart)
