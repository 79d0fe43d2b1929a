"""Many files on every core: files per second of ``tactiled score``, ``features`` and ``replay`` at 1, 2 and all cores.

Writes ten simulated recordings (robot scene, 3 slides each, about 6 s) and copies them to make folders of 10, 100
and 1 000 files; times each whole command (start-up, loading and the work) with ``--jobs 1``, ``2`` and ``0`` (every
core). Copies replay exactly like their originals, so the work per file is the same at every size.

Usage: python bench/bench_files.py [--sizes 10,100,1000] [--jobs 1,2,0] [--commands score,features,replay] [--out DIR]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from bench_daemon import TACTILED
from scratch import scratch

from tactiled.learn.model import default_model_path
from tactiled.run.pool import cores
from tactiled.sim.simulate import write_dataset


def folder(root: Path, originals: list[Path], n: int) -> list[str]:
    """``n`` recordings in ``root/n``: the originals repeated (hard links where the file system allows)."""
    out = root / str(n)
    out.mkdir(exist_ok=True)
    paths = []
    for i in range(n):
        dst = out / f"{i:05d}_{originals[i % len(originals)].name}"
        if not dst.exists():
            try:
                os.link(originals[i % len(originals)], dst)
            except OSError:
                shutil.copy(originals[i % len(originals)], dst)
        paths.append(str(dst))
    return paths


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="10,100,1000")
    ap.add_argument("--jobs", default="1,2,0")
    ap.add_argument("--commands", default="score,features")
    ap.add_argument("--out", help="folder for the recordings (default: a temporary one)")
    args = ap.parse_args()
    root = scratch(args.out, "tactiled-files-")
    originals = write_dataset(root / "originals", scene="robot", seed=7, surfaces=5, files_per_surface=2, slides_per_file=3)
    print(f"{len(originals)} recordings of {sum(p.stat().st_size for p in originals) / len(originals) / 1e3:.0f} kB; "
          f"{cores()} cores; python {sys.version.split()[0]}")
    print("| command | files | jobs | wall s | files/s |")
    print("|---|---|---|---|---|")
    for command in args.commands.split(","):
        for n in (int(s) for s in args.sizes.split(",")):
            paths = folder(root, originals, n)
            for jobs in args.jobs.split(","):
                if command == "score":
                    cmd = [*TACTILED, "score", str(default_model_path()), *paths, "--json", "--jobs", jobs]
                elif command == "replay":
                    cmd = [*TACTILED, "replay", *paths, "--json", "--jobs", jobs]
                else:
                    cmd = [*TACTILED, "features", *paths, "-o", str(root / "f.npz"), "--force", "--jobs", jobs]
                t0 = time.perf_counter()
                subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
                wall = time.perf_counter() - t0
                print(f"| {command} | {n} | {jobs if jobs != '0' else f'0 (all {cores()})'} | {wall:.2f} | {n / wall:.1f} |", flush=True)


if __name__ == "__main__":
    main()
