"""How many 20 kHz sensors one machine sustains: K daemons, each on its own virtual board.

Usage: python bench/bench_load.py [--counts 1,2,4,6,8,10] [--seconds 30]
For each K: every daemon's CPU share, its latency p99, the measured sample rate and
samples lost. A daemon has fallen behind when it loses samples (the tty overflowed because
it did not read in time) or its p99 latency exceeds 20 ms. The virtual boards run on the
same machine and take CPU too; the table says how much.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np
from tactiled_client import BlockingSubscriber, NoData, Roughness, Status

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from bench_daemon import cpu_seconds


def run(k: int, seconds: float) -> dict[str, object]:
    tmp = tempfile.mkdtemp(prefix=f"tactiled-load{k}-")
    exe = [sys.executable, "-m", "tactiled"]
    boards, daemons = [], []
    for i in range(k):
        board = subprocess.Popen([*exe, "simulate", "serial", "--link", f"{tmp}/tty{i}", "--seed", str(i)], stdout=subprocess.PIPE,
                                 stderr=subprocess.DEVNULL, text=True)
        assert board.stdout is not None
        board.stdout.readline()
        boards.append(board)
        daemons.append(subprocess.Popen([*exe, "run", "--port", f"{tmp}/tty{i}", "--publish", f"ipc://{tmp}/pub{i}", "--sensor-id", f"s{i}"],
                                        stderr=subprocess.DEVNULL))
    lat: list[list[float]] = [[] for _ in range(k)]
    last: list[Status | None] = [None] * k
    stop = threading.Event()

    def reader(i: int) -> None:
        with BlockingSubscriber(f"ipc://{tmp}/pub{i}", timeout=1.0) as sub:
            while not stop.is_set():
                try:
                    m = sub.receive()
                except NoData:
                    continue
                if isinstance(m, Roughness):
                    lat[i].append(m.latency_ms)
                elif isinstance(m, Status):
                    last[i] = m

    threads = [threading.Thread(target=reader, args=(i,), daemon=True) for i in range(k)]
    for t in threads:
        t.start()
    time.sleep(3.0)  # start-up (imports) excluded from the measurement
    lost0 = [s.samples_lost if s else 0 for s in last]
    c0 = [cpu_seconds(d.pid) for d in daemons]
    b0 = [cpu_seconds(b.pid) for b in boards]
    t0 = time.monotonic()
    time.sleep(seconds)  # the measurement period
    dt = time.monotonic() - t0
    cpu = [(cpu_seconds(d.pid) - c) / dt for d, c in zip(daemons, c0, strict=True)]
    board_cpu = [(cpu_seconds(b.pid) - c) / dt for b, c in zip(boards, b0, strict=True)]
    stop.set()
    for p in daemons + boards:
        p.terminate()
    for p in daemons + boards:
        p.wait(10)
    p99 = [float(np.percentile(x, 99)) if x else float("nan") for x in lat]
    lost = [(s.samples_lost if s else -1) - l0 for s, l0 in zip(last, lost0, strict=True)]
    behind = [lo != 0 or not (p < 20) for lo, p in zip(lost, p99, strict=True)]
    return {"k": k, "daemon_cpu_mean": float(np.mean(cpu)), "daemon_cpu_max": float(np.max(cpu)), "board_cpu_mean": float(np.mean(board_cpu)),
            "latency_p99_ms_max": float(np.nanmax(p99)), "samples_lost": lost, "labels": [len(x) for x in lat], "fell_behind": sum(behind)}


def main() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    ap = argparse.ArgumentParser()
    ap.add_argument("--counts", default="1,2,4,6,8,10")
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--json")
    args = ap.parse_args()
    rows = []
    for k in (int(c) for c in args.counts.split(",")):
        row = run(k, args.seconds)
        rows.append(row)
        print(f"K={k:2d}: daemon CPU mean {100 * row['daemon_cpu_mean']:.1f} % (max {100 * row['daemon_cpu_max']:.1f} %), "
              f"board CPU mean {100 * row['board_cpu_mean']:.1f} %, latency p99 max {row['latency_p99_ms_max']:.2f} ms, "
              f"samples lost {row['samples_lost']}, fell behind {row['fell_behind']}", flush=True)
        if row["fell_behind"]:
            break
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
