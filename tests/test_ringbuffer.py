from __future__ import annotations

import numpy as np
import pytest

from tactiled.core.ringbuffer import RingBuffer
from tactiled.errors import NotYetWrittenError, OverwrittenError


def test_reads_across_the_wrap() -> None:
    ring = RingBuffer(100, 2)
    data = np.arange(500, dtype=np.int16).reshape(250, 2)
    for i in range(0, 250, 30):
        ring.write(1000 + i, data[i:i + 30])
    got, valid = ring.read(1000 + 170, 1000 + 250)
    assert np.array_equal(got, data[170:250]) and valid.all()
    assert ring.oldest == 1150 and ring.end == 1250


def test_errors_for_overwritten_and_future() -> None:
    ring = RingBuffer(10, 1)
    ring.write(0, np.zeros((25, 1), dtype=np.int16))
    with pytest.raises(OverwrittenError):
        ring.read(5, 20)
    with pytest.raises(NotYetWrittenError):
        ring.read(20, 26)
    with pytest.raises(ValueError):
        ring.write(10, np.zeros((1, 1), dtype=np.int16))


def test_gaps_are_marked_lost() -> None:
    ring = RingBuffer(50, 1)
    ring.write(0, np.ones((10, 1), dtype=np.int16))
    assert ring.write(15, np.ones((10, 1), dtype=np.int16)) == 5
    got, valid = ring.read(5, 20)
    assert valid.tolist() == [True] * 5 + [False] * 5 + [True] * 5
    assert got[5:10].sum() == 0
    assert ring.lost_in(0, 25) == 5
    mask = np.array([True, False, True])
    ring.write(25, np.ones((3, 1), dtype=np.int16), mask)
    assert ring.lost_in(25, 28) == 1


def test_huge_gap_and_huge_write() -> None:
    ring = RingBuffer(8, 1)
    ring.write(0, np.ones((3, 1), dtype=np.int16))
    ring.write(1000, np.arange(20, dtype=np.int16).reshape(20, 1))
    got, valid = ring.read(1012, 1020)
    assert got[:, 0].tolist() == list(range(12, 20)) and valid.all()
