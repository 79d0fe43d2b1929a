"""Replay throughput (multiples of real time, one core) and feature time per window.

Usage: python bench/bench_pipeline.py [--seconds 120]
Budget (docs/benchmarks.md): replay >= 1000x real time for 2-channel 20 kHz recordings.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from tactiled.analysis import AnalysisSettings
from tactiled.config import Config
from tactiled.features import FeaturePlan
from tactiled.model import load_model
from tactiled.recording import Recording
from tactiled.replay import replay_recording
from tactiled.sensor_model import SensorModel, SimParams, default_surfaces


def main() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)  # as the tactiled command does
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=120.0)
    args = ap.parse_args()
    p = SimParams()
    m = SensorModel(p, 0)
    n = int(args.seconds * p.fs)
    m.schedule_random(default_surfaces(), n)
    rec = Recording(m.read(n), p.fs, p.volts_per_count)
    model = load_model()
    t0 = time.perf_counter()
    results = replay_recording(rec, Config(), model)
    dt = time.perf_counter() - t0
    print(f"replay: {args.seconds:.0f} s of 2-channel 20 kHz in {dt:.2f} s = {args.seconds / dt:.0f}x real time, {len(results)} slides, "
          f"shipped model ({len(model.names)} features)")
    x = rec.volts()[:10000]
    all_names = AnalysisSettings.from_config(Config(), 2).names
    six = (*all_names[:3], "film2.freq.D3.sd", "film1.time.A4.energy", "film2.time.D2.kurt")
    for label, names in (("all 192", all_names), ("six", six), ("shipped model", model.names)):
        plan = FeaturePlan(names)
        reps = 50
        t0 = time.perf_counter()
        for _ in range(reps):
            plan.compute(x)
        print(f"features ({label}) on a 0.5 s window: {(time.perf_counter() - t0) / reps * 1e3:.2f} ms")
    print(f"slide result compute_ms: median {np.median([r.compute_ms for r in results]):.3f} ms")


if __name__ == "__main__":
    main()
