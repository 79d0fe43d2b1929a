"""The cheaper numerical paths of replay give the old paths' numbers bit for bit: the band statistics in numpy against
the per-row arithmetic they replace, medians sorted or chosen among int16 counts against ``np.median``, counts of True
against ``np.count_nonzero``, the detector's medians of three taken ahead, its blocks in any size, spike removal in
place, and int16 windows (medians from the counts, no scaling check) against the same windows given in volts; on random,
silent, constant, saturated, spiky, tiny and non-finite inputs."""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections import deque
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
import pytest
import pywt

from tactiled.config import Config
from tactiled.core.analysis import Analyser, AnalysisSettings, clipped_fractions
from tactiled.core.detect import SlideDetector, _median3, median3_runs
from tactiled.core.events import DetectorEvent
from tactiled.core.features import FeaturePlan, band_stats, family_names, row_dots
from tactiled.core.spikes import median_last, remove_spikes_many, row_counts
from tactiled.sim.physics import SensorSimulator, SimParams, default_surfaces

STATS = ("mean", "sd", "energy", "rms", "skew", "kurt")


def band_stats_per_row(c: npt.NDArray[np.float64], stats: Sequence[str]) -> dict[str, npt.NDArray[np.float64]]:
    """The band statistics as computed before (each row's arithmetic on Python floats): the reference."""
    n = c.shape[1]
    means = [v / n for v in c.sum(axis=1).tolist()]
    d = c - np.array(means)[:, None]
    m2s = (row_dots(d, d) / n).tolist()
    highs, lows = c.max(axis=1).tolist(), c.min(axis=1).tolist()
    energies = row_dots(c, c).tolist()
    cubes = ((d * d * d).sum(axis=1) / n).tolist()
    fourths = (((d * d) ** 2).sum(axis=1) / n).tolist()
    out: dict[str, list[float]] = {s: [] for s in stats}
    for mean, m2, high, low, energy, cube, fourth in zip(means, m2s, highs, lows, energies, cubes, fourths, strict=True):
        scale = max(abs(mean), high, -low, 1e-300)
        flat = m2 <= (1e-12 * scale) * (1e-12 * scale)
        for s in stats:
            if s == "mean":
                value = mean
            elif s == "sd":
                value = 0.0 if flat or n < 2 else math.sqrt(m2 * n / (n - 1))
            elif s == "energy":
                value = energy
            elif s == "rms":
                value = math.sqrt(energy / n)
            elif s == "skew":
                value = 0.0 if flat else cube / m2 ** 1.5
            else:
                value = 0.0 if flat else fourth / (m2 * m2)
            out[s].append(value)
    return {s: np.array(v, dtype=np.float64) for s, v in out.items()}


def median_by_partition(a: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """The median along the last axis as computed before (one partition, the largest of the lower half): the reference."""
    n = a.shape[-1]
    k = n // 2
    p = np.partition(a, k, axis=-1)
    if n % 2:
        return p[..., k]  # type: ignore[no-any-return]
    return p[..., :k].max(axis=-1) / 2 + p[..., k] / 2  # type: ignore[no-any-return]


def rows_of_every_kind(m: int, seed: int) -> npt.NDArray[np.float64]:
    """(14, m) rows: noise at several scales, silent, constant, saturated, a spike, tiny, large (the features scale larger
    windows down first), a near-constant one, NaN, inf."""
    rng = np.random.default_rng(seed)
    rows = [rng.standard_normal(m), rng.standard_normal(m) * 1e-9, np.abs(rng.standard_normal(m)) * 1e3, np.zeros(m), np.full(m, 0.3),
            np.where(np.arange(m) % 2, 1.0, -1.0) * 3.2767, rng.standard_normal(m) * 1e-3, np.full(m, 1e-310),
            rng.standard_normal(m) * 1e25, 0.5 + rng.standard_normal(m) * 1e-14, rng.standard_normal(m), rng.standard_normal(m),
            rng.standard_normal(m), rng.standard_normal(m)]
    rows[6][m // 3] = 40.0  # a spike
    rows[10][m // 2] = np.nan
    rows[11][-1] = np.inf
    rows[12][0] = np.inf
    rows[12][-1] = -np.inf
    rows[13][:] = np.nan
    return np.array(rows)


@pytest.mark.parametrize("m", [1, 2, 7, 183, 1265])
def test_band_statistics_in_numpy_are_the_per_row_arithmetic(m: int) -> None:
    c = rows_of_every_kind(m, m)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for stats in (STATS, ("sd",), ("sd", "energy", "rms"), ("kurt", "mean")):
            new, old = band_stats(c, stats), band_stats_per_row(c, stats)
            assert list(new) == list(old)
            for s in stats:
                assert new[s].tobytes() == old[s].tobytes(), (m, s)  # bit for bit, NaN and the sign of zero included


@pytest.mark.parametrize("n", [1, 2, 3, 20, 21, 256, 257, 5000, 5001])
def test_medians_sorted_partitioned_or_from_counts_are_numpys(n: int) -> None:
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
    assert median_last(counts, scale=vpc).tobytes() == expected.tobytes()
    assert median_last(volts.copy(), in_place=True).tobytes() == expected.tobytes()
    x = rng.standard_normal((5, n))
    x[1, : n // 2 + 1] = np.nan  # NaN past the middle: numpy's median is NaN
    x[2, 0] = np.nan
    x[3] = -0.0
    assert median_last(x).tobytes() == median_by_partition(x).tobytes()  # NaN sorted last, as the partition put it
    assert median_last(x.copy(), in_place=True).tobytes() == median_by_partition(x).tobytes()


def test_row_counts_are_count_nonzero() -> None:
    rng = np.random.default_rng(1)
    for shape in ((16, 2, 5000), (3, 5001), (4, 8), (0, 16), (7,), (2, 3, 0)):
        b = rng.random(shape) < 0.3
        assert np.array_equal(row_counts(b), np.count_nonzero(b, axis=-1))
        t = b[..., ::2]  # not contiguous
        assert np.array_equal(row_counts(t), np.count_nonzero(t, axis=-1))


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


class HopByHop(SlideDetector):
    """The detector with every hop through :meth:`SlideDetector._step` (no short path, no median taken ahead): the reference."""

    def _hops(self, at: int, energy: list[float], hop_valid: list[bool]) -> list[DetectorEvent]:
        events: list[DetectorEvent] = []
        unsettled = self._first + self.front.history  # type: ignore[operator]
        for env, ok in zip(energy, hop_valid, strict=True):
            events += [dataclasses.replace(e, at=at + self.hop) for e in self._step(at, env, ok and at >= unsettled)]
            at += self.hop
        return events


def _detect(volts: npt.NDArray[np.float64], valid: npt.NDArray[np.bool_] | None, fs: float, block: int,
            gap: tuple[int, int] | None = None, kind: type[SlideDetector] = SlideDetector) -> list[tuple[object, ...]]:
    """Every event of the detector fed ``volts`` in blocks of ``block`` rows (those inside ``gap`` never fed), then its
    state at the end (envelope, floor: the floats its decisions compare)."""
    det = kind(Config().detector, fs, 2)
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


@pytest.mark.parametrize("seed", [4, 8])
def test_the_detectors_short_paths_are_its_step_by_step_decisions(seed: int) -> None:
    """Slides, their quiet ends (a Pause, then an Offset or a Resume), rest and losses: the same events and end state as
    every hop through _step."""
    volts, valid, fs = _scene(40, seed)
    events = _detect(volts, valid, fs, 65536)
    assert {"Pause", "Offset", "Resume"} <= {e[0] for e in events}
    assert events == _detect(volts, valid, fs, 65536, kind=HopByHop)


def test_spike_removal_in_place_and_with_the_medians_given() -> None:
    rng = np.random.default_rng(3)
    x = rng.standard_normal((8, 2, 5000))
    x[1] = 0.0
    x[2, 0, ::397] = 40.0
    x[3, 1, 100] = np.nan
    x[4] = 1.0
    x[5, 0, :2600] = 3.0  # most of a row at one value: MAD 0
    windows = x.transpose(0, 2, 1)
    clean, counts = remove_spikes_many(windows)
    assert counts[2] > 0
    scratch = x.copy()
    clean2, counts2 = remove_spikes_many(scratch.transpose(0, 2, 1), overwrite=True, medians=median_last(x))
    assert clean2.tobytes() == clean.tobytes() and np.array_equal(counts2, counts)
    assert np.array_equal(windows, x.transpose(0, 2, 1), equal_nan=True)  # the caller's samples untouched without overwrite


def test_int16_windows_give_the_features_of_the_same_windows_in_volts() -> None:
    """The int16 path (medians chosen among the counts, volts known to be in range) against the float path (medians of
    the volts, the range checked) on random, silent, saturated, spiky, clipped and lost-sample windows, every family."""
    rng = np.random.default_rng(6)
    names = tuple(name for f in ("dwt", "psd", "tex") for name in family_names(f, 2, 20000.0))
    vpc = 5 / 32768
    w = (rng.standard_normal((10, 5000, 2)) * 3000).astype(np.int16)
    w[1] = 0
    w[2] = 32767
    w[3, ::2] = -32768
    w[4, ::397, 0] = 32767
    w[5] = 7
    w[6, :2500] = 32767
    w[7, 1000:3000:2] = 32767
    valid = np.ones((10, 5000), dtype=bool)
    valid[8, :50] = False  # filled in
    valid[9, :400] = False  # too many lost
    settings = AnalysisSettings(duration_s=0.25, names=names)
    counts = Analyser(settings, 20000.0, vpc, True).analyse_many(w, valid)
    volts = Analyser(settings, 20000.0, 1.0, False).analyse_many(w * vpc, valid)
    assert [r.reason for r in counts] == [r.reason for r in volts]
    for a, b in zip(counts, volts, strict=True):
        assert (a.features is None) == (b.features is None)
        if a.features is not None and b.features is not None:
            assert a.features.tobytes() == b.features.tobytes()
        assert {k: v for k, v in a.quality.items() if k != "saturated"} == {k: v for k, v in b.quality.items() if k != "saturated"}
    assert np.array_equal(clipped_fractions(w), [r.quality["saturated"] for r in counts])


@pytest.mark.parametrize("m", [60, 183, 338, 647, 1000, 1001, 2501])
def test_a_dwt_level_of_all_rows_at_once_is_pywavelets_row_by_row(m: int) -> None:
    """Short rows go down a level in one pywt.dwt call: the coefficients of pywt.downcoef of each row, bit for bit."""
    plan = FeaturePlan(["film1.freq.A1.sd"])
    a = np.abs(rows_of_every_kind(m, m))
    a[np.isnan(a)] = 0.0
    for part in ("a", "d"):
        expected = np.stack([pywt.downcoef(part, row, plan.wavelet, mode=plan.mode, level=1) for row in a])
        assert plan._downcoef(part, a).tobytes() == expected.tobytes(), part


@pytest.mark.parametrize("fs", [20_000.0, 2200.0, 44_100.0])
def test_band_powers_of_many_rows_are_np_interp_of_each_row(fs: float) -> None:
    """band_powers integrates every PSD row at once with np.interp's formula: each row bit for bit np.interp of that row, on
    random, silent and tiny spectra, with bands at the ends of the range and beyond the bins."""
    from tactiled.core.features import band_powers, psd_bands, psd_of

    rng = np.random.default_rng(int(fs))
    bands = [*psd_bands(fs), (0.0, 5.0), (fs / 2 - 1.0, fs / 2), (0.0, fs / 2)]
    for n in (64, 5000):
        x = rng.standard_normal((6, n)) * 10.0 ** rng.uniform(-150, 3, (6, 1))
        x[0] = 0.0
        f, p = psd_of(x, fs)
        df = f[1] - f[0]
        edges = np.concatenate((f - df / 2, [f[-1] + df / 2])).clip(min=0.0)
        for row, got in zip(p, band_powers(f, p, bands), strict=True):
            cum = np.concatenate(([0.0], np.cumsum(row) * df))
            want = np.maximum(np.interp([b[1] for b in bands], edges, cum) - np.interp([b[0] for b in bands], edges, cum), 0.0)
            assert np.array_equal(got, want)
        assert np.array_equal(band_powers(f, p[1], bands), band_powers(f, p[1:2], bands)[0])
