"""Another unit further from the training unit than docs/simulator.md's tolerance: do the labels and the unknown-surface test hold?

Per scene: the default model (``tactiled train`` with its defaults) trained on unit 0, as bench/labels.py trains it, and
tested end to end (every true slide; an unknown counts as wrong) on units 1-4 drawn within the simulator's manufacturing
tolerance scaled by 1, 1.5 and 2 (each film's resonance, gain and damping, and the cross-talk: ±15 % resonance becomes
±22.5 % and ±30 %), each with new specimens; beside the plain baseline of bench/labels.py trained on the same files. Prints
the default's accuracy, its top class, the share of known slides it calls unknown, and the plain baseline's accuracy,
means over the four units.

Usage: python bench/wider_units.py [--scenes "hand;robot;one-channel"] [--mixed] [--out DIR]
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np
from labels import dataset, end_to_end, plain_baseline
from scratch import scratch

import tactiled.sim.physics as physics
from tactiled.config import Config
from tactiled.learn.dataset import load_recordings
from tactiled.learn.train import train

UNITS = (1, 2, 3, 4)
SCALES = (1.0, 1.5, 2.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="hand;robot;one-channel")
    ap.add_argument("--mixed", action="store_true", help="bench/labels.py's far-apart set of 8 grades and 7 gratings")
    ap.add_argument("--out", help="folder for the recordings (default: a temporary one)")
    args = ap.parse_args()
    root = scratch(args.out, "tactiled-wider-")
    config = Config()
    nominal = physics.Tolerance()
    print("| scene | tolerance | default, unknowns wrong | default, top class | known slides called unknown | plain baseline |")
    print("|---|---|---|---|---|---|")
    for spec in args.scenes.split(";"):
        tr = dataset(root / spec / "train", spec, 100, 3, 3, args.mixed)
        model = train(tr, config, progress=lambda m: None).model
        train_recs = load_recordings(tr)
        for scale in SCALES:
            wide = dataclasses.replace(nominal, resonance=nominal.resonance * scale, film_gain=nominal.film_gain * scale,
                                       damping=nominal.damping * scale, crosstalk=nominal.crosstalk * scale)
            physics.other_unit.__defaults__ = (wide,)  # write_dataset draws every other unit within this tolerance
            others = {u: load_recordings(dataset(root / spec / f"x{scale:g}" / f"unit{u}", spec, 200 + 100 * u, 2, 3, args.mixed,
                                                 unit=u, specimen=u)) for u in UNITS}
            plain = plain_baseline(train_recs, others)
            scored = [end_to_end(recs, config, model) for recs in others.values()]
            unknown = np.mean([s["unknown"] / max(1, s["n"]) for s in scored])
            print(f"| {spec}{' (far apart)' if args.mixed else ''} | {scale:g}x | {100 * np.mean([s['accuracy'] for s in scored]):.1f} % | "
                  f"{100 * np.mean([s['top_accuracy'] for s in scored]):.1f} % | {100 * unknown:.1f} % | {100 * np.mean(list(plain.values())):.1f} % |",
                  flush=True)
        physics.other_unit.__defaults__ = (nominal,)


if __name__ == "__main__":
    main()
