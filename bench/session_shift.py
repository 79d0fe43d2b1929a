"""Could a daemon tell, without labels, that its fingertip is another unit than the one the model was trained on?

Per scene, bench/labels.py's recordings (unit 0 for training; new recordings of unit 0, and units 1 and 2 with new
specimens, for testing): a model trained with ``tactiled train --novelty far`` (the default's classifier; each final
label's ``novelty`` is then the slide's distance to the nearest taught surface in the classifier's own standardised
features, over the 95 % quantile of the training slides' distances to their surface's other recordings). A session
of another unit would show as slides farther from the training set than a session of the same unit. Prints, per
test set, the 10/25/50/75/90th percentiles of that ratio over the set's final labels, and the median's ratio to the
same unit's.

Usage: python bench/session_shift.py [--scenes "hand;robot;one-channel;continuous;fluctuating"] [--out DIR]
"""

from __future__ import annotations

import argparse

import numpy as np
from labels import dataset
from scratch import scratch

from tactiled.config import Config
from tactiled.learn.dataset import load_recordings
from tactiled.learn.train import train
from tactiled.run.replay import replay_recording

SETS = {"same": (200, 0), "other1": (300, 1), "other2": (400, 2)}  # bench/labels.py's seeds, units and specimens


def main() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="hand;robot;one-channel;continuous;fluctuating")
    ap.add_argument("--out", help="folder for the recordings (default: a temporary one)")
    args = ap.parse_args()
    root = scratch(args.out, "tactiled-shift-")
    config = Config()
    print("| scene | same unit: novelty 10/25/50/75/90 % | unit 1 | unit 2 | median over the same unit's: unit 1 / unit 2 |")
    print("|---|---|---|---|---|")
    for spec in args.scenes.split(";"):
        name = spec.replace(",", "+")
        model = train(dataset(root / name / "train", spec, 100, 3, 3), config, progress=lambda m: None, novelty="far").model
        cells, medians = [], []
        for set_name, (seed, unit) in SETS.items():
            recs = load_recordings(dataset(root / name / set_name, spec, seed, 2, 3, unit=unit, specimen=unit))
            ratios = np.array([r.novelty for _, rec in recs for r in replay_recording(rec, config, model) if r.final and r.novelty is not None])
            q = np.percentile(ratios, [10, 25, 50, 75, 90])
            cells.append(" / ".join(f"{v:.3f}" for v in q) + f" ({ratios.size})")
            medians.append(q[2])
        print(f"| {spec} | {' | '.join(cells)} | {medians[1] / medians[0]:.2f} / {medians[2] / medians[0]:.2f} |", flush=True)


if __name__ == "__main__":
    main()
