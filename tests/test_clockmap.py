"""The sensor-to-host time map (tactiled.board.clockmap): monotonic, smooth, and close to the truth after settling.

Arrivals are synthetic (a board whose crystal is 0.05 % fast, reads every 2-5 ms, 2-6 ms of
transport, a first read 31.8 ms later than the rest, host stalls of 0.3 s and 2 s), and the
stamps are computed exactly as a samples-topic subscriber does: ``index_mono + k / fs_clock``
with the daemon's rounding.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np
import pytest

from tactiled.board.clockmap import ClockMap, wall_offset

FS, TRUE_FS, T0 = 20_000.0, 20_010.0, 100.0
SETTLE_S = 3.0  # docs/integrations.md and docs/messages.md state this settling time


def stream(seed: int, seconds: float = 30.0) -> tuple[np.ndarray, np.ndarray, ClockMap]:
    """(row stamps, row indices) of every published batch, and the map."""
    rng = np.random.default_rng(seed)
    clock = ClockMap(FS)
    end = int(0.035 * TRUE_FS)
    t = T0 + 0.035 + 0.002 + 0.0318  # an early burst: 35 ms of samples in the first read, 31.8 ms late
    a = 0
    stamps, rows = [], []
    stalled = False
    while t < T0 + seconds:
        clock.observe(end, t)
        if end > a and (end - a >= 500 or rng.random() < 0.3):  # batches of any size, never past what arrived
            mono, rate = round(clock.mono(a), 6), round(clock.rate(a, end), 3)  # as the daemon publishes them
            stamps.append(mono + np.arange(end - a) / rate)
            rows.append(np.arange(a, end))
            a = end
        t += 0.002 + rng.uniform(0, 0.003) + (0.3 if rng.random() < 0.002 else 0.0)
        if not stalled and t > T0 + 15:
            t, stalled = t + 2.0, True  # a 2 s host stall: one late read, then the backlog
        end = max(end, int((t - T0 - 0.002 - rng.uniform(0, 0.004)) * TRUE_FS))
    return np.concatenate(stamps), np.concatenate(rows), clock


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_stamps_never_go_back_and_settle_near_the_truth(seed: int) -> None:
    stamps, rows, clock = stream(seed)
    assert np.array_equal(rows, np.arange(len(rows)))
    steps = np.diff(stamps)
    assert steps.min() > (1 - clock.max_slew) / TRUE_FS - 2e-6  # strictly increasing: half a sample period at the least
    err = stamps - (T0 + rows / TRUE_FS)  # the truth plus the transport: 2 ms at least
    settled = rows / TRUE_FS > SETTLE_S
    assert err[0] > 0.03  # the first read was late: the map starts late ...
    assert err[settled].min() >= 0.0015 and err[settled].max() <= 0.0025  # ... and is within 0.5 ms of the smallest transport after 3 s
    assert abs(clock.fs - TRUE_FS) < 1.0 and clock.resets == 0 and clock.steps == 0
    local = 1 / steps[settled[1:]]  # samples per second, row to row (1 us rounding of index_mono is 2 % of a period)
    assert local.min() > TRUE_FS * 0.97 and local.max() < TRUE_FS * 1.03


def test_once_settled_the_map_runs_within_half_a_percent_of_the_estimate() -> None:
    _, _, clock = stream(0)
    ki, kt = np.array(clock._ki), np.array(clock._kt)
    slope = np.diff(kt) / np.diff(ki) * clock.fs  # relative to the rate now (it moved by ppm since)
    late = ki[1:] > SETTLE_S * TRUE_FS
    assert (slope > 0).all() and slope.min() >= 1 - clock.max_slew - 1e-4
    assert np.all(np.abs(slope[late] - 1) <= 0.005)


def test_times_handed_out_never_change() -> None:
    clock = ClockMap(FS)
    given: dict[int, float] = {}
    rng = np.random.default_rng(3)
    for k in range(1, 3000):
        end = k * 40
        clock.observe(end, T0 + end / TRUE_FS + 0.002 + rng.uniform(0, 0.01) + (0.04 if k == 1 else 0.0))
        i = int(rng.integers(0, end + 1))
        given.setdefault(i, clock.mono(i))
    assert max(abs(clock.mono(i) - t) for i, t in given.items()) < 1e-8


def test_a_restart_steps_forward_and_an_index_jump_squeezes_without_going_back() -> None:
    clock = ClockMap(FS)
    for k in range(1, 500):
        clock.observe(k * 400, T0 + k * 400 / FS + 0.002)
    before = clock.mono(499 * 400)
    for k in range(100):  # a board restart that continues the timeline: late by about 60 s, for more than persist_s
        clock.observe(500 * 400 + k * 400, T0 + 70.0 + k * 0.02)
    assert clock.resets == 1 and clock.steps == 1
    assert abs(clock.mono(599 * 400) - (T0 + 71.98)) < 0.01 and clock.mono(500 * 400) > before
    last = clock.mono(599 * 400)
    clock.observe(10**9, T0 + 73.0)  # the index leaps ahead of the time that passed
    assert clock.steps == 2 and abs(clock.mono(10**9) - (T0 + 73.0)) < 1e-6
    assert last < clock.mono(10**6) < clock.mono(10**9)


def test_unix_times_follow_the_wall_clock_slowly_and_its_steps_at_once() -> None:
    clock = ClockMap(FS)
    wall = 1.7e9
    for k in range(1, 201):
        clock.observe(k * 200, T0 + k * 200 / FS + 0.002, wall + (0.001 if k > 100 else 0.0))  # NTP moved the wall clock 1 ms
    mono, unix = clock.host(200 * 200)
    assert 0 < unix - mono - wall < 0.001  # followed at most 500 ppm: 1 s of map moves it 0.5 ms
    assert np.all(np.diff([clock.host(i)[1] for i in range(0, 200 * 200, 100)]) > 0)
    clock.observe(201 * 200, T0 + 201 * 200 / FS + 0.002, wall - 5.0)  # a wall-clock step back by 5 s is followed at once
    assert abs(clock.host(201 * 200)[1] - clock.mono(201 * 200) - (wall - 5.0)) < 1e-6


def test_the_wall_offset_is_read_between_two_monotonic_reads_and_a_preempted_triple_is_not_used() -> None:
    """A thread preempted for 40 ms between reading the two clocks (a loaded host) put 40 ms into the offset, which the unix
    map then took for a wall-clock step (over its 0.1 s) or slewed towards."""
    offset = 1.7e9  # the true time.time() - time.monotonic()
    mono = iter([10.0, 10.040, 10.1, 10.1 + 4e-7])  # the first triple preempted after its monotonic read; no third read
    wall = iter([offset + 10.040, offset + 10.1 + 2e-7])
    assert abs(wall_offset(3, lambda: next(mono), lambda: next(wall)) - offset) < 1e-6  # the second, tight triple: stopped there
    assert abs(wall_offset() - (time.time() - time.monotonic())) < 0.01  # the real clocks


def test_before_any_arrival_there_is_no_time() -> None:
    clock = ClockMap(FS)
    assert not clock.ready and clock.rate(0, 100) == FS
    with pytest.raises(ValueError):
        clock.mono(0)


def test_a_full_map_drops_its_oldest_knots_and_stays_monotonic(monkeypatch: pytest.MonkeyPatch) -> None:
    import tactiled.board.clockmap as cm

    monkeypatch.setattr(cm, "MAX_KNOTS", 64)
    _, rows, clock = stream(4, seconds=10.0)
    assert 48 <= len(clock._ki) <= 64  # bounded: the oldest quarter went each time it filled
    assert clock._ki[0] > 0  # early knots are gone: their indices are extrapolated at the rate then
    probe = np.linspace(0, rows[-1], 2001).astype(np.int64)
    times = np.array([clock.mono(int(i)) for i in probe])
    assert np.all(np.isfinite(times)) and np.all(np.diff(times) > 0)


class _LaggingSource:
    """What the daemon reads from, as :class:`~tactiled.board.serialsource.SerialSource` feeds it: a 0.05 %-fast board's
    frames (20 samples, 2-4 ms of transport), read every 10 ms, handed over every 40 ms, each hand-over consumed ``lag``
    seconds after it was made (an analysis that lags, held, then catching up). ``arrival`` is the newest read when an item
    is consumed; ``read_at`` is each byte's own read."""

    def __init__(self, on_bytes: Callable[[bytes], Awaitable[None]], lag: Callable[[float], float], seconds: float) -> None:
        from tactiled.board.frames import encode_frame
        from tactiled.board.serialsource import Reads

        self.on_bytes, self.connected, self.reconnects, self.errors, self.shed_bytes, self.discarded_at_start = on_bytes, False, 0, 0, 0, 0
        self.arrival, self.alive_at, self.hand_over_s, self.behind = 0.0, 0.0, 0.04, 0.0
        rng = np.random.default_rng(5)
        frames = int(seconds * TRUE_FS) // 20
        block = np.zeros((20, 2), dtype=np.int16)
        came = np.maximum.accumulate(T0 + np.arange(1, frames + 1) * 20 / TRUE_FS + 0.002 + rng.uniform(0, 0.002, frames))  # in order
        self.read_times = T0 + 0.01 * np.arange(1, int(seconds / 0.01) + 2) + rng.uniform(0, 0.0005, int(seconds / 0.01) + 1)
        read_of = np.searchsorted(self.read_times, came)  # the first read at or after a frame came returns it
        reads = [b"".join(encode_frame(f * 20, block) for f in np.flatnonzero(read_of == k)) for k in range(len(self.read_times))]
        self.items = [(Reads.join(reads[k:k + 4], list(self.read_times[k:k + 4])), self.read_times[min(k + 3, len(reads) - 1)])
                      for k in range(0, len(reads), 4)]  # (reads, when handed over)
        self.lag = lag
        self.current = self.items[0][0]
        self.sample_read = np.repeat(self.read_times, [len(r) // 92 * 20 for r in reads])  # each sample's own read

    def read_at(self, offset: int) -> float:
        return self.current.time_at(offset)

    def request_stop(self) -> None:
        pass

    async def run(self) -> None:
        for reads, handed in self.items:
            consumed = handed + self.lag(handed - T0)
            self.current, self.arrival = reads, self.read_times[np.searchsorted(self.read_times, consumed, "right") - 1]
            await self.on_bytes(reads.data)


def _daemon_map(tmp: Any, lag_s: float, held_s: float) -> tuple[ClockMap, _LaggingSource]:
    """The clock map of a daemon fed by a :class:`_LaggingSource` whose consumer lags ``lag_s`` for ``held_s`` from 4 s on."""
    from tactiled.config import Config
    from tactiled.service.daemon import Daemon

    def lag(t: float) -> float:  # none, then lag_s reached at half speed, held, and drained at twice the input's speed
        return float(np.clip(min(t - 4.0, lag_s, lag_s - 0.5 * (t - 4.0 - lag_s - held_s)), 0.0, None))

    box: list[_LaggingSource] = []

    def factory(on_bytes: Callable[[bytes], Awaitable[None]], on_state: Callable[[str, str], None]) -> _LaggingSource:
        box.append(_LaggingSource(on_bytes, lag, LAG_RUN_S))
        return box[0]

    daemon = Daemon(Config().override({"publish.endpoint": f"ipc://{tmp}/pub", "sensor.fs": FS}), None, source_factory=factory)
    asyncio.run(daemon.run())
    return daemon.clock, box[0]


LAG_RUN_S = 11.0  # 3 s to settle, 1 s more, the longest lag (1.5 s reached in 1.5 s, held 3 s, drained in 3 s), 1 s after


@pytest.fixture(scope="module")
def unlagged(tmp_path_factory: pytest.TempPathFactory) -> ClockMap:
    return _daemon_map(tmp_path_factory.mktemp("unlagged"), 0.0, 0.0)[0]


@pytest.mark.parametrize(("lag_s", "held_s"), [(0.6, 1.2), (1.5, 3.0)])
def test_a_lagging_analysis_changes_nothing_in_the_map(tmp_path: Any, unlagged: ClockMap, lag_s: float, held_s: float) -> None:
    """The daemon feeds the map each slice's own read time, so an analysis ``lag_s`` behind for ``held_s`` (the daemon says
    "overloaded: input 1.43 s behind") gives the very map it would have made keeping up. Fed the newest read's time (before
    the fix), the map took the lag for a board restart (a reset, two steps): stamps up to 0.58 s and 1.5 s after the
    samples' own read, local rates of 1 264 Hz to 41 kHz and of 746 Hz to 44 kHz."""
    clock, source = _daemon_map(tmp_path, lag_s, held_s)
    rows = np.arange(0, len(source.sample_read) - 800, 800)  # a published batch's first row every 40 ms
    stamps = np.array([clock.mono(int(i)) for i in rows])
    rate = np.array([clock.rate(int(a), int(a) + 800) for a in rows])
    late = stamps - source.sample_read[rows]  # after the read that returned the sample: never
    settled = rows > SETTLE_S * TRUE_FS
    err = (stamps - (T0 + rows / TRUE_FS))[settled]  # the truth plus the transport: 2 ms at least
    figures = (f"resets {clock.resets}, steps {clock.steps}, late up to {late.max() * 1e3:.1f} ms, settled error {err.min() * 1e3:.2f}.."
               f"{err.max() * 1e3:.2f} ms, local rate {rate[settled[:len(rate)]].min():.0f}..{rate[settled[:len(rate)]].max():.0f} Hz")
    assert clock.resets == 0 and clock.steps == 0, figures
    assert late.max() <= 0.0, figures
    assert np.array_equal(stamps, [unlagged.mono(int(i)) for i in rows]), figures  # the map of a daemon keeping up, exactly
    assert np.array_equal(rate, [unlagged.rate(int(a), int(a) + 800) for a in rows]), figures
    # the map's own accuracy is tested above (finer reads); with 1 ms frames read every 10 ms and handed over every 40 ms:
    assert err.min() > 0.0 and err.max() < 0.004 and np.all(np.abs(rate[settled[:len(rate)]] / TRUE_FS - 1) < 0.02), figures


def test_each_byte_handed_over_keeps_the_time_of_its_own_read() -> None:
    from tactiled.board.serialsource import Reads

    item = Reads.join([b"ab", b"cde", b"f"], [1.0, 2.0, 3.0])  # three reads handed over together
    assert item.data == b"abcdef" and [item.time_at(i) for i in range(6)] == [1.0, 1.0, 2.0, 2.0, 2.0, 3.0]
    assert Reads.join([b"xy"], [5.0]).time_at(1) == 5.0


@pytest.mark.parametrize("true_fs", [8_000.0, 16_000.0, 30_000.0])
def test_a_board_slower_or_faster_than_nominal_is_measured(true_fs: float) -> None:
    """A board at 8 kHz on a port configured for 16 kHz fell behind the nominal line by 0.5 s a second; once 0.5 s behind
    for 1 s the map took it for a restart and began again, before the 2 s the rate takes to measure: fs stayed the
    nominal one, and the daemon never said the board's rate (an outside audit). Faster boards were measured."""
    nominal = 16_000.0
    clock = ClockMap(nominal)
    for k in range(1, 400):  # 8 s of reads every 20 ms, 2 ms of transport
        t = T0 + k * 0.02
        clock.observe(int((t - T0 - 0.002) * true_fs), t)
    assert abs(clock.fs - true_fs) < 0.01 * true_fs and clock.resets == 0
