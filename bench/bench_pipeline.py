"""Replay throughput (multiples of real time, one core), start-up time, resident memory, feature time per window.

Usage: python bench/bench_pipeline.py [--seconds 300 | --recording FILE] [--save FILE] [--repeat 3] [--startup 5]
                                      [--daemon-seconds 0]

Budgets (docs/benchmarks.md): replay of a 5-minute 2-channel 20 kHz recording >= 1000x real time on one core
(CPU time of the replay, the recording already loaded); ``tactiled --help`` and ``tactiled replay`` start in
<= 0.5 s (wall time of the whole command on a 2 s recording, the best of --startup runs); resident memory
<= 100 MB (peak, VmHWM, of ``tactiled replay`` on the 5-minute recording and of the daemon after
--daemon-seconds at 20 kHz with the shipped model).
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_daemon import TACTILED

from tactiled.config import Config
from tactiled.core.analysis import AnalysisSettings
from tactiled.core.features import FeaturePlan
from tactiled.files.recording import Recording, load_recording, save_recording
from tactiled.learn.model import load_model
from tactiled.run.replay import replay_recording
from tactiled.sim.physics import SensorSimulator, SimParams, default_surfaces


def simulate(seconds: float, seed: int = 0) -> Recording:
    """``seconds`` of the hand scene at 20 kHz, 2 channels: rests and slides over random surfaces."""
    p = SimParams()
    m = SensorSimulator(p, seed)
    n = int(seconds * p.fs)
    m.schedule_random(default_surfaces(), n)
    return Recording(m.read(n), p.fs, p.volts_per_count)


def wall_s(cmd: list[str]) -> float:
    """Wall time (s) of one run of ``cmd``, output discarded."""
    t0 = time.perf_counter()
    subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
    return time.perf_counter() - t0


# the tactiled command, then its own peak resident memory (VmHWM: per process image; a child's ru_maxrss would
# include this benchmark's own memory at fork)
PEAK = """
import sys
from tactiled.cli.main import main
try:
    sys.exit(main(sys.argv[1:]))
finally:  # also after --help, which exits from argparse
    print(next(line for line in open("/proc/self/status") if line.startswith("VmHWM:")).split()[1], file=sys.stderr)
"""


def peak_kb(args: list[str]) -> int:
    """Peak resident memory (VmHWM, kB) of ``tactiled ARGS``."""
    out = subprocess.run([sys.executable, "-P", "-c", PEAK, *args], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, check=True)
    return int(out.stderr.split()[-1])


def vm_kb(pid: int, key: str) -> int:
    """A ``Vm…`` line (kB) of /proc/<pid>/status, e.g. VmHWM (peak resident) or VmRSS."""
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    raise SystemExit(f"/proc/{pid}/status: no {key}")


def daemon_memory(seconds: float) -> tuple[int, int]:
    """(VmHWM, VmRSS) kB of ``tactiled run`` with the shipped model after ``seconds`` of a simulated 20 kHz board."""
    with tempfile.TemporaryDirectory(prefix="tactiled-bench-") as tmp:
        return _daemon_memory(seconds, tmp)


def _daemon_memory(seconds: float, tmp: str) -> tuple[int, int]:
    link = f"{tmp}/tty"
    board = subprocess.Popen([*TACTILED, "simulate", "serial", "--link", link, "--seed", "11"], stdout=subprocess.PIPE,
                             stderr=subprocess.DEVNULL, text=True)
    assert board.stdout is not None
    board.stdout.readline()  # the board announces its tty when it is ready
    daemon = subprocess.Popen([*TACTILED, "run", "--port", link, "--publish", f"ipc://{tmp}/pub"], stderr=subprocess.DEVNULL)
    try:
        time.sleep(seconds)  # the measurement period, not synchronisation
        return vm_kb(daemon.pid, "VmHWM"), vm_kb(daemon.pid, "VmRSS")
    finally:
        daemon.terminate()
        board.terminate()
        daemon.wait(10)
        board.wait(10)


def main() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)  # as the tactiled command does
    from tactiled.run.heap import keep_freed_memory

    keep_freed_memory()  # as tactiled replay does: the pipeline's temporaries stay in glibc's heap
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=300.0, help="simulated recording length, s")
    ap.add_argument("--recording", help="replay this recording instead of simulating one")
    ap.add_argument("--save", help="keep the simulated recording here")
    ap.add_argument("--repeat", type=int, default=3, help="replays timed (the best is reported)")
    ap.add_argument("--startup", type=int, default=5, help="runs of each command timed for start-up (0: skip start-up and memory)")
    ap.add_argument("--daemon-seconds", type=float, default=0.0, help="run the daemon this long and report its memory (0: skip)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="tactiled-bench-") as tmp:
        measure(args, Path(tmp))


def measure(args: argparse.Namespace, tmp: Path) -> None:
    """Every figure the command line asks for; ``tmp`` holds the recordings made for it (removed after)."""
    if args.recording:
        path = Path(args.recording)
        rec = load_recording(path)
    else:
        rec = simulate(args.seconds)
        path = Path(args.save or tmp / "replay.npz")
        save_recording(path, rec)
    seconds = rec.samples.shape[0] / rec.fs
    model = load_model()
    cpu, wall = [], []
    for _ in range(args.repeat):
        c0, w0 = time.process_time(), time.perf_counter()
        results = replay_recording(rec, Config(), model)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    print(f"replay: {seconds:.0f} s of {rec.channels}-channel {rec.fs:g} Hz in {min(cpu):.3f} s CPU = {seconds / min(cpu):.0f}x real time "
          f"(best of {args.repeat}; wall {min(wall):.3f} s = {seconds / min(wall):.0f}x), {len(results)} slide results, "
          f"shipped model ({model.kind}, {len(model.names)} features)")
    print(f"slide result compute_ms: median {np.median([r.compute_ms for r in results]):.3f} ms")
    x = rec.volts()[:10000]
    all_names = AnalysisSettings.from_config(Config(), 2).names
    six = (*all_names[:3], "film2.freq.D3.sd", "film1.time.A4.energy", "film2.time.D2.kurt")
    for label, names in (("all 192", all_names), ("six", six), ("shipped model", model.names)):
        plan = FeaturePlan(names)
        reps = 50
        t0 = time.process_time()
        for _ in range(reps):
            plan.compute(x)
        print(f"features ({label}) on a 0.5 s window: {(time.process_time() - t0) / reps * 1e3:.2f} ms")
    if args.startup > 0:
        short = tmp / "short.npz"
        save_recording(short, Recording(rec.samples[: round(2 * rec.fs)], rec.fs, rec.volts_per_count))
        for label, cmd in (("tactiled --help", ["--help"]), ("tactiled replay (2 s recording)", ["replay", str(short)])):
            runs = [wall_s([*TACTILED, *cmd]) for _ in range(args.startup)]
            print(f"start-up, {label}: best {min(runs):.3f} s, median {float(np.median(runs)):.3f} s of {args.startup}; "
                  f"peak resident {peak_kb(cmd) / 1024:.1f} MB")
        print(f"tactiled replay ({seconds:.0f} s recording): peak resident (VmHWM) {peak_kb(['replay', str(path)]) / 1024:.1f} MB")
    if args.daemon_seconds > 0:
        hwm, rss = daemon_memory(args.daemon_seconds)
        print(f"daemon after {args.daemon_seconds:g} s at 20 kHz, shipped model: VmHWM {hwm / 1024:.1f} MB, VmRSS {rss / 1024:.1f} MB")
    print(f"(this process: peak resident {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB)")


if __name__ == "__main__":
    main()
