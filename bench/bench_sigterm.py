"""How long ``tactiled run`` takes to stop on SIGTERM while its input costs more to process than it takes to arrive
(issue 22: within 2 s under any input). Floods as in tests/test_hostile_daemon.py: valid-looking frame headers that
claim 16 kB frames (1 MB/s), and intact one-sample frames each far ahead of the last (160 000 frames/s offered); and a
virtual board at real time for comparison.

    .venv/bin/python bench/bench_sigterm.py --trials 5

Each trial starts a daemon on a pty fed by the flood, waits until status shows input reaching it and 3 s more of flood,
sends SIGTERM and measures the time until the process has exited (exit code reported too); the longest wait between two
status messages over those 3 s is reported beside it (issue 22: status within 1 s; the daemon sends one every 0.5 s).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tactiled_client import BlockingSubscriber, Status

from tests.conftest import tactiled_cmd
from tests.test_hostile_daemon import GAP_FRAMES_RATE, HEADER_FLOOD_RATE, flooding, gap_frames, header_flood

FLOODS = {"headers-claiming-16kB-frames": (header_flood, HEADER_FLOOD_RATE), "one-sample-frames-far-ahead": (gap_frames, GAP_FRAMES_RATE * 16)}


def one_trial(folder: Path, stream: bytes | None, rate: float) -> tuple[float, int, float]:
    """(seconds from SIGTERM to exit, exit code, the longest wait between two status messages over 3 s) of one daemon under
    ``stream`` at ``rate`` bytes/s (None: a board at real time)."""
    link, endpoint = str(folder / "tty"), f"ipc://{folder}/pub"
    feeder = flooding(stream, rate, link) if stream is not None else _board(link)
    with feeder, BlockingSubscriber(endpoint, topics=["status"], timeout=30) as sub:
        proc = subprocess.Popen(tactiled_cmd("run", "--port", link, "--publish", endpoint), stderr=subprocess.DEVNULL)
        try:
            while True:  # input reaching the daemon
                m = sub.receive()
                if isinstance(m, Status) and (m.bytes_discarded or m.samples):
                    break
            until = last = time.monotonic()
            until += 3.0
            gap = 0.0
            while last < until:  # 3 s more of input, paced by the daemon's own status messages
                if isinstance(sub.receive(), Status):
                    now = time.monotonic()
                    gap, last = max(gap, now - last), now
            t0 = time.perf_counter()
            proc.terminate()
            code = proc.wait(60)
            return time.perf_counter() - t0, code, gap
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def _board(link: str):  # type: ignore[no-untyped-def]
    """A virtual board at real time on ``link`` while the block runs (tests.conftest's own helper)."""
    from tactiled.sim.physics import SensorSimulator, SimParams, pick_surfaces
    from tactiled.sim.virtualboard import VirtualBoard
    from tests.conftest import running

    return running(VirtualBoard(SensorSimulator(SimParams(), seed=0), pick_surfaces(3), link=link, speed=1.0))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=5)
    args = ap.parse_args()
    cases: dict[str, tuple[bytes | None, float]] = {name: (make(), rate) for name, (make, rate) in FLOODS.items()}
    cases["board at real time"] = (None, 0.0)
    for name, (stream, rate) in cases.items():
        times, codes, gaps = [], [], []
        for _ in range(args.trials):
            with tempfile.TemporaryDirectory() as folder:
                seconds, code, gap = one_trial(Path(folder), stream, rate)
            times.append(seconds)
            gaps.append(gap)
            codes.append(code)
        print(f"{name}: SIGTERM to exit median {statistics.median(times):.2f} s, max {max(times):.2f} s over {args.trials}; "
              f"exit codes {sorted(set(codes))}; longest wait between status messages {max(gaps):.2f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
