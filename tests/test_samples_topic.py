"""The raw samples topic: a faulty stream on a real pty, reconstructed by a subscriber, against what the board sent."""

from __future__ import annotations

import itertools
import time
from pathlib import Path

import numpy as np
from tactiled_client import BlockingSubscriber, Samples, Status

from tactiled.board.clockmap import ClockMap
from tactiled.service.samples_topic import samples_chunks
from tactiled.sim.physics import SensorSimulator, SimParams, pick_surfaces
from tactiled.sim.virtualboard import VirtualBoard, read_log
from tests.conftest import daemon_process, running, wait_for


def test_every_intact_sample_once_at_its_index_and_every_lost_one_listed(tmp_path: Path) -> None:
    link, log_path, endpoint = str(tmp_path / "tty"), tmp_path / "board.jsonl", f"ipc://{tmp_path}/pub"
    sent: list[np.ndarray] = []
    first_index = 2**32 - 40_000  # the board's 32-bit counter wraps during the test
    with open(log_path, "w") as log:
        model = SensorSimulator(SimParams(), seed=3)
        read = model.read

        def recording_read(n: int) -> np.ndarray:
            block = read(n)
            sent.append(block.copy())
            return block

        model.read = recording_read  # type: ignore[method-assign]
        board = VirtualBoard(model, pick_surfaces(3), link=link, speed=2.0, corrupt=0.01, drop=0.01, garbage=0.01, seed=3, log=log,
                             first_index=first_index)
        got: list[tuple[Samples, float]] = []
        statuses: list[Status] = []
        with daemon_process(link, endpoint, "--no-model", "--samples") as proc, \
                BlockingSubscriber(endpoint, topics=["samples", "status"], timeout=30) as sub:
            assert isinstance(sub.receive(), Status)  # the daemon is up (waiting for the port): the board starts now
            with running(board):
                def enough() -> bool:
                    msg = sub.receive()
                    if isinstance(msg, Samples):
                        got.append((msg, time.monotonic()))
                    elif isinstance(msg, Status):
                        statuses.append(msg)
                    return sum(m.n for m, _ in got) >= 6 * 20_000 and bool(statuses) and statuses[-1].clock_index is not None
                wait_for(enough, timeout=120, what="six seconds of raw samples")
                proc.terminate()
                proc.wait(30)
    assert proc.returncode == 0
    msgs = [m for m, _ in got]
    assert all(m.missed == 0 and m.extra == {} for m in msgs)
    assert [m.seq for m in msgs] == list(range(msgs[0].seq, msgs[0].seq + len(msgs)))
    # contiguous: every index from the first message on exactly once
    for a, b in itertools.pairwise(msgs):
        assert b.index == a.index + a.n + b.lost_before
    lo, hi = msgs[0].index, msgs[-1].index + msgs[-1].n
    truth = np.concatenate(sent)[lo - first_index:hi - first_index]
    rows = np.concatenate([m.counts() for m in msgs])
    valid = np.concatenate([m.valid() for m in msgs])
    assert lo - first_index < 20_000 and hi > 2**32 + 20_000  # from the board's first second, across the wrap
    assert rows.shape == truth.shape and not any(m.lost_before for m in msgs)
    assert np.array_equal(rows[valid], truth[valid])  # every intact sample, at its index
    assert not rows[~valid].any()  # lost rows are zero
    # the samples lost are exactly the frames the board dropped, corrupted or could not write
    expected = np.ones(hi - lo, dtype=bool)
    events = [e for e in read_log(log_path) if e["event"] in ("drop", "corrupt", "overrun") and lo <= e["index"] < hi]
    for e in events:
        expected[e["index"] - lo:e["index"] - lo + 20] = False
    assert sum(e["event"] == "drop" for e in events) > 0 and sum(e["event"] == "corrupt" for e in events) > 0
    assert np.array_equal(valid, expected)
    # time mapping (its accuracy is tested on synthetic arrivals below; here, on a machine of unknown load, the plumbing): a plausible
    # rate, host times never after the subscriber got the samples. The board is asked for speed 2 (40 kHz) but may be slowed, and
    # a board thread starved by a loaded test machine catches up in a burst, which the map follows up to 50 % faster than its
    # estimate (ClockMap's max_slew): 69 kHz was seen with the suite's other tests running beside
    later = [(m, t) for m, t in got if m.index_mono is not None and m.index - lo > 5 * 20_000]
    assert later and all(10_000 < m.fs_clock < 2 * 40_000 * 1.5 for m, _ in later), sorted(m.fs_clock for m, _ in later)
    # never after the subscriber got them, within what a loaded machine makes of the map: its estimate keeps finding earlier
    # arrivals, which the map, never stepping back, joins within tau_s, so it may lie a few tens of ms late meanwhile (17 ms
    # seen with two busy processes beside; 5 ms allowed before, which that failed); a plumbing fault is off by far more
    late = max(m.index_mono + (m.n - 1) / m.fs_clock - t for m, t in later)  # type: ignore[operator]
    assert late <= 0.05, late
    # the status's mapping and the message's agree on the same index: they are two states of one clock map, which moves by ~10
    # ms on a loaded machine (measured: 10.5 and 14.6 ms) between them; a plumbing fault (index, units, unix/mono) is off by far
    # more than the 50 ms allowed. The message nearest the status's own point of the map: far beyond it, the status
    # extrapolates at its rate, which a board catching up in a burst had moved (0.27 s off over 0.47 s, loaded host)
    s = statuses[-1]
    assert s.clock_index is not None
    m = min((m for m, _ in later), key=lambda m: abs(m.index - s.clock_index))  # type: ignore[operator]
    assert abs(s.host_mono(m.index) - m.index_mono) < 0.05  # type: ignore[operator]
    assert abs((s.host_unix(m.index) - s.host_mono(m.index)) - (m.index_unix - m.index_mono)) < 0.01  # type: ignore[operator]


def test_raw_batches_fill_short_gaps_and_split_long_ones() -> None:
    def block(i: int, n: int) -> tuple[int, np.ndarray]:
        return i, np.full((n, 2), i % 1000, dtype=np.int16)

    out = samples_chunks([block(100, 10), block(115, 5), block(200, 4)], expected=95, max_fill=50)
    assert [(b.index, b.samples.shape[0], b.lost, b.lost_before) for b in out] == [(95, 25, [[0, 5], [15, 5]], 0), (200, 4, [], 80)]
    assert not out[0].samples[:5].any() and (out[0].samples[5:15] == 100).all()
    assert samples_chunks([block(7, 3)], expected=None, max_fill=1)[0].index == 7


def test_clock_map_follows_the_earliest_arrivals() -> None:
    rng = np.random.default_rng(0)
    clock = ClockMap(20_000.0)
    true_fs, t0 = 20_010.0, 100.0  # the board's crystal is 0.05 % fast
    for k in range(1, 600):
        end = k * 400
        clock.observe(end, t0 + end / true_fs + 0.002 + rng.uniform(0, 0.01))  # 2 ms transport + up to 10 ms read jitter
    assert abs(clock.fs - true_fs) < 2.0
    assert 0.0 <= clock.mono(200_000) - (t0 + 200_000 / true_fs) <= 0.0025
    line = clock.mono(200_000)
    clock.observe(600 * 400, t0 + 600 * 400 / true_fs + 2.0)  # a host stall of 2 s: one late arrival, then the backlog, on time
    for k in range(1, 100):
        end = round((14.0 + 0.02 * k) * true_fs)
        clock.observe(end, t0 + end / true_fs + 0.003)
    assert clock.resets == 0 and abs(clock.mono(200_000) - line) < 1e-4  # the line holds (refined by the new on-time arrivals)
    for k in range(0, 100):  # a board restart that continues the timeline: late by about 70 s from now on, for more than persist_s
        clock.observe(400_000 + k * 400, t0 + 90.0 + k * 0.02)
    assert clock.resets == 1 and abs(clock.mono(400_000 + 99 * 400) - (t0 + 91.98)) < 0.01
    clock.observe(10**9, t0 + 93.0)  # a forward jump: the samples would have arrived before they were taken; the line moves down
    assert abs(clock.mono(10**9) - (t0 + 93.0)) < 1e-6 and clock.mono(10**9) > clock.mono(400_000 + 99 * 400)
