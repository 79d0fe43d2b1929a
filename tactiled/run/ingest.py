"""The ingest core, sans-IO: bytes → frames → channel and gap policies → batches → pipeline → events.

One path for every driver: the daemon feeds it the bytes it reads from the port,
``tactiled replay x.bin`` the bytes of a raw capture, tests bytes from memory; a recorder
takes the batches. Nothing here does I/O or reads a clock.

- **Decoder** (:class:`~tactiled.board.frames.FrameDecoder`): frames in bulk, CRC-checked.
- **Channel policy**: an intact frame whose channel count is not the sensor's is counted in
  ``stats.channel_errors`` and skipped; it never moves the sample index.
- **Gap policy**: a forward jump of the index is lost samples, however long, as long as the
  board's 32-bit counter can say how many (below 2**31, or ``max_gap`` if set): the batch after it
  carries ``lost`` and its index jumps with it (nothing is allocated for the gap; the pipeline
  marks the samples invalid, and skips a gap longer than the ring in constant time). A jump back
  that is not a repeat of a frame already placed (a board reset, even to a small index), or a
  forward jump beyond ``max_gap``, is a board restart or a resync. It costs O(1): counted in
  ``stats.restarts``, the host's timeline continues where it was, and the batch after it carries
  ``restart`` so the pipeline ends the stream (a slide in progress ends there) before going on.
  Repeated frames are dropped and counted in ``stats.duplicates``.
- **Batches**: decoded frames are held until at least ``min_batch`` samples are there, then
  handed out as contiguous :class:`Batch` es (the pipeline's cost is mostly per call).
- **End of stream**: :meth:`Ingest.flush`.

The pipeline is joined to it by :class:`tactiled.run.stream.Stream`, the one object every driver uses.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from tactiled.board.frames import DecoderStats, Frame, FrameDecoder


@dataclass(slots=True)
class Batch:
    """Contiguous samples: ``samples`` (n, C) int16 counts whose first has host index ``index``.

    ``lost``: samples missing between the previous batch's end and ``index``;
    ``restart``: the board restarted (or the stream resynchronised) just before ``index``.
    """

    index: int
    samples: npt.NDArray[np.int16]
    lost: int = 0
    restart: bool = False

    @property
    def end(self) -> int:
        """Host index one past the last sample."""
        return self.index + self.samples.shape[0]


def max_gap_for(ring_seconds: float, fs: float) -> int:
    """The ring's length, samples: a longer gap leaves nothing to analyse across it (it ends a slide in progress)."""
    return max(1, round(ring_seconds * fs))


class Ingest:
    """Bytes in, :class:`Batch` es out; counters in :attr:`stats` (see the module docstring)."""

    def __init__(self, channels: int, *, max_gap: int | None = None, min_batch: int = 1, duplicate_window: int = 65536) -> None:
        self.channels = channels
        self.min_batch = max(1, int(min_batch))
        self.decoder = FrameDecoder(duplicate_window, channels=channels, max_gap=max_gap)
        self._pending: list[Frame] = []
        self._pending_n = 0

    @property
    def stats(self) -> DecoderStats:
        """The decoder's counters (samples, lost, CRC errors, restarts, ...)."""
        return self.decoder.stats

    @property
    def held(self) -> int:
        """Samples decoded but not yet handed out (waiting for ``min_batch``)."""
        return self._pending_n

    def feed(self, data: bytes | bytearray | memoryview) -> list[Batch]:
        """Decode ``data``; the batches it completes (none until ``min_batch`` samples are held)."""
        runs = self.decoder.feed_runs(data)
        if runs:
            self._pending += runs
            self._pending_n += sum(r.samples.shape[0] for r in runs)
        return self._release() if self._pending_n >= self.min_batch else []

    def flush(self) -> list[Batch]:
        """End of stream: whatever is held, and frames the decoder can still complete."""
        self._pending += self.decoder.flush_runs()
        return self._release()

    def _release(self) -> list[Batch]:
        runs, self._pending, self._pending_n = self._pending, [], 0
        return join_runs(runs)


def join_runs(runs: list[Frame]) -> list[Batch]:
    """Decoded runs (increasing host index) joined into as few contiguous batches as possible."""
    groups: list[tuple[Frame, list[npt.NDArray[np.int16]]]] = []
    end = None
    for r in runs:
        if groups and r.index == end and not r.restart:
            groups[-1][1].append(r.samples)
        else:
            groups.append((r, [r.samples]))
        end = r.index + r.samples.shape[0]
    return [Batch(first.index, np.concatenate(parts) if len(parts) > 1 else parts[0], first.lost, first.restart) for first, parts in groups]


@dataclass
class BatchCollector:
    """Batches kept in memory as one contiguous recording: index gaps become zero rows listed in ``lost``.

    ``limit``: keep at most this many rows (then :attr:`done`). A restart continues the timeline,
    so nothing here grows with the size of an index jump. ``max_lost``: keep at most this many zero
    rows for gaps in all; a gap that would go over it ends the rows kept (:attr:`truncated`, then
    :attr:`done`), so a few bytes claiming huge gaps cost no more than the budget. Every gap is
    still counted, kept or not, in :attr:`samples_lost` (and the samples after it in :attr:`samples_seen`).
    """

    channels: int
    limit: int | None = None
    max_lost: int | None = None
    first_index: int | None = None
    restarts: int = 0
    truncated: bool = False
    samples_seen: int = 0
    samples_lost: int = 0
    _chunks: list[npt.NDArray[np.int16]] = field(default_factory=list)
    _lost: list[tuple[int, int]] = field(default_factory=list)
    _n: int = 0
    _n_lost: int = 0
    _next: int | None = None

    @property
    def n(self) -> int:
        """Rows kept so far, lost (zero) rows included."""
        return self._n

    @property
    def done(self) -> bool:
        """True once ``limit`` rows are kept, or a gap went over ``max_lost`` (never without either)."""
        return self.truncated or (self.limit is not None and self._n >= self.limit)

    def add(self, batch: Batch) -> None:
        """Append ``batch``'s (n, C) int16 counts, after zero rows listed as lost for any index gap before it, up to ``limit``
        rows and ``max_lost`` zero rows; the gap and the samples are counted even when no longer kept."""
        gap = 0 if self._next is None else max(0, batch.index - self._next)
        self.samples_lost += gap
        self.samples_seen += batch.samples.shape[0]
        self._next = batch.end
        if self.done:
            return
        if self.first_index is None:
            self.first_index = batch.index
        self.restarts += batch.restart
        gap = batch.index - (self.first_index + self._n)
        if gap > 0:
            if self.max_lost is not None and self._n_lost + gap > self.max_lost:
                self.truncated = True  # rows for this gap would cost more than the file could justify: keep what came before
                return
            self._n_lost += gap
            keep = gap if self.limit is None else min(gap, self.limit - self._n)
            self._append(np.zeros((keep, self.channels), dtype=np.int16), lost=True)
        self._append(batch.samples, lost=False)

    def _append(self, block: npt.NDArray[np.int16], lost: bool) -> None:
        if self.limit is not None:
            block = block[: self.limit - self._n]
        if not block.shape[0]:
            return
        if lost:
            self._lost.append((self._n, block.shape[0]))
        self._chunks.append(block)
        self._n += block.shape[0]

    def samples(self) -> npt.NDArray[np.int16]:
        """(n, C) int16: every row from the first index on, lost ones zero."""
        if not self._chunks:
            return np.zeros((0, self.channels), dtype=np.int16)
        return np.concatenate(self._chunks).astype(np.int16, copy=False)

    def lost(self) -> npt.NDArray[np.int64]:
        """(k, 2) int64 [position, count] of the lost rows."""
        return np.asarray(self._lost, dtype=np.int64).reshape(-1, 2)

    def recording(self, fs: float, volts_per_count: float, meta: dict[str, Any] | None = None) -> Any:
        """A :class:`~tactiled.files.recording.Recording` of what was collected."""
        from tactiled.files.recording import Recording

        return Recording(samples=self.samples(), fs=fs, volts_per_count=volts_per_count, first_index=self.first_index or 0,
                         lost=self.lost(), meta=dict(meta or {}))
