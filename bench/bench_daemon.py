"""The live daemon at 20 kHz from the simulator on a pty: CPU share, latency, memory (and a soak).

Usage: python bench/bench_daemon.py [--seconds 600] [--corrupt 0.01 --drop 0.005 --garbage 0.01]
                                    [--unplugs 3] [--subscribers 5] [--config C.toml] [--profile OUT]
One of the subscribers never reads. Budgets (docs/benchmarks.md): <= 2 % of one core without
faults, <= 3 % with the soak's; end of slide -> label published <= 20 ms at p99; resident memory
flat over 10 minutes.

Two latencies per final label: ``latency_ms`` (the daemon's: from the batch that revealed the
end to publication) and the sensor's: from the slide's last sample (``stop - 1``, mapped to host
time by the daemon's ClockMap, ``stop_mono``) to the moment the subscriber holds the message;
it includes the detector's off-hold, the read period and the batching (see docs/benchmarks.md). The label of a slide
already under way when the daemon opened the port (it starts at the stream's first sample, and ends by the detector's
start-up rule, 0.7 s after its quiet began: docs/detection.md) is left out of the latency figures and reported apart
(``mid_slide_start_sensor_latencies_ms``); the others are the steady state.
``--profile OUT``: run the daemon under cProfile (the CPU figure then includes the profiler).

The floor, in the same run: the player streams the same byte rate into a second pty, which a bare Python thread reads
at the daemon's read period (``serial.read_interval_s``: sleep, then read what the kernel holds, like the daemon's reader)
and throws away; its CPU share over the same seconds is ``floor_cpu_share``, and ``cpu_over_floor`` the daemon's as a
multiple of it (what a run on a busier or quieter minute changes least). ``--no-floor`` leaves it out.

``--board player`` (default): the simulator's samples are made and encoded once (faults
injected per frame: --corrupt, --drop, --garbage) and one cheap player process writes them into
the pty at the line rate (bench/bench_load.py --play), so a loaded machine cannot slow the
board down; ``--board sim``: the live simulator (``tactiled simulate serial``), which can also
unplug, and whose log the loss accounting reconciles.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator

import numpy as np
import zmq
from scratch import scratch
from tactiled_client import BlockingSubscriber, Message, NoData, Roughness, Slide, Status

from tactiled.sim.virtualboard import read_log

# The tactiled command every bench runs. -P: the working directory is not put first on sys.path, so PYTHONPATH chooses
# the code (an A/B of two checkouts: PYTHONPATH=/path/to/other/checkout python bench/...). Without it, `python -m tactiled` run from a
# checkout imports that checkout's tactiled whatever PYTHONPATH says.
TACTILED = [sys.executable, "-P", "-m", "tactiled"]


def cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def thread_seconds(pid: int) -> dict[str, float]:
    """CPU seconds per thread of ``pid`` (``/proc/PID/task/TID/schedstat``, ns), keyed ``TID:comm`` (the main thread's TID is the PID)."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/schedstat") as fh:
                ns = int(fh.read().split()[0])
            with open(f"/proc/{pid}/task/{tid}/comm") as fh:
                comm = fh.read().strip()
        except OSError:  # the thread ended meanwhile
            continue
        out[f"{tid}:{comm}"] = ns / 1e9
    return out


def bare_reader(path: str, interval: float) -> None:
    """The floor: a thread that reads ``path`` (a pty) every ``interval`` s and keeps nothing, until stdin closes."""
    import termios
    import tty

    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY)
    tty.setraw(fd, termios.TCSANOW)
    stop = threading.Event()

    def loop() -> None:
        while not stop.is_set():
            time.sleep(interval)  # the read period, as the daemon's reader
            with contextlib.suppress(BlockingIOError):
                while os.read(fd, 65536):
                    pass

    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    print("ready", flush=True)
    sys.stdin.read()  # until the bench closes stdin
    stop.set()
    thread.join(5)
    os.close(fd)


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


FS = 20_000


def pct(values: list[float], qs: tuple[float, ...]) -> list[float] | None:
    """Percentiles ``qs`` of ``values``, rounded to 0.1 (None if empty)."""
    return [round(float(np.percentile(values, q)), 1) for q in qs] if values else None


def scene_samples(seconds: float, seed: int = 11, scene: str = "hand") -> np.ndarray:
    """(n, 2) int16 counts: ``seconds`` of a simulator scene at 20 kHz, slides over random surfaces."""
    from tactiled.sim.physics import SensorSimulator, default_surfaces
    from tactiled.sim.simulate import scene_for

    _, params = scene_for(scene)
    if params.fs != FS or params.channels != 2:
        raise SystemExit(f"--scene {scene}: the player streams 2 channels at 20 kHz (the daemon's default sensor)")
    model = SensorSimulator(params, seed=seed)
    n = round(seconds * FS)
    parts = []
    for lo in range(0, n, FS):
        model.schedule_random(default_surfaces(), model.position + FS + 200)
        parts.append(model.read(min(FS, n - lo)))
    return np.concatenate(parts)


def make_stream(seconds: float, seed: int = 11, corrupt: float = 0.0, drop: float = 0.0, garbage: float = 0.0, scene: str = "hand") -> bytes:
    """``seconds`` of a simulator scene (:func:`scene_samples`) as the board's frames, faults injected per frame."""
    from tactiled.board.frames import encode_frame

    samples = scene_samples(seconds, seed, scene)
    rng = np.random.default_rng(seed)
    if not (corrupt or drop or garbage):
        from tactiled.board.frames import encode_frames

        return encode_frames(0, samples)
    out = []
    for i in range(0, samples.shape[0] - 19, 20):
        if rng.random() < drop:
            continue
        frame = bytearray(encode_frame(i, samples[i:i + 20]))
        if rng.random() < corrupt:
            frame[int(rng.integers(2, len(frame)))] ^= int(rng.integers(1, 256))
        if rng.random() < garbage:
            frame = bytearray(rng.integers(0, 256, int(rng.integers(1, 40)), dtype=np.uint8).tobytes()) + frame
        out.append(bytes(frame))
    return b"".join(out)


def report(out: dict[str, object], path: str | None) -> None:
    """Print the figures as JSON, and write them to ``path`` too if given."""
    print(json.dumps(out, indent=1))
    if path:
        with open(path, "w") as fh:
            json.dump(out, fh, indent=1)


def messages(endpoint: str, stop: threading.Event) -> Iterator[Message]:
    """Every message a subscriber of ``endpoint`` receives until ``stop`` is set (checked at least once a second)."""
    with BlockingSubscriber(endpoint, timeout=1.0) as sub:
        while not stop.is_set():
            try:
                yield sub.receive()
            except NoData:
                continue


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=600.0)
    ap.add_argument("--corrupt", type=float, default=0.0)
    ap.add_argument("--drop", type=float, default=0.0)
    ap.add_argument("--garbage", type=float, default=0.0)
    ap.add_argument("--unplugs", type=int, default=0, help="unplug the board this many times (needs --board sim: the player cannot)")
    ap.add_argument("--subscribers", type=int, default=1, help="readers; one more that never reads is always added")
    ap.add_argument("--json", help="write the figures here too")
    ap.add_argument("--config", help="the daemon's config file (e.g. serial.read_interval_s, serial.batch_s)")
    ap.add_argument("--profile", help="write the daemon's cProfile stats here")
    ap.add_argument("--board", choices=("player", "sim"), default="player")
    ap.add_argument("--scene", default="hand", help="the player's simulator scene (2 channels at 20 kHz: hand, robot, fluctuating, hot-gain, grating)")
    ap.add_argument("--no-floor", action="store_true", help="leave out the bare reader of a second pty (the floor)")
    ap.add_argument("--bare-reader", help=argparse.SUPPRESS)  # the floor's own process: the pty to read
    ap.add_argument("--interval", type=float, default=0.01, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.unplugs and args.board != "sim":
        ap.error("--unplugs needs --board sim (the player board cannot unplug)")
    if args.bare_reader:
        return bare_reader(args.bare_reader, args.interval)
    floor = args.board == "player" and not args.no_floor
    tmp = str(scratch(None, "tactiled-bench-"))
    link, endpoint, log = f"{tmp}/tty", f"ipc://{tmp}/pub", f"{tmp}/board.jsonl"
    unplug_at = ",".join(str(round(args.seconds * (k + 1) / (args.unplugs + 1), 1)) for k in range(args.unplugs))
    if args.board == "sim":
        board = subprocess.Popen([*TACTILED, "simulate", "serial", "--link", link, "--seed", "11", "--corrupt", str(args.corrupt), "--drop", str(args.drop),
                                  "--garbage", str(args.garbage), "--log", log, *(["--unplug-at", unplug_at] if unplug_at else [])],
                                 stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    else:
        stream = f"{tmp}/stream.bin"
        with open(stream, "wb") as fh:
            fh.write(make_stream(args.seconds + 10, corrupt=args.corrupt, drop=args.drop, garbage=args.garbage, scene=args.scene))
        board = subprocess.Popen([sys.executable, os.path.join(os.path.dirname(__file__), "bench_load.py"), "--play",
                                  link + (f",{tmp}/floor" if floor else ""), "--stream", stream], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert board.stdout is not None
    board.stdout.readline()
    bare = None
    if floor:
        from tactiled.config import load_config

        interval = load_config(args.config).serial.read_interval_s
        bare = subprocess.Popen([sys.executable, __file__, "--bare-reader", f"{tmp}/floor", "--interval", str(interval)],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert bare.stdout is not None
        bare.stdout.readline()
    lazy = zmq.Context.instance().socket(zmq.SUB)
    lazy.setsockopt(zmq.SUBSCRIBE, b"")
    lazy.connect(endpoint)
    run = [*TACTILED, "run", "--port", link, "--publish", endpoint, *(["--config", args.config] if args.config else [])]
    if args.profile:
        run = [sys.executable, "-P", "-m", "cProfile", "-o", args.profile, "-m", "tactiled", *run[len(TACTILED):]]
    daemon = subprocess.Popen(run, stderr=open(f"{tmp}/daemon.log", "w"))  # noqa: SIM115
    standing: dict[int, tuple[float, float | None]] = {}  # slide id -> (daemon latency, sensor-side latency) of its last final label
    withdrawn = [0]
    started: dict[int, float] = {}  # slide id -> sensor-side latency of its start message (from the slide's first sample)
    slide_start: dict[int, int] = {}  # slide id -> its first sample's index
    first_provisional: dict[int, float] = {}  # slide id -> from the slide's first sample to its first provisional label in hand
    statuses: list[Status] = []
    labels = [0] * args.subscribers
    missed = [0] * args.subscribers
    stop = threading.Event()

    def reader(k: int) -> None:
        for msg in messages(endpoint, stop):
            missed[k] += msg.missed
            if isinstance(msg, Roughness):
                labels[k] += 1
                if k == 0 and not msg.final and msg.start_mono is not None:
                    first_provisional.setdefault(msg.slide_id, (time.monotonic() - msg.start_mono) * 1e3)
                if k == 0 and msg.final:
                    sensor = None if msg.stop_mono is None else (time.monotonic() - msg.stop_mono) * 1e3 + 1e3 / 20_000
                    standing[msg.slide_id] = (msg.latency_ms, sensor)
            elif isinstance(msg, Slide) and k == 0 and msg.event == "start" and msg.start_mono is not None:
                started[msg.slide_id] = (time.monotonic() - msg.start_mono) * 1e3
                slide_start[msg.slide_id] = msg.start
            elif isinstance(msg, Slide) and k == 0 and msg.event == "resumed":  # that final label was withdrawn: the slide went on
                withdrawn[0] += standing.pop(msg.slide_id, None) is not None
            elif isinstance(msg, Status) and k == 0:
                statuses.append(msg)

    threads = [threading.Thread(target=reader, args=(k,), daemon=True) for k in range(args.subscribers)]
    for t in threads:
        t.start()
    time.sleep(3.0)  # let the daemon start and import before measuring: benchmark warm-up, not synchronisation
    c0, t0, th0 = cpu_seconds(daemon.pid), time.monotonic(), thread_seconds(daemon.pid)
    f0 = sum(thread_seconds(bare.pid).values()) if bare else 0.0
    lost0 = statuses[-1].samples_lost if statuses else 0  # lost while the daemon started (stale bytes are discarded_at_start, not lost)
    load0 = round(os.getloadavg()[0], 2)
    rss = []
    while time.monotonic() - t0 < args.seconds:
        time.sleep(min(10.0, args.seconds / 20))  # sampling period of the memory curve
        rss.append((round(time.monotonic() - t0, 1), round(rss_mb(daemon.pid), 1)))
    th1, elapsed = thread_seconds(daemon.pid), time.monotonic() - t0
    cpu = (cpu_seconds(daemon.pid) - c0) / elapsed
    floor_cpu = (sum(thread_seconds(bare.pid).values()) - f0) / elapsed if bare else None
    if bare:
        assert bare.stdin is not None
        bare.stdin.close()
        bare.wait(10)
    threads_pct = {k: round(100 * (v - th0.get(k, 0.0)) / elapsed, 3) for k, v in sorted(th1.items(), key=lambda kv: -kv[1] + th0.get(kv[0], 0.0))}
    t_term = time.monotonic()
    daemon.send_signal(2) if args.profile else daemon.terminate()  # SIGINT lets cProfile write its stats
    daemon.wait(30)
    stop_s = time.monotonic() - t_term
    stop.set()
    board.terminate()
    board.wait(10)
    lazy.close(linger=0)
    last = statuses[-1] if statuses else None
    # a slide already under way when the daemon opened the port (it starts at the stream's first sample) ends by the detector's
    # start-up rule (docs/detection.md): its label is reported apart, the others are the steady state
    first_index = last.index - last.samples - last.samples_lost if last is not None else None
    measured = {k: v for k, v in standing.items() if first_index is None or slide_start.get(k, first_index + 1) > first_index}
    lat = np.array([d for d, _ in measured.values()])
    sensor_latencies = [s for _, s in measured.values() if s is not None]
    accounting = None
    if last is not None and args.board == "sim":
        # reconcile: samples the daemon counted lost against what the board says it did not deliver intact
        first = last.index - last.samples - last.samples_lost
        # read_log: an overrun line of the board's log holds up to a second of frames; it gives one event per frame
        inside = [e for e in read_log(log) if first <= e.get("index", -1) < last.index]
        faulty = sum(e.get("count", 20) for e in inside if e["event"] in ("drop", "corrupt", "overrun"))
        unplugged = sum(1 for e in inside if e["event"] == "unplug")
        down = unplugged * (round(0.3 * 20_000) + 20)  # simulate serial's default --unplug-s 0.3, plus the frame at the unplug
        accounting = {"first_index": first, "frames_dropped_or_corrupted_or_overrun_samples": faulty, "unplugs": unplugged,
                      "unplug_down_samples": down, "daemon_samples_lost": last.samples_lost,
                      "lost_beyond_injected": last.samples_lost - faulty - down}
    out = {
        "seconds": args.seconds, "cpu_share": round(cpu, 4),
        "floor_cpu_share": None if floor_cpu is None else round(floor_cpu, 4),
        "cpu_over_floor": round(cpu / floor_cpu, 2) if floor_cpu else None, "threads_cpu_pct": threads_pct, "labels": labels, "missed_messages": missed,
        "latency_ms_p50": round(float(np.percentile(lat, 50)), 3) if lat.size else None,
        "latency_ms_p99": round(float(np.percentile(lat, 99)), 3) if lat.size else None,
        "latency_ms_max": round(float(lat.max()), 3) if lat.size else None,
        "sensor_latency_ms_p50_p99_max": [round(float(np.percentile(sensor_latencies, q)), 1) for q in (50, 99, 100)] if sensor_latencies else None,
        "sensor_latencies_ms": [round(v[1], 1) for _, v in sorted(measured.items()) if v[1] is not None],
        "latencies_ms": [round(v[0], 2) for _, v in sorted(measured.items())],
        "mid_slide_start_sensor_latencies_ms": [round(v[1], 1) for k, v in sorted(standing.items()) if k not in measured and v[1] is not None],
        "start_latency_ms_p50_p90_max": pct(list(started.values()), (50, 90, 100)),
        "first_provisional_ms_p50_p90_max": pct(list(first_provisional.values()), (50, 90, 100)),
        "samples_lost_while_measured": None if last is None else last.samples_lost - lost0,
        "final_labels_standing": len(standing), "final_labels_withdrawn": withdrawn[0], "scene": args.scene,
        "config": args.config, "board": args.board, "load_avg_1min_start_end": [load0, round(os.getloadavg()[0], 2)],
        "rss_mb": rss, "rss_mb_first_last_max": [rss[0][1], rss[-1][1], max(r for _, r in rss)] if rss else None,
        "daemon_exit": daemon.returncode, "stop_s": round(stop_s, 3), "loss_accounting": accounting,
        "status": None if last is None else {k: getattr(last, k) for k in ("samples", "samples_lost", "crc_errors", "bad_headers",
                                                                             "bytes_discarded", "reconnects", "slides", "labels")},
    }
    report(out, args.json)


if __name__ == "__main__":
    main()
