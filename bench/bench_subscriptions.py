"""What one hostile subscriber costs a running daemon: resident memory of ``tactiled run`` before, after N distinct
subscriptions of L bytes from one SUB socket, and after that peer disconnects (issue 22: <= 150 MB, then back to
baseline + 10 MB).

    .venv/bin/python bench/bench_subscriptions.py --count 10000 --length 60
    .venv/bin/python bench/bench_subscriptions.py --count 10000 --length 1000
    .venv/bin/python bench/bench_subscriptions.py --silent 5000     # silent connections held open instead (publish.max_connections)

The daemon runs with no board (a port that does not exist: it waits for it and publishes status), publishing on ipc
in a temporary folder. Memory is read from /proc/PID/status (VmRSS) once it has stopped changing for a second.
"""

from __future__ import annotations

import argparse
import os
import resource
import socket
import subprocess
import tempfile
import time
from pathlib import Path

import zmq
from bench_daemon import TACTILED


def rss_mb(pid: int) -> float:
    """Resident memory of ``pid``, MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS")


def settled(pid: int, quiet_s: float = 1.0, timeout_s: float = 120.0) -> float:
    """RSS once it has not changed by more than 1 MB for ``quiet_s`` (polled every 0.1 s: a measurement, not a synchronisation)."""
    deadline = time.monotonic() + timeout_s
    last, since = rss_mb(pid), time.monotonic()
    while time.monotonic() < deadline:
        time.sleep(0.1)
        now = rss_mb(pid)
        if abs(now - last) > 1.0:
            last, since = now, time.monotonic()
        elif time.monotonic() - since >= quiet_s:
            return now
    return rss_mb(pid)


def main() -> int:
    """Start the daemon, subscribe ``--count`` distinct ``--length``-byte topics from one peer, disconnect; print RSS at each step."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=10_000)
    ap.add_argument("--length", type=int, default=60)
    ap.add_argument("--silent", type=int, default=0, help="hold this many silent connections open instead (the daemon's nofile: 1024)")
    args = ap.parse_args()
    if args.silent:
        resource.setrlimit(resource.RLIMIT_NOFILE, (args.silent + 1024, max(args.silent + 1024, resource.getrlimit(resource.RLIMIT_NOFILE)[1])))
    with tempfile.TemporaryDirectory() as tmp:
        endpoint = f"ipc://{tmp}/pub"
        proc = subprocess.Popen([*TACTILED, "run", "--port", f"{tmp}/absent", "--publish", endpoint],
                                stderr=subprocess.DEVNULL, preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_NOFILE, (1024, 4096)))
        ctx = zmq.Context()
        try:
            watch = ctx.socket(zmq.SUB)
            watch.setsockopt(zmq.SUBSCRIBE, b"status")
            watch.connect(endpoint)
            watch.recv_multipart()  # the daemon is up and serving
            base = settled(proc.pid)
            if args.silent:
                fds = len(os.listdir(f"/proc/{proc.pid}/fd"))
                held, failed = [], 0
                for _ in range(args.silent):
                    conn = socket.socket(socket.AF_UNIX)
                    conn.settimeout(5)
                    try:
                        conn.connect(f"{tmp}/pub")
                    except OSError:  # the listen backlog full (refused, or timed out)
                        conn.close()
                        failed += 1
                        continue
                    held.append(conn)
                loaded = settled(proc.pid)
                watch.recv_multipart()  # still serving
                print(f"{len(held)} silent connections held ({failed} could not connect): RSS {base:.1f} MB before, {loaded:.1f} MB with them; "
                      f"daemon file descriptors "
                      f"{fds} before, {len(os.listdir(f'/proc/{proc.pid}/fd'))} with them")
                for conn in held:
                    conn.close()
                watch.close(0)
                return 0
            peer = ctx.socket(zmq.SUB)
            peer.setsockopt(zmq.LINGER, 0)
            peer.setsockopt(zmq.SNDHWM, 0)  # every subscription reaches the daemon (the default high-water mark drops those past 1 000)
            peer.connect(endpoint)
            for k in range(args.count):
                peer.setsockopt(zmq.SUBSCRIBE, (b"status/%08d" % k).ljust(args.length, b"x"))
            loaded = settled(proc.pid)
            peer.close()
            left = settled(proc.pid, quiet_s=6.0)  # the daemon returns freed memory to the system 1 and 5 s after a peer leaves
            watch.recv_multipart()  # still serving
            print(f"{args.count} distinct {args.length}-byte subscriptions from one peer: RSS {base:.1f} MB before, "
                  f"{loaded:.1f} MB with them (+{loaded - base:.1f}), {left:.1f} MB after the peer left (+{left - base:.1f})")
            watch.close()
        finally:
            proc.terminate()
            proc.wait(30)
            ctx.term()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
