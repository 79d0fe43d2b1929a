"""The cheaper numerical paths of replay give the old paths' numbers bit for bit: medians sorted against the partition
they replace, the detector's medians of three taken ahead, and its blocks in any size, with or without validity flags;
on random, silent, saturated, tied and non-finite inputs."""

from __future__ import annotations

import dataclasses
from collections import deque

import numpy as np
import numpy.typing as npt
import pytest

from tactiled.config import Config
from tactiled.core.detect import SlideDetector, _median3, median3_runs
from tactiled.core.spikes import median_last
from tactiled.sim.physics import SensorSimulator, SimParams, default_surfaces


def median_by_partition(a: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """The median along the last axis as computed before (one partition, the largest of the lower half): the reference."""
    n = a.shape[-1]
    k = n // 2
    p = np.partition(a, k, axis=-1)
    if n % 2:
        return p[..., k]  # type: ignore[no-any-return]
    return p[..., :k].max(axis=-1) / 2 + p[..., k] / 2  # type: ignore[no-any-return]


@pytest.mark.parametrize("n", [1, 2, 3, 20, 21, 256, 257, 5000, 5001])
def test_medians_sorted_or_partitioned_are_numpys(n: int) -> None:
    rng = np.random.default_rng(n)
    counts = rng.integers(-32768, 32768, size=(6, 2, n)).astype(np.int16)
    counts[1] = 0
    counts[2] = 32767
    counts[3, :, ::2] = -32768
    counts[4, 0] = rng.integers(-3, 3, size=n)  # many ties
    vpc = 5 / 32768
    volts = counts * vpc
    expected = np.median(volts, axis=-1)
    assert median_last(volts).tobytes() == expected.tobytes()
    assert median_last(volts.copy(), in_place=True).tobytes() == expected.tobytes()
    x = rng.standard_normal((5, n))
    x[1, : n // 2 + 1] = np.nan  # NaN past the middle: numpy's median is NaN
    x[2, 0] = np.nan
    x[3] = -0.0
    assert median_last(x).tobytes() == median_by_partition(x).tobytes()  # NaN sorted last, as the partition put it
    assert median_last(x.copy(), in_place=True).tobytes() == median_by_partition(x).tobytes()


def test_medians_of_three_taken_ahead_are_the_detectors() -> None:
    rng = np.random.default_rng(2)
    for n in (0, 1, 2, 3, 50):
        v = (np.abs(rng.standard_normal(n)) * 10.0 ** rng.integers(-20, 20, n)).tolist()
        v[n // 2: n // 2 + 3] = [1.5] * len(v[n // 2: n // 2 + 3])  # ties
        runs = median3_runs(v)
        assert runs[:2] == v[:2]
        assert runs[2:] == [_median3(deque(v[i - 2: i + 1], maxlen=3)) for i in range(2, n)]


def _scene(seconds: float, seed: int) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.bool_], float]:
    p = SimParams()
    sim = SensorSimulator(p, seed)
    n = int(seconds * p.fs)
    sim.schedule_random(default_surfaces(), n)
    volts = sim.read(n) * p.volts_per_count
    valid = np.ones(n, dtype=bool)
    valid[n // 3: n // 3 + 40] = False  # a short loss
    valid[n // 2: n // 2 + 30000] = False  # a long one (skipped in constant time)
    volts[~valid] = 0.0
    volts[2 * n // 3: 2 * n // 3 + 5000] = 0.0  # digital silence
    return volts, valid, p.fs


def _detect(volts: npt.NDArray[np.float64], valid: npt.NDArray[np.bool_] | None, fs: float, block: int,
            gap: tuple[int, int] | None = None) -> list[tuple[object, ...]]:
    """Every event of the detector fed ``volts`` in blocks of ``block`` rows (those inside ``gap`` never fed), then its
    state at the end (envelope, floor: the floats its decisions compare)."""
    det = SlideDetector(Config().detector, fs, 2)
    out: list[tuple[object, ...]] = []
    for lo in range(0, volts.shape[0], block):
        hi = min(lo + block, volts.shape[0])
        if gap is not None and lo >= gap[0] and hi <= gap[1]:
            continue  # an index gap: those rows never fed
        out += [(type(e).__name__, *dataclasses.astuple(e)) for e in det.feed(lo, volts[lo:hi], None if valid is None else valid[lo:hi])]
    out += [(type(e).__name__, *dataclasses.astuple(e)) for e in det.finish()]
    return [*out, ("state", det.envelope, det.floor, det.sliding)]


def test_the_detector_in_any_block_size_with_or_without_validity_flags() -> None:
    """The same events and end state whatever the blocks (the front end reads across blocks without joining them), with
    flags or None for all valid, and with an index gap or its rows flagged lost."""
    volts, valid, fs = _scene(40, 4)
    whole = _detect(volts, valid, fs, volts.shape[0])
    assert any(e[0] == "Offset" for e in whole)
    for block in (99, 100, 777, 800, 16384, 65536):
        assert _detect(volts, valid, fs, block) == whole, block
    clean = _scene(20, 5)[0]
    flags = np.ones(clean.shape[0], dtype=bool)
    assert _detect(clean, None, fs, 800) == _detect(clean, flags, fs, 800) == _detect(clean, None, fs, 65536) == _detect(clean, flags, fs, 777)
    gapped = clean.copy()
    flags[8000:16000] = False
    gapped[~flags] = 0.0
    assert _detect(gapped, None, fs, 800, gap=(8000, 16000)) == _detect(gapped, flags, fs, 800)
