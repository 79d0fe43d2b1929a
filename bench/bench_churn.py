"""A storm of peers that connect to the daemon's publish socket and leave at once: does the analysis fall behind?

Usage: python bench/bench_churn.py [--storms 4] [--connections 15000] [--out DIR]

A virtual board (``tactiled simulate serial``, the hand scene at 20 kHz) on a pty, ``tactiled run`` reading it and
publishing on an ipc socket, and, once it has run 5 s, ``--storms`` storms of ``--connections`` Unix-socket connections
each opened and closed at once, from this process, one after the other. Prints how long each storm took, then the
daemon's log lines that say it fell behind (``overloaded``, ``caught up``: samples not analysed) and its last line.
The code measured is the one imported by ``python -P -m tactiled`` (``PYTHONPATH`` chooses another checkout).
"""

from __future__ import annotations

import argparse
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from scratch import scratch

TACTILED = [sys.executable, "-P", "-m", "tactiled"]


def wait_for(path: Path, timeout: float) -> None:
    """Until ``path`` exists (the board's pty link, the daemon's socket), or fail."""
    end = time.monotonic() + timeout
    while not path.exists():
        if time.monotonic() > end:
            sys.exit(f"{path} did not appear within {timeout:g} s")
        time.sleep(0.05)  # polling for a file, with a timeout


def storm(path: Path, connections: int) -> float:
    """Open and close ``connections`` connections to the Unix socket at ``path``; returns the seconds it took."""
    t0 = time.perf_counter()
    for _ in range(connections):
        with socket.socket(socket.AF_UNIX) as s:
            s.connect(str(path))
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--storms", type=int, default=4)
    ap.add_argument("--connections", type=int, default=15000)
    ap.add_argument("--out", default=None, help="folder for the pty link, socket, config and logs (default: a temporary one)")
    args = ap.parse_args()
    root = scratch(args.out, "tactiled-churn-")
    tty, pub = root / "tty", root / "pub.sock"
    config = root / "d.toml"
    config.write_text(f'[sensor]\nport = "{tty}"\n[publish]\nendpoint = "ipc://{pub}"\n')
    board = subprocess.Popen([*TACTILED, "simulate", "serial", "--link", str(tty)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    daemon = None
    try:
        wait_for(tty, 30)
        log = open(root / "daemon.log", "w")  # noqa: SIM115 - closed below, after the daemon stops
        daemon = subprocess.Popen([*TACTILED, "run", "--config", str(config)], stderr=log, stdout=log)
        wait_for(pub, 30)
        time.sleep(5.0)  # the daemon running steadily before the storms: benchmark warm-up, not synchronisation
        for k in range(args.storms):
            print(f"storm {k + 1}: {args.connections} connections in {storm(pub, args.connections):.2f} s", flush=True)
        time.sleep(4.0)  # the last storm's aftermath in the log: benchmark settling, not synchronisation
        daemon.send_signal(signal.SIGTERM)
        daemon.wait(30)
        log.close()
    finally:
        for p in (daemon, board):
            if p is not None and p.poll() is None:
                p.terminate()
                p.wait(30)
    lines = (root / "daemon.log").read_text().splitlines()
    behind = [line for line in lines if "overloaded" in line or "caught up" in line]
    print("\n".join(behind) if behind else "never fell behind")
    print(lines[-1] if lines else "(no daemon log)")


if __name__ == "__main__":
    main()
