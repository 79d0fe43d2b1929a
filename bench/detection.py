"""Detection on simulated scenes: recall, precision and boundary errors of the daemon's detector, and how often an
early end (after ``detector.end_hold_s`` of quiet: the final label is published then) was withdrawn because the slide went on.

Usage: python bench/detection.py [--scenes hand,robot,...] [--files-per-surface 2] [--slides-per-file 3] [--out DIR] [--reuse]
                                 [--mid-slide | --lead S] [--start-level]
Prints one row per scene (markdown). ``--start-level``: the detector has the start level ``tactiled train`` would
learn from the scene's recordings (tactiled/learn/levels.py), as the daemon's has with such a model. ``--mid-slide``:
instead, each recording is also detected from 40 % into each of its first three slides (a daemon started mid-slide),
and the row counts how often the first slide, once a quiet ended it, took in more than one true slide. ``--lead S``: the
same, from S s before each of those slides (a recording or daemon started just before the finger moved), with the first
slide's start error. Recordings are
simulated into --out (a temporary folder by default); ``--reuse`` takes the recordings already in --out (of an earlier run with the same arguments) instead.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scratch import scratch

from tactiled.config import Config
from tactiled.core.events import Offset, Resume
from tactiled.core.matching import match_slides
from tactiled.files.recording import Recording, load_recording
from tactiled.learn.dataset import detect_slides, detector_events
from tactiled.learn.levels import start_level
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
    ap.add_argument("--mid-slide", action="store_true", help="detect from 40 %% into each of the first three slides of each recording")
    ap.add_argument("--lead", type=float, default=None, help="detect from this many s before each of the first three slides")
    ap.add_argument("--start-level", action="store_true", help="the start level train would learn from the scene's recordings")
    args = ap.parse_args()
    specs = [s for s in args.scenes.replace(";", "|").split("|")]
    specs = [x for s in specs for x in (s.split(",") if s == DEFAULT.split(";")[0] else [s])]
    config = Config()
    root = scratch(args.out, "tactiled-detect-")
    if args.mid_slide or args.lead is not None:
        print(f"| scene | starts {'mid-slide' if args.mid_slide else f'{args.lead:g} s before a slide'} | first slide ended by a quiet "
              "| of those, taking in more than one true slide | its start error median / p90, s |")
        print("|---|---|---|---|---|")
    else:
        print("| scene | true slides | detections | recall | precision | start error median / p90, s | end error median / p90, s "
              "| early ends withdrawn |")
        print("|---|---|---|---|---|---|---|---|")
    for spec in specs:
        folder = root / spec.replace(",", "+")
        paths = sorted(folder.glob("*.npz")) if args.reuse else []
        if not paths:
            paths = write_dataset(folder, scene=spec, seed=args.seed, files_per_surface=args.files_per_surface,
                                  slides_per_file=args.slides_per_file)
        level = learnt_level(paths, config) if args.start_level else None
        if args.start_level:
            print(f"<!-- {spec}: start level {level} -->", flush=True)
        if args.mid_slide or args.lead is not None:
            cuts, quiet, merged, errs = mid_slide(paths, config, level, args.lead)
            err = f"{np.median(errs):.3f} / {np.percentile(errs, 90):.3f}" if errs else "-"
            print(f"| {spec} | {cuts} | {quiet} | {merged} | {err} |", flush=True)
            continue
        n_true = n_det = paired = withdrawn = 0
        starts, ends = [], []
        for p in paths:
            rec = load_recording(p)
            truth = [(a, b) for a, b, _ in rec.slides()]
            events = detector_events(rec, config, level)  # one pass: the slides, and the early ends withdrawn (Resume)
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


def learnt_level(paths: list[Path], config: Config) -> float | None:
    """The start level train would learn from the recordings at ``paths`` (their true slides)."""
    recs = [load_recording(p) for p in paths]
    return start_level(recs, [[(a, b) for a, b, _ in r.slides()] for r in recs], config.detector)


def mid_slide(paths: list[Path], config: Config, level: float | None = None,
              lead: float | None = None) -> tuple[int, int, int, list[float]]:
    """(streams cut 40 % into each of the first three slides of each recording, or ``lead`` s before each; those whose first
    detected slide a quiet ended (the others end with the stream); those of them whose first slide overlaps more than one
    true slide; the start error of each such first slide against the true slide it overlaps most, s (a stream cut inside
    a slide: against the cut))."""
    cuts = quiet = merged = 0
    errors: list[float] = []
    for p in paths:
        rec = load_recording(p)
        truth = [(a, b) for a, b, _ in rec.slides()]
        for a, b in truth[:3]:
            cut = a + (b - a) * 2 // 5 if lead is None else max(0, a - round(lead * rec.fs))
            ends = [e for e in detector_events(Recording(rec.samples[cut:], rec.fs, rec.volts_per_count), config, level) if isinstance(e, Offset)]
            cuts += 1
            if not ends or ends[0].reason != "quiet":
                continue
            quiet += 1
            first = ends[0]
            overlaps = [(min(first.stop, hi - cut) - max(first.start, lo - cut), lo) for lo, hi in truth if hi > cut]
            merged += sum(o > 0 for o, _ in overlaps) > 1
            errors.append(abs(first.start - max(0, max(overlaps)[1] - cut)) / rec.fs)
    return cuts, quiet, merged, errors


if __name__ == "__main__":
    main()
