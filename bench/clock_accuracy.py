"""The clock map's accuracy fed as the daemon feeds it: deterministic, no hardware, a few seconds.

Usage: python bench/clock_accuracy.py [--seconds 60] [--seeds 20] [--settle 3] [--slide-every 5 --slide-s 2]

A board sends 20-sample frames (92 bytes) at 20 kHz x ``rate`` (1.0005 and 0.9995: a crystal 0.05 % fast and slow);
each frame reaches the host 1-2 ms after its last sample (uniform, in order). The serial reader reads every 10 ms (plus
0-0.5 ms of sleep overshoot; a host stall of 50-300 ms on 0.2 % of the reads) and hands over what it holds once 40 ms
have passed during a slide and 200 ms at rest (a slide of ``--slide-s`` every ``--slide-every`` s). The daemon decodes
each hand-over in 4096-byte slices and, after each, calls ``observe(decoded end index, time of the read that returned
the slice's last byte)`` (tactiled/service/daemon.py ``_on_bytes``).

Reported from ``--settle`` s on, over every 40 ms of samples (800 at 20 kHz, the daemon's batch during a slide):
the map's time of a sample minus its true time minus the smallest transport delay of the run (ms: what the docs call
"within X ms of the smallest transport delay"), and the map's local rate ``rate(i, i + 800)`` against the board's true
rate (%). p50 / p99 / max of the absolute values, and the signed range.
"""

from __future__ import annotations

import argparse

import numpy as np

from tactiled.board.clockmap import ClockMap

FS, T0, FRAME, FRAME_BYTES, SLICE_BYTES, WINDOW = 20_000.0, 100.0, 20, 92, 4096, 800


def run(rate: float, seed: int, seconds: float, slide_every: float, slide_s: float) -> tuple[np.ndarray, np.ndarray]:
    """[time since the first samples, s; offset minus the smallest transport delay, s; local rate error, fraction] at every
    window start, and (resets, steps) of the map."""
    rng = np.random.default_rng(seed)
    fs = FS * rate
    n = int(seconds * fs) // FRAME
    done = T0 + np.arange(1, n + 1) * FRAME / fs  # when frame f's last sample was taken: the true time of index 20 (f + 1)
    came = np.maximum.accumulate(done + 0.001 + rng.uniform(0.0, 0.001, n))  # in order
    d_min = float((came - done).min())
    clock = ClockMap(FS)
    t, handed, got = T0, T0, 0
    held: list[tuple[int, float]] = []  # (frames a read returned, its time)
    while got < n:
        t += 0.010 + rng.uniform(0.0, 0.0005) + (rng.uniform(0.05, 0.3) if rng.random() < 0.002 else 0.0)
        upto = int(np.searchsorted(came, t, "right"))
        if upto > got:
            held.append((upto - got, t))
            got = upto
        hand_over = 0.04 if (t - T0) % slide_every < slide_s else 0.2
        if held and t - handed >= hand_over:
            base = (got - sum(k for k, _ in held)) * FRAME_BYTES  # bytes decoded before this hand-over
            ends = np.cumsum([k * FRAME_BYTES for k, _ in held])
            size = int(ends[-1])
            for lo in range(0, size, SLICE_BYTES):
                hi = min(lo + SLICE_BYTES, size)
                read = int(np.searchsorted(ends, hi - 1, "right"))  # the read that returned byte hi - 1
                end = (base + hi) // FRAME_BYTES * FRAME  # the decoder's next index: complete frames only
                clock.observe(end, held[read][1], 0.0)
            held, handed = [], t
    last = got * FRAME
    starts = np.arange(0, last - WINDOW, WINDOW)
    mono = np.array([clock.mono(int(i)) for i in starts])
    offset = mono - (T0 + starts / fs) - d_min
    local = np.array([clock.rate(int(i), int(i) + WINDOW) for i in starts]) / fs - 1.0
    return np.stack([starts / fs, offset, local]), np.array([clock.resets, clock.steps])


def figures(values: np.ndarray, scale: float) -> str:
    a = np.abs(values) * scale
    return (f"p50 {np.percentile(a, 50):.2f}, p99 {np.percentile(a, 99):.2f}, max {a.max():.2f} "
            f"(signed {values.min() * scale:+.2f}..{values.max() * scale:+.2f})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--settle", type=float, default=3.0, help="report from this many seconds after the first samples")
    ap.add_argument("--slide-every", type=float, default=5.0, help="a slide (40 ms hand-overs) starts this often, s")
    ap.add_argument("--slide-s", type=float, default=2.0, help="... and lasts this long (200 ms hand-overs otherwise), s")
    args = ap.parse_args()
    print(f"{args.seconds:g} s, seeds 0..{args.seeds - 1}, from {args.settle:g} s on, every {WINDOW} samples, "
          f"a slide of {args.slide_s:g} s every {args.slide_every:g} s")
    print("| board rate | offset - smallest transport, ms | local rate error, % | resets, steps |")
    print("|---|---|---|---|")
    pooled = []
    for rate in (1.0005, 0.9995):
        rows = []
        events = np.zeros(2, dtype=int)
        for seed in range(args.seeds):
            r, ev = run(rate, seed, args.seconds, args.slide_every, args.slide_s)
            rows.append(r[:, r[0] >= args.settle])
            events += ev
        r = np.concatenate(rows, axis=1)
        pooled.append(r)
        print(f"| {rate:g} | {figures(r[1], 1e3)} | {figures(r[2], 1e2)} | {events[0]}, {events[1]} |")
    r = np.concatenate(pooled, axis=1)
    print(f"| both | {figures(r[1], 1e3)} | {figures(r[2], 1e2)} | |")
    for lo, hi in ((3.0, 10.0), (10.0, 30.0), (30.0, args.seconds)):
        m = (r[0] >= lo) & (r[0] < hi)
        if m.any():
            print(f"  {lo:g}-{hi:g} s: offset {figures(r[1][m], 1e3)} ms; local rate {figures(r[2][m], 1e2)} %")


if __name__ == "__main__":
    main()
