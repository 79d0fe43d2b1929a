"""Frame decoder throughput, MB/s on one core, with 1 % corrupted frames.

Usage: python bench/bench_decoder.py [--seconds-of-stream 60] [--chunk 4096] [--per-frame]
Budget (docs/benchmarks.md): >= 9.4 MB/s (100x the fingertip's line rate).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from tactiled.board.frames import FrameDecoder, encode_frame


def make_stream(seconds: float, corrupt: float, seed: int = 0) -> tuple[bytes, int]:
    rng = np.random.default_rng(seed)
    n_frames = int(seconds * 1000)
    samples = rng.integers(-3000, 3000, (n_frames * 20, 2)).astype(np.int16)
    frames = []
    bad = 0
    for i in range(n_frames):
        frame = bytearray(encode_frame(i * 20, samples[i * 20:(i + 1) * 20]))
        if rng.random() < corrupt:
            frame[int(rng.integers(2, len(frame)))] ^= 0xFF
            bad += 1
        frames.append(bytes(frame))
    return b"".join(frames), bad


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds-of-stream", type=float, default=60.0)
    ap.add_argument("--chunk", type=int, default=4096, help="bytes per feed() call")
    ap.add_argument("--corrupt", type=float, default=0.01)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--per-frame", action="store_true", help="feed() (one Frame per frame) instead of feed_runs() (bulk runs)")
    args = ap.parse_args()
    data, bad = make_stream(args.seconds_of_stream, args.corrupt)
    best = float("inf")
    for _ in range(args.repeat):
        dec = FrameDecoder(channels=2)
        feed = dec.feed if args.per_frame else dec.feed_runs
        t0 = time.process_time()  # CPU time: the machine is shared
        for i in range(0, len(data), args.chunk):
            feed(data[i:i + args.chunk])
        best = min(best, time.process_time() - t0)
    mbps = len(data) / best / 1e6
    how = 'feed' if args.per_frame else 'feed_runs'
    print(f"decoder ({how}): {len(data) / 1e6:.1f} MB ({bad} of {len(data) // 92} frames corrupted), chunk {args.chunk} B: "
          f"{mbps:.1f} MB/s ({best * 1e3:.0f} ms of CPU), {mbps * 1e6 / 92_000:.0f}x the fingertip's 92 kB/s line rate "
          f"(frames {dec.stats.frames}, crc errors {dec.stats.crc_errors}, samples lost {dec.stats.samples_lost})")


if __name__ == "__main__":
    main()
