"""How many 20 kHz sensors one machine sustains: K daemons, each on its own pty, fed by one cheap frame player.

Usage: python bench/bench_load.py [--counts 1,8,16,24,32,40] [--seconds 30] [--json OUT]

The boards are not simulated live (the simulator costs about four daemons): the simulator's
samples for the whole run are made once, encoded as frames once, and one player process
(tactiled.sim.ptyplayer.PtyPlayer) writes them into K ptys at the line rate (92 kB/s each), one
write per pty every 5 ms. Each daemon gets the same stream, started at a different offset.

For each K: every daemon's CPU share, the player's, the sensor-side latency (slide's last
sample → label received, from ``stop_mono``) p50/p99 over all labels, samples lost and
bytes the ptys would not take. A daemon has fallen behind when it loses samples or the
player overran its pty during the measurement (it did not read in time), or the sensor-side p99 latency exceeds 1 s.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time

import numpy as np
import zmq
from scratch import scratch
from tactiled_client import schema

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from bench_daemon import FS, TACTILED, cpu_seconds, make_stream

LINE_RATE = 92 * FS // 20  # bytes/s of 2-channel, 20-sample frames


def play(args: argparse.Namespace) -> None:
    """The player process: streams from --stream into ptys behind the --links symlinks until stdin closes.

    Each line on stdin is answered with the bytes the ptys would not take so far (a reader too slow, or not started yet).
    """
    from tactiled.sim.ptyplayer import PtyPlayer

    with open(args.stream, "rb") as fh:
        data = fh.read()
    links = args.play.split(",")
    frame = 92
    streams = [data[(k * 7919 * frame) % len(data):] + data[:(k * 7919 * frame) % len(data)] for k in range(len(links))]
    player = PtyPlayer(streams, LINE_RATE, links=links)
    stop = threading.Event()
    thread = threading.Thread(target=player.run, args=(stop,), daemon=True)
    thread.start()
    print("ready", flush=True)
    for _ in sys.stdin:  # each line asks for the overruns so far; end of input stops
        print(json.dumps({"overruns": player.overruns}), flush=True)
    stop.set()
    thread.join(5)
    player.close()


def overruns_so_far(player: subprocess.Popen[str]) -> int:
    assert player.stdin is not None and player.stdout is not None
    player.stdin.write("\n")
    player.stdin.flush()
    return int(json.loads(player.stdout.readline())["overruns"])


def run(k: int, seconds: float, stream_path: str, warmup: float, config: str | None = None) -> dict[str, object]:
    tmp = str(scratch(None, f"tactiled-load{k}-"))
    links = [f"{tmp}/tty{i}" for i in range(k)]
    player = subprocess.Popen([sys.executable, __file__, "--play", ",".join(links), "--stream", stream_path], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    assert player.stdout is not None and player.stdin is not None
    player.stdout.readline()
    daemons = [subprocess.Popen([*TACTILED, "run", "--port", links[i], "--publish", f"ipc://{tmp}/pub{i}", "--sensor-id", f"s{i}",
                                 *(["--config", config] if config else [])],
                                stderr=subprocess.DEVNULL) for i in range(k)]
    ctx = zmq.Context.instance()
    socks = []
    poller = zmq.Poller()
    for i in range(k):
        s = ctx.socket(zmq.SUB)
        for topic in (b"roughness", b"status"):
            s.setsockopt(zmq.SUBSCRIBE, topic)
        s.connect(f"ipc://{tmp}/pub{i}")
        poller.register(s, zmq.POLLIN)
        socks.append(s)
    lat: list[float] = []
    last: list[dict[str, object] | None] = [None] * k
    measuring = threading.Event()
    stop = threading.Event()

    def reader() -> None:  # one thread, all sockets: the subscriber side must not be the bottleneck either
        while not stop.is_set():
            for sock, _ in poller.poll(200):
                topic, body = schema.decode(sock.recv_multipart())
                i = socks.index(sock)
                if topic.startswith("roughness") and body.get("final") and body.get("stop_mono") is not None and measuring.is_set():
                    lat.append((time.monotonic() - body["stop_mono"]) * 1e3 + 1e3 / FS)
                elif topic.startswith("status"):
                    last[i] = body

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    deadline = time.monotonic() + 60 + 5 * k
    while not all(s and int(s["samples"]) > 0 for s in last) and time.monotonic() < deadline:  # type: ignore[call-overload]
        time.sleep(0.5)  # polling the statuses the reader thread collects: every daemon has started and reads its pty
    time.sleep(warmup)  # then a settling period (the first slide imports the model's code): benchmark warm-up, not synchronisation
    measuring.set()
    lost0 = [int(s["samples_lost"]) if s else 0 for s in last]  # type: ignore[call-overload]
    overruns0 = overruns_so_far(player)
    c0 = [cpu_seconds(d.pid) for d in daemons]
    p0 = cpu_seconds(player.pid)
    t0 = time.monotonic()
    time.sleep(seconds)  # the measurement period
    dt = time.monotonic() - t0
    cpu = [(cpu_seconds(d.pid) - c) / dt for d, c in zip(daemons, c0, strict=True)]
    player_cpu = (cpu_seconds(player.pid) - p0) / dt
    lost = [(int(s["samples_lost"]) if s else -1) - l0 for s, l0 in zip(last, lost0, strict=True)]  # type: ignore[call-overload]
    overruns = overruns_so_far(player) - overruns0
    stop.set()
    thread.join(5)
    for d in daemons:
        d.terminate()
    for d in daemons:
        d.wait(30)
    player.communicate("", timeout=30)
    for s in socks:
        s.close(linger=0)
    la = np.array(lat)
    p99 = float(np.percentile(la, 99)) if la.size else float("nan")
    behind = sum(lo != 0 for lo in lost) + (overruns > 0) + (not p99 < 1000)
    return {"k": k, "daemon_cpu_mean": round(float(np.mean(cpu)), 4), "daemon_cpu_max": round(float(np.max(cpu)), 4),
            "daemon_cpu_total": round(float(np.sum(cpu)), 3), "player_cpu": round(player_cpu, 4),
            "sensor_latency_ms_p50": round(float(np.percentile(la, 50)), 1) if la.size else None, "sensor_latency_ms_p99": round(p99, 1),
            "labels": int(la.size), "samples_lost": lost, "pty_overrun_bytes": overruns, "fell_behind": int(behind),
            "load_avg_1min": round(os.getloadavg()[0], 2)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--counts", default="1,8,16,24,32,40")
    ap.add_argument("--config", help="the daemons' config file")
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--warmup", type=float, default=5.0, help="s after every daemon reads its pty, before measuring")
    ap.add_argument("--json")
    ap.add_argument("--play", help=argparse.SUPPRESS)
    ap.add_argument("--stream", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.play:
        play(args)
        return
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    counts = [int(c) for c in args.counts.split(",")]
    stream_path = os.path.join(str(scratch(None, "tactiled-load-")), "stream.bin")
    with open(stream_path, "wb") as fh:
        fh.write(make_stream(args.seconds + args.warmup + 60))
    rows = []
    for k in counts:
        row = run(k, args.seconds, stream_path, args.warmup, args.config)
        rows.append(row)
        print(f"K={k:2d}: daemon CPU mean {100 * row['daemon_cpu_mean']:.2f} % (max {100 * row['daemon_cpu_max']:.2f} %, "  # type: ignore[operator]
              f"total {100 * row['daemon_cpu_total']:.0f} %), player {100 * row['player_cpu']:.1f} %, "  # type: ignore[operator]
              f"sensor latency p50 {row['sensor_latency_ms_p50']} ms p99 {row['sensor_latency_ms_p99']} ms ({row['labels']} labels), "
              f"lost {sum(row['samples_lost'])}, pty overruns {row['pty_overrun_bytes']} B, "  # type: ignore[arg-type]
              f"fell behind {row['fell_behind']}, load {row['load_avg_1min']}", flush=True)
        if row["fell_behind"]:
            break
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
