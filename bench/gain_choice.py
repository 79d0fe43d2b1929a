"""``train --gain-tolerance``: the default model chosen with and without another film gain in the choice, end to end.

Usage: python bench/gain_choice.py --out DIR [--gains 0,0.2] [--scenes "hand;robot;..."] [--json FILE]

``DIR`` is a ``python bench/labels.py --out DIR`` folder (its default scenes, or ``--mixed``): per scene ``train/`` (unit 0),
``same/`` (other tracks of the same specimens) and ``other1/`` .. ``other4/`` (other units of the sensor, each with new
specimens), as many as it has. For each gain tolerance, ``tactiled train`` with its defaults and ``gain`` learns the
training files; each test set is replayed end to end through the daemon's pipeline (every true slide counted, a slide
called an unknown surface counted wrong), beside the plain forty-line whole-slide spectral baseline of ``bench/labels.py``
trained on the same files. One line per scene as it is done, then the means and how many sets are at or above the
baseline.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from labels import end_to_end, plain_baseline

from tactiled.config import Config
from tactiled.learn.dataset import load_recordings
from tactiled.learn.train import train

TESTS = ("same", "other1", "other2", "other3", "other4")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True, help="a bench/labels.py --out folder")
    ap.add_argument("--gains", default="0,0.2", help="gain tolerances to compare, as fractions")
    ap.add_argument("--scenes", default=None, help="scene folders separated by ';' (default: every one with a train/ folder)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    root, gains, config = Path(args.out), [float(g) for g in args.gains.split(",")], Config()
    scenes = args.scenes.split(";") if args.scenes else sorted(p.parent.name for p in root.glob("*/train"))
    rows: dict[str, Any] = {}
    for scene in scenes:
        d = root / scene
        tests = {k: load_recordings(sorted((d / k).glob("*.npz"))) for k in TESTS if (d / k).is_dir()}
        files = sorted((d / "train").glob("*.npz"))
        row: dict[str, Any] = {"plain": plain_baseline(load_recordings(files), tests)}
        for g in gains:
            t0 = time.perf_counter()
            res = train(files, config, progress=lambda m: None, gain=g)
            row[str(g)] = {"winner": res.winner, "nested": res.nested["mean"], "train_s": time.perf_counter() - t0,
                           **{k: end_to_end(v, config, res.model)["accuracy"] for k, v in tests.items()}}
        rows[scene] = row
        sets = list(tests)
        print(f"{scene}: plain " + " / ".join(f"{100 * row['plain'][k]:.1f}" for k in sets)
              + "".join(f"; gain {g:g}: " + " / ".join(f"{100 * row[str(g)][k]:.1f}" for k in sets) + f" ({row[str(g)]['winner']})"
                        for g in gains) + f"  [{', '.join(sets)}]", flush=True)
    for g in gains:
        same = [r[str(g)]["same"] for r in rows.values()]
        other = [r[str(g)][k] for r in rows.values() for k in TESTS[1:] if k in r["plain"]]
        at = sum(r[str(g)][k] >= r["plain"][k] - 1e-9 for r in rows.values() for k in TESTS if k in r["plain"])
        print(f"gain {g:g}: mean same unit {100 * np.mean(same):.1f} %, other units {100 * np.mean(other):.1f} %; "
              f"sets at or above the plain baseline: {at} of {sum(k in r['plain'] for r in rows.values() for k in TESTS)}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main()
