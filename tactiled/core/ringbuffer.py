"""A fixed-capacity ring buffer of multichannel samples addressed by absolute sample index.

Samples keep their absolute (64-bit) index; reads by index range work across the wrap.
Gaps (lost samples) are written as zeros and marked invalid, so anything downstream knows
a window is incomplete. A range already overwritten, or not yet written, is a clear error.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from tactiled.errors import NotYetWrittenError, OverwrittenError


def check_range(start: int, stop: int, oldest: int, end: int) -> None:
    """Raise unless samples [start, stop) (absolute indices) are held, i.e. within [oldest, end): ValueError if the range
    is reversed, :class:`NotYetWrittenError` past ``end``, :class:`OverwrittenError` before ``oldest``."""
    if stop < start:
        raise ValueError(f"range [{start}, {stop}) is reversed")
    if stop > end:
        raise NotYetWrittenError(f"samples [{start}, {stop}) not yet written (newest is {end - 1})")
    if start < oldest:
        raise OverwrittenError(f"samples [{start}, {stop}) already overwritten (oldest held is {oldest})")


class RingBuffer:
    """``capacity`` samples of ``channels`` channels of ``dtype``, plus a validity mask."""

    def __init__(self, capacity: int, channels: int, dtype: npt.DTypeLike = np.int16) -> None:
        if capacity < 1 or channels < 1:
            raise ValueError("capacity and channels must be >= 1")
        self.capacity = capacity
        self.channels = channels
        self._data = np.zeros((capacity, channels), dtype=dtype)
        self._valid = np.zeros(capacity, dtype=bool)
        self._start: int | None = None  # absolute index of the first sample ever written
        self._end = 0  # absolute index one past the newest sample

    @property
    def end(self) -> int:
        """Absolute index one past the newest sample (0 before any write)."""
        return self._end

    @property
    def oldest(self) -> int:
        """Absolute index of the oldest sample still held."""
        if self._start is None:
            return 0
        return max(self._start, self._end - self.capacity)

    def write(self, index: int, samples: npt.NDArray[np.generic], valid: npt.NDArray[np.bool_] | None = None) -> int:
        """Append ``samples`` (n, C) starting at absolute ``index`` >= :attr:`end`.

        A gap between :attr:`end` and ``index`` is filled with zeros marked invalid.
        ``valid`` (n,) marks samples that carry no data. Returns the number of gap samples.
        """
        if samples.ndim != 2 or samples.shape[1] != self.channels:
            raise ValueError(f"samples must have shape (n, {self.channels}); got {samples.shape}")
        if self._start is None:
            self._start = index
            self._end = index
        if index < self._end:
            raise ValueError(f"write at {index} overlaps samples already written up to {self._end}")
        gap = index - self._end
        if gap:
            self._fill(self._end, min(gap, self.capacity), None, False)
            self._end = index
        self._fill(index, samples.shape[0], samples, valid)
        self._end = index + samples.shape[0]
        return gap

    def _fill(self, index: int, n: int, samples: npt.NDArray[np.generic] | None, valid: npt.NDArray[np.bool_] | bool | None) -> None:
        if samples is not None and n > self.capacity:
            samples = samples[-self.capacity:]
            if isinstance(valid, np.ndarray):
                valid = valid[-self.capacity:]
            index += n - self.capacity
            n = self.capacity
        n = min(n, self.capacity)
        pos = index % self.capacity
        first = min(n, self.capacity - pos)
        for dst, lo, hi in ((pos, 0, first), (0, first, n)):
            if hi <= lo:
                continue
            sl = slice(dst, dst + hi - lo)
            if samples is None:
                self._data[sl] = 0
            else:
                self._data[sl] = samples[lo:hi]
            if valid is None:
                self._valid[sl] = samples is not None
            elif isinstance(valid, np.ndarray):
                self._valid[sl] = valid[lo:hi]
            else:
                self._valid[sl] = valid

    def _check(self, start: int, stop: int) -> None:
        check_range(start, stop, self.oldest, self._end)

    def _take(self, arr: npt.NDArray[np.generic], start: int, stop: int) -> npt.NDArray[np.generic]:
        lo, n = start % self.capacity, stop - start  # n <= capacity (checked): at most two slices, no index array
        if lo + n <= self.capacity:
            return arr[lo: lo + n].copy()
        return np.concatenate([arr[lo:], arr[: lo + n - self.capacity]])

    def read(self, start: int, stop: int) -> tuple[npt.NDArray[np.generic], npt.NDArray[np.bool_]]:
        """Copy of samples [start, stop) as (n, C) and their validity (n,) bool."""
        self._check(start, stop)
        return self._take(self._data, start, stop), self._take(self._valid, start, stop)  # type: ignore[return-value]

    def lost_in(self, start: int, stop: int) -> int:
        """How many samples in [start, stop) carry no data."""
        self._check(start, stop)
        return int(stop - start - np.count_nonzero(self._take(self._valid, start, stop)))


class HeldSamples:
    """The read side of a :class:`RingBuffer` over samples held whole in memory (offline replay of a recording): reads are
    views and nothing is ever overwritten. :attr:`end` (absolute index one past the samples counted as written) is set
    by the caller as the replay advances, so reads past it fail as a ring's would."""

    def __init__(self, index: int, samples: npt.NDArray[np.generic], valid: npt.NDArray[np.bool_] | None = None) -> None:
        """``samples`` (n, C) and ``valid`` (n,) (None: all valid) whose first row has absolute ``index``."""
        self.first = index
        self.samples = samples
        self.valid = valid
        self.end = index

    def read(self, start: int, stop: int) -> tuple[npt.NDArray[np.generic], npt.NDArray[np.bool_]]:
        """Samples [start, stop) as (n, C) and their validity (n,) bool: views, not copies (but for all-valid samples)."""
        check_range(start, stop, self.first, self.end)
        rows = slice(start - self.first, stop - self.first)
        return self.samples[rows], np.ones(stop - start, dtype=bool) if self.valid is None else self.valid[rows]
