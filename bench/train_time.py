"""Wall time of ``tactiled train`` (the default search) at several dataset sizes, on this machine and on a Dask LocalCluster.

Simulates the robot scene (15 surfaces, 5 slides per file, as many files per surface as the size needs), then
times ``train()`` with its defaults: on every local core (joblib), and through ``--scheduler`` on a
``dask.distributed.LocalCluster`` of 2 and of 4 single-threaded workers. Each cell is one run; the
datasets are written once under --out.

Usage: python bench/train_time.py [--sizes 300,1000,3000] [--workers 2,4] [--out DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
from pathlib import Path
from typing import Any

from scratch import scratch

from tactiled.config import Config
from tactiled.learn.train import train
from tactiled.sim.simulate import write_dataset

SLIDES_PER_FILE = 5
SURFACES = 15


def timed(paths: list[Path], scheduler: str | None) -> dict[str, Any]:
    """Seconds of one default ``train`` on ``paths`` (and what it chose)."""
    t0 = time.perf_counter()
    res = train(paths, Config(), scheduler=scheduler, progress=lambda m: None)
    return {"seconds": time.perf_counter() - t0, "winner": res.winner, "nested_cv": res.nested["mean"], "slides": res.slides}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="300,1000,3000", help="slides, comma separated")
    ap.add_argument("--workers", default="2,4", help="Dask LocalCluster sizes, comma separated ('' for none)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    root = scratch(args.out, "tactiled-train-time-")
    workers = [int(w) for w in args.workers.split(",") if w]
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    print("| slides | this machine (joblib, every core) | " + " | ".join(f"Dask LocalCluster, {w} workers" for w in workers) + " |")
    print("|---|---|" + "---|" * len(workers), flush=True)
    rows = []
    for size in (int(s) for s in args.sizes.split(",")):
        files = max(2, math.ceil(size / (SURFACES * SLIDES_PER_FILE)))
        folder = root / f"robot-{size}"
        paths = sorted(folder.glob("*.npz")) or write_dataset(folder, scene="robot", seed=7, files_per_surface=files,
                                                                slides_per_file=SLIDES_PER_FILE)
        row: dict[str, Any] = {"size": size, "local": timed(list(paths), None)}
        for w in workers:
            from dask.distributed import LocalCluster

            with LocalCluster(n_workers=w, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
                row[f"dask{w}"] = timed(list(paths), cluster.scheduler_address)
        rows.append(row)
        cells = [row["local"]] + [row[f"dask{w}"] for w in workers]
        print(f"| {row['local']['slides']} | " + " | ".join(f"{c['seconds']:.0f} s" for c in cells) + " |", flush=True)
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
