"""Detection on simulated scenes: recall, precision and boundary errors of the daemon's detector, and how often an
early end (after ``detector.end_hold_s`` of quiet: the final label is published then) was withdrawn because the slide went on.

Usage: python bench/detection.py [--scenes hand,robot,...] [--files-per-surface 2] [--slides-per-file 3] [--out DIR] [--reuse]
Prints one row per scene (markdown). Recordings are simulated into --out (a temporary folder by default);
``--reuse`` takes the recordings already in --out (of an earlier run with the same arguments) instead.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from tactiled.config import Config
from tactiled.core.events import Resume
from tactiled.core.matching import match_slides
from tactiled.files.recording import load_recording
from tactiled.learn.dataset import detect_slides, detector_events
from tactiled.sim.physics import SCENES
from tactiled.sim.simulate import write_dataset

DEFAULT = ",".join(SCENES) + ";continuous,one-channel;fluctuating,one-channel;robot,hot-gain"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", default=DEFAULT, help="scene specs separated by ';' (each may join scenes with ',')")
    ap.add_argument("--files-per-surface", type=int, default=2)
    ap.add_argument("--slides-per-file", type=int, default=3)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--out", default=None)
    ap.add_argument("--reuse", action="store_true", help="use the recordings an earlier run left in --out")
    args = ap.parse_args()
    specs = [s for s in args.scenes.replace(";", "|").split("|")]
    specs = [x for s in specs for x in (s.split(",") if s == DEFAULT.split(";")[0] else [s])]
    config = Config()
    root = Path(args.out or tempfile.mkdtemp(prefix="tactiled-detect-"))
    print("| scene | true slides | detections | recall | precision | start error median / p90, s | end error median / p90, s "
          "| early ends withdrawn |")
    print("|---|---|---|---|---|---|---|---|")
    for spec in specs:
        folder = root / spec.replace(",", "+")
        paths = sorted(folder.glob("*.npz")) if args.reuse else []
        if not paths:
            paths = write_dataset(folder, scene=spec, seed=args.seed, files_per_surface=args.files_per_surface,
                                  slides_per_file=args.slides_per_file)
        n_true = n_det = paired = withdrawn = 0
        starts, ends = [], []
        for p in paths:
            rec = load_recording(p)
            truth = [(a, b) for a, b, _ in rec.slides()]
            events = detector_events(rec, config)  # one pass: the slides, and the early ends withdrawn (Resume)
            det = detect_slides(rec, config, events)
            withdrawn += sum(isinstance(e, Resume) for e in events)
            pairs = match_slides(det, truth)
            n_true += len(truth)
            n_det += len(det)
            for j, i in enumerate(pairs):
                if i is not None:
                    paired += 1
                    starts.append(abs(det[i][0] - truth[j][0]) / rec.fs)
                    ends.append(abs(det[i][1] - truth[j][1]) / rec.fs)
        s, e = np.array(starts), np.array(ends)
        print(f"| {spec} | {n_true} | {n_det} | {paired / n_true:.3f} | {paired / max(1, n_det):.3f} | "
              f"{np.median(s):.3f} / {np.percentile(s, 90):.3f} | {np.median(e):.3f} / {np.percentile(e, 90):.3f} | "
              f"{withdrawn} ({100 * withdrawn / max(1, n_det):.0f} % of detections) |", flush=True)


if __name__ == "__main__":
    main()
