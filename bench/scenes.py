"""The cross-scene table: detection and end-to-end accuracy of the defaults on every simulator scene.

For each scene: simulate a training set and a separate test set (other seeds: other tracks
of the same specimens), train the default (``tactiled train``) and the papers' method
(``tactiled train --method paper``) on the training set, and score both end to end on the
test set (``tactiled score``: the daemon's pipeline, every true slide counted). Detection
recall and precision are measured on the test set.

Usage: python bench/scenes.py [--scenes "hand;robot;..."] [--files 3] [--test-files 2] [--slides 3] [--out DIR] [--json FILE]
       [--all-candidates]
Prints a markdown table; --json keeps every number (leaderboards included). --all-candidates also scores every candidate
of the default search on the test set: the data for judging a selection rule.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from scratch import scratch

from tactiled.config import Config
from tactiled.core.matching import match_slides
from tactiled.learn.dataset import detect_slides, load_recordings
from tactiled.learn.score import score_recordings
from tactiled.learn.train import train
from tactiled.sim.simulate import write_dataset

DEFAULT = "hand;robot;continuous;fluctuating;hot-gain;one-channel;grating;continuous,one-channel;fluctuating,one-channel;hand,hot-gain"


def detection(recs: list[tuple[str, Any]], config: Config) -> dict[str, float]:
    n_true = n_det = paired = 0
    for _, rec in recs:
        truth = [(a, b) for a, b, _ in rec.slides()]
        det = detect_slides(rec, config)
        n_true, n_det = n_true + len(truth), n_det + len(det)
        paired += sum(j is not None for j in match_slides(det, truth))
    return {"recall": paired / max(1, n_true), "precision": paired / max(1, n_det), "true": n_true, "detected": n_det}


def main() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", default=DEFAULT, help="scene specs separated by ';'")
    ap.add_argument("--files", type=int, default=3, help="training files per surface")
    ap.add_argument("--test-files", type=int, default=2, help="test files per surface")
    ap.add_argument("--slides", type=int, default=3, help="slides per file")
    ap.add_argument("--out", default=None)
    ap.add_argument("--json", default=None)
    ap.add_argument("--all-candidates", action="store_true",
                    help="also refit every candidate of the default search and score it on the test set (kept in --json)")
    args = ap.parse_args()
    config = Config()
    root = scratch(args.out, "tactiled-scenes-")
    rows = []
    print("| scene | detection recall / precision | default: winner | default: accuracy (coverage) | papers' method: accuracy (coverage) "
          "| train s (default / paper) |")
    print("|---|---|---|---|---|---|", flush=True)
    for spec in args.scenes.split(";"):
        name = spec.replace(",", "+")
        tr = write_dataset(root / name / "train", scene=spec, seed=100, files_per_surface=args.files, slides_per_file=args.slides)
        te = write_dataset(root / name / "test", scene=spec, seed=200, files_per_surface=args.test_files, slides_per_file=args.slides)
        test = load_recordings(te)
        det = detection(test, config)
        out: dict[str, Any] = {"scene": spec, "detection": det}
        for method in ("auto", "paper"):
            t0 = time.perf_counter()
            every = args.all_candidates and method == "auto"
            res = train(tr, config, method=method, progress=lambda m: None, keep_models=every)
            seconds = time.perf_counter() - t0
            sc = score_recordings(test, config, res.model)
            out[method] = {"winner": res.winner, "nested_cv": res.nested["mean"], "leaderboard": res.leaderboard if every else res.leaderboard[:8],
                           "train_s": seconds, "accuracy": sc["accuracy"], "coverage": sc["coverage"], "n": sc["n"], "abstained": sc["abstained"]}
            if every:
                out[method]["test_accuracy"] = {name: score_recordings(test, config, m)["accuracy"] for name, m in res.models.items()}
        rows.append(out)
        a, p = out["auto"], out["paper"]
        print(f"| {spec} | {det['recall']:.3f} / {det['precision']:.3f} ({det['true']} slides) | {a['winner']} | "
              f"**{100 * a['accuracy']:.1f} %** ({100 * a['coverage']:.0f} %) | {100 * p['accuracy']:.1f} % ({100 * p['coverage']:.0f} %) | "
              f"{a['train_s']:.0f} / {p['train_s']:.0f} |", flush=True)
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1, default=float))
    wins = sum(r["auto"]["accuracy"] >= r["paper"]["accuracy"] for r in rows)
    print(f"\ndefault >= papers' method on {wins} of {len(rows)} scenes; mean accuracy {100 * np.mean([r['auto']['accuracy'] for r in rows]):.1f} % "
          f"vs {100 * np.mean([r['paper']['accuracy'] for r in rows]):.1f} %", file=sys.stderr)


if __name__ == "__main__":
    main()
