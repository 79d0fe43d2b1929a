"""The fingertip ADC's serial frames (docs/sensor-frames.md), sans-IO.

:class:`FrameDecoder` takes bytes and returns frames; it does no I/O, so serial, replay
and tests only hand it bytes. It never trusts a sync word without the CRC: a frame whose
header is out of range or whose CRC fails is not a frame, and the decoder drops one byte
and hunts for the next sync word, so a corrupted frame costs only that frame.

Intact consecutive frames are decoded in bulk (one numpy view over the run, one CRC call
per frame), so :meth:`FrameDecoder.feed_runs` costs little more per read than per frame.

The 32-bit sample index is unwrapped into a 64-bit one. A forward jump (less than half the
counter's range, 2**31 samples: more could as well be a jump back) counts the samples lost,
however many: the host index jumps with it, so positions stay equal to sensor time. A jump back
by at most ``duplicate_window`` samples to a frame already placed, with the same CRC, is a
duplicated frame (dropped and counted); any other jump back (a board reset to a small index
sends other samples at those indices), or a forward jump of ``max_gap`` or more when one is set,
is a board restart (or a frame that passed the CRC by chance): counted, flagged on the frame, and
the host's timeline continues from where it was (the samples lost across a restart are unknown).
Nothing is allocated for a gap. Frames with a foreign channel count never move the index.
"""

from __future__ import annotations

import binascii
import struct
from collections import deque
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
_index = struct.Struct("<I")


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
    """One decoded frame, or (from :meth:`FrameDecoder.feed_runs`) a run of consecutive frames.

    ``index``: 64-bit unwrapped index of the first sample on the host's timeline;
    ``samples``: (N, C) int16 ADC counts;
    ``lost``: samples missing just before this frame (index gap);
    ``restart``: the board restarted (or the stream resynchronised) just before this frame;
    ``frame_count``: samples per frame on the wire (a run holds N / frame_count frames).
    """

    index: int
    samples: npt.NDArray[np.int16]
    lost: int = 0
    restart: bool = False
    frame_count: int = 0


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
    restarts: int = 0  # backward jumps that are not duplicates, and forward jumps the counter cannot make
    duplicates: int = 0  # frames dropped as repeats of frames already placed
    channel_errors: int = 0  # intact frames with a channel count other than the expected one (skipped)


class FrameDecoder:
    """Sans-IO decoder: ``feed(bytes) -> list[Frame]`` (one per frame) or ``feed_runs`` (runs of frames); counters in :attr:`stats`.

    ``channels``: if set, intact frames with another channel count are counted in
    ``stats.channel_errors`` and skipped without moving the index. ``max_gap``: the longest
    forward jump counted as lost samples (default, and at most, 2**31 - 1: the longest the
    32-bit counter can say unambiguously); a longer one is a restart, as a jump back that is
    not a duplicate is: the timeline continues where it was, in O(1). Nothing is allocated
    for a gap either way.

    Duplicates are recognised by content: the decoder keeps the CRC of each frame placed in
    the last ``duplicate_window`` samples (a few kB), and a frame whose index goes back is a
    duplicate only if it repeats one of them exactly.
    """

    def __init__(self, duplicate_window: int = 65536, *, channels: int | None = None, max_gap: int | None = None) -> None:
        self._buf = b""
        self._next: int | None = None  # host (64-bit) index expected next
        self._next32 = 0  # the board's 32-bit index expected next
        self._duplicate_window = duplicate_window
        self._channels = channels
        self._max_gap = _HALF - 1 if max_gap is None else min(max(int(max_gap), 0), _HALF - 1)
        # the runs placed whose frames may lie in the last duplicate_window samples, oldest first: (board index of the
        # run's first frame, samples per frame, the frames' CRCs); a run costs one entry, not one per frame
        self._runs: deque[tuple[int, int, list[int]]] = deque()
        self.stats = DecoderStats()
        self.foreign_channels: int | None = None  # the channel count of the last intact frame skipped for its layout

    def channel_mismatch(self, sensor_id: str) -> str:
        """The one line a daemon, a recorder or a replay says when intact frames were skipped for their channel count (the
        last such frame's against the ``channels`` expected): the board is not the one configured, none of its samples is used."""
        return (f"sensor {sensor_id}: frames of {self.foreign_channels} channel(s) skipped, sensor.channels is {self._channels}: "
                "set [sensor] channels to the board's")

    @property
    def next_index(self) -> int | None:
        """The unwrapped index the next frame should start at (None before the first frame)."""
        return self._next

    @property
    def pending(self) -> int:
        """Bytes held back waiting for the rest of a frame."""
        return len(self._buf)

    def flush(self) -> list[Frame]:
        """End of stream, one frame per item: see :meth:`flush_runs`."""
        return _split(self.flush_runs())

    def flush_runs(self) -> list[Frame]:
        """End of stream: decode what is left, treating an incomplete frame as garbage.

        A corrupted count field can make the decoder wait for more bytes than will come;
        at the end of a finite stream that must not hold back the good frames after it.
        """
        out = self._decode(final=True)
        self.stats.bytes_discarded += len(self._buf)
        self._buf = b""
        return out

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame]:
        """Decode what ``data`` completes, one :class:`Frame` per frame; partial frames are kept for the next call."""
        return _split(self.feed_runs(data))

    def feed_runs(self, data: bytes | bytearray | memoryview) -> list[Frame]:
        """Decode what ``data`` completes in bulk: consecutive frames come as one :class:`Frame` (a run).

        The samples and indices are those :meth:`feed` gives; only how they are grouped depends
        on how the bytes were cut.
        """
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
        unpack_index = _index.unpack_from
        crc_hqx = binascii.crc_hqx
        view = memoryview(buf)
        while n - pos >= HEADER_SIZE + CRC_SIZE + 2:
            if buf[pos] != 0xA5 or buf[pos + 1] != 0x5A:
                j = buf.find(SYNC, pos + 1)
                if j < 0:
                    # keep a trailing 0xA5: it may be the first half of a sync word
                    j = n - 1 if buf[n - 1] == 0xA5 else n
                stats.bytes_discarded += j - pos
                pos = j
                continue
            version, channels, count, _ = unpack_header(buf, pos + 2)
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
            # bulk: the consecutive frames from here (same header fields, indices following on), each checked by its CRC
            head = buf[pos:pos + 6]
            first32 = unpack_index(buf, pos + 6)[0]
            next32 = first32
            good = 0
            p = pos
            last = n - total
            crcs: list[int] = []
            while p <= last and buf.startswith(head, p) and unpack_index(buf, p + 6)[0] == next32:
                crc = unpack_crc(buf, p + total - CRC_SIZE)[0]
                if crc_hqx(view[p + 2:p + total - CRC_SIZE], 0xFFFF) != crc:
                    break
                crcs.append(crc)
                good += 1
                p += total
                next32 = (next32 + count) % _WRAP
            if not good:
                stats.crc_errors += 1
                stats.bytes_discarded += 1
                pos += 1
                continue
            start, pos = pos, p
            if self._channels is not None and channels != self._channels:
                stats.channel_errors += good  # intact, but not this sensor's layout: the index must not move
                self.foreign_channels = channels
                continue
            if good == 1:
                samples = np.frombuffer(buf, dtype="<i2", count=channels * count, offset=start + HEADER_SIZE).reshape(count, channels)
            else:
                run = np.frombuffer(buf, dtype=np.uint8, count=good * total, offset=start).reshape(good, total)
                samples = np.ascontiguousarray(run[:, HEADER_SIZE:total - CRC_SIZE]).view("<i2").reshape(good * count, channels)
            frame = self._place(first32, samples, count, crcs)
            if frame is not None:
                out.append(frame)
        self._buf = buf[pos:]
        return out

    def _place(self, index32: int, samples: npt.NDArray[np.int16], count: int, crcs: list[int]) -> Frame | None:
        """Place a run of consecutive frames (``count`` samples each, CRCs ``crcs``) starting at board index ``index32``."""
        stats = self.stats
        expected = self._next
        lost = 0
        restart = False
        if expected is None:
            index = index32
        else:
            delta = (index32 - self._next32) % _WRAP
            back = _WRAP - delta
            if delta <= self._max_gap:
                lost = delta
                index = expected + delta
            elif back <= self._duplicate_window and self._placed(index32) == crcs[0]:
                # a repeat of a frame already placed: the frames that start before what was placed are duplicates,
                # whole frames as if fed one by one
                drop = -(-back // count)
                same = 0  # the leading frames that repeat what was placed, each checked as it would be fed alone
                while same < min(drop, len(crcs)) and self._placed((index32 + same * count) % _WRAP) == crcs[same]:
                    same += 1
                stats.duplicates += same
                if same < min(drop, len(crcs)):  # then one that goes back with other samples: placed as a frame of its own would be
                    return self._place((index32 + same * count) % _WRAP, samples[same * count:], count, crcs[same:])
                if drop >= len(crcs):
                    return None
                samples = samples[drop * count:]
                crcs = crcs[drop:]
                lost = drop * count - back
                index32 = (index32 + drop * count) % _WRAP
                index = expected + lost
            else:
                # the board restarted (a reset to a small index sends other samples at indices already placed),
                # or the counter jumped further than it can say
                restart = True
                stats.restarts += 1
                index = expected
                self._runs.clear()
        n = samples.shape[0]
        stats.frames += -(-n // count)
        stats.samples += n
        stats.samples_lost += lost
        self._next = index + n
        self._next32 = (index32 + n) % _WRAP
        self._remember(index32, count, crcs)
        return Frame(index, samples, lost, restart, count)

    def _remember(self, index32: int, count: int, crcs: list[int]) -> None:
        """Keep the CRCs of the run just placed, forgetting the runs wholly more than ``duplicate_window`` samples behind."""
        runs, nxt, window = self._runs, self._next32, self._duplicate_window
        runs.append((index32, count, crcs))
        while runs and (nxt - runs[0][0] - (len(runs[0][2]) - 1) * runs[0][1]) % _WRAP > window:
            runs.popleft()

    def _placed(self, index32: int) -> int | None:
        """The CRC of the frame placed at board index ``index32`` in the last ``duplicate_window`` samples (the newest such
        frame), or None."""
        if (self._next32 - index32) % _WRAP > self._duplicate_window:
            return None
        for first, count, crcs in reversed(self._runs):
            k, off = divmod((index32 - first) % _WRAP, count)
            if not off and k < len(crcs):
                return crcs[k]
        return None


def _split(runs: list[Frame]) -> list[Frame]:
    """Runs cut back into one :class:`Frame` per frame on the wire (views of the run's samples)."""
    out: list[Frame] = []
    for run in runs:
        c = run.frame_count or run.samples.shape[0]
        for j in range(0, run.samples.shape[0], c):
            first = j == 0
            out.append(Frame(run.index + j, run.samples[j:j + c], run.lost if first else 0, run.restart and first, c))
    return out
