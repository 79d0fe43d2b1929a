"""Days of stream in hours: the daemon's resident memory over a long stream fed faster than real time through a socket.

Usage: python bench/soak_socket.py [--stream-hours 24] [--speed 10] [--sample-s 60] [--json OUT]

A pty overruns when a board writes faster than the daemon's read period drains it, so a real-time soak (bench/bench_daemon.py)
takes a day to say what a day does. A TCP socket holds the writer back instead (flow control): the bench plays the
simulator's hand scene (ten minutes of it, over and over, the frame index counting on) into a loopback socket at ``--speed``
× real time, the index starting ten stream-minutes before the board's 32-bit counter wraps, and ``tactiled run`` reads it
as ``sensor.port = "socket://..."`` (``sensor.allow_url = true``), its sensor still configured at 20 kHz, the shipped model,
one subscriber reading everything. Every ``--sample-s`` of wall time it notes the daemon's resident memory (VmRSS) against
the hours of stream played, and at the end the daemon's own counts (samples, lost, slides, labels, analyses skipped).

What it accelerates: everything counted in samples (the ring, the detector, windows, slides and labels, the clock map's
fit, the decoder's counters, the index's wrap). What it does not: what happens per second of wall time (status messages,
the reader's reads, timers) runs at its real rate, so ten stream-hours at ``--speed 10`` are one hour of those. The
daemon says once that the board runs faster than configured (the rate check), and goes on.
"""

from __future__ import annotations

import argparse
import socket
import subprocess
import threading
import time

from bench_daemon import FS, TACTILED, messages, report, rss_mb, scene_samples
from scratch import scratch
from tactiled_client import Roughness, Status

from tactiled.board.frames import encode_frames

LOOP_S = 600.0  # seconds of the scene played over and over
CHUNK = 2_000  # samples per send (0.1 s of stream)


def play(server: socket.socket, samples: object, first: int, total: int, speed: float, played: list[int], stop: threading.Event) -> None:
    """Send ``total`` samples of ``samples`` (looped) as frames from index ``first``, ``speed`` × real time; ``played[0]``
    counts the samples sent. TCP's flow control holds the sender back when the daemon reads late: nothing is dropped."""
    import numpy as np

    rows = np.asarray(samples)
    conn, _ = server.accept()
    with conn:
        start = time.monotonic()
        sent = 0
        while sent < total and not stop.is_set():
            lo = sent % rows.shape[0]
            chunk = rows[lo: lo + min(CHUNK, total - sent, rows.shape[0] - lo)]
            conn.sendall(encode_frames(first + sent, chunk))
            sent += chunk.shape[0]
            played[0] = sent
            ahead = start + sent / (FS * speed) - time.monotonic()
            if ahead > 0:
                time.sleep(ahead)  # pacing the board, not synchronisation


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stream-hours", type=float, default=24.0, help="hours of stream to play")
    ap.add_argument("--speed", type=float, default=10.0, help="times real time")
    ap.add_argument("--sample-s", type=float, default=60.0, help="wall seconds between memory samples")
    ap.add_argument("--json", help="write the figures here too")
    args = ap.parse_args()
    tmp = scratch(None, "tactiled-soak-")
    samples = scene_samples(LOOP_S)
    total = round(args.stream_hours * 3600 * FS) // 20 * 20
    first = 2**32 - round(LOOP_S * FS)  # the 32-bit counter wraps ten stream-minutes in
    server = socket.create_server(("127.0.0.1", 0))
    host, port = server.getsockname()
    played, stop = [0], threading.Event()
    player = threading.Thread(target=play, args=(server, samples, first, total, args.speed, played, stop), daemon=True)
    player.start()
    config, endpoint = tmp / "soak.toml", f"ipc://{tmp}/pub"
    config.write_text("[sensor]\nallow_url = true\n")
    log = open(tmp / "daemon.log", "w")  # noqa: SIM115
    daemon = subprocess.Popen([*TACTILED, "run", "--config", str(config), "--port", f"socket://{host}:{port}", "--publish", endpoint],
                              stderr=log)
    statuses: list[Status] = []
    labels = [0]

    def read() -> None:
        for msg in messages(endpoint, stop):
            if isinstance(msg, Roughness) and msg.final:
                labels[0] += 1
            elif isinstance(msg, Status):
                statuses[:] = [msg]

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    t0 = time.monotonic()
    curve: list[tuple[float, float, float]] = []  # (wall s, stream hours, VmRSS MB)
    try:
        while player.is_alive() and daemon.poll() is None:
            player.join(args.sample_s)  # the memory curve's period (returns early when the stream ends)
            curve.append((round(time.monotonic() - t0, 1), round(played[0] / FS / 3600, 3), round(rss_mb(daemon.pid), 1)))
            print(f"{curve[-1][0]:8.0f} s wall, {curve[-1][1]:7.3f} h of stream, VmRSS {curve[-1][2]:.1f} MB", flush=True)
        # the stream has ended: wait for the daemon to say it has taken every sample (the bridge closed: disconnected)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not (statuses and statuses[-1].samples + statuses[-1].samples_lost >= played[0]):
            reader.join(1.0)  # polling the reader's latest status, with a deadline
    finally:
        stop.set()
        daemon.terminate()
        daemon.wait(30)
        log.close()
    last = statuses[-1] if statuses else None
    hour = [r for _, h, r in curve if h >= 1.0]
    out = {
        "stream_hours": round(played[0] / FS / 3600, 3), "speed": args.speed, "wall_s": round(time.monotonic() - t0, 1),
        "rss_mb_curve": curve,
        "rss_mb_first_after_1h_last_max": [curve[0][2], hour[0] if hour else None, curve[-1][2], max(r for *_, r in curve)] if curve else None,
        "final_labels": labels[0], "daemon_exit": daemon.returncode,
        "status": None if last is None else {k: getattr(last, k) for k in ("samples", "samples_lost", "crc_errors", "restarts", "reconnects",
                                                                             "slides", "labels", "overloaded", "index")},
        "daemon_log": (tmp / "daemon.log").read_text().splitlines()[:20],
    }
    report(out, args.json)


if __name__ == "__main__":
    main()
