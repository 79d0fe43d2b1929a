"""Does training on speed-perturbed copies of each slide help another unit of the sensor? Measured before building it.

A surface's spectrum moves with the sliding speed, and another unit's film resonances sit up to 15 % away from this
one's (docs/simulator.md). Speed perturbation (resampling each training slide by a factor near 1, as speech recognition
does against speaking rate) teaches a classifier that a spectrum a few per cent higher or lower is the same surface.

Per scene: a training set on unit 0, a same-unit test set and one test set per other unit (new specimens each), as
bench/labels.py makes them (``--mixed``: its far-apart set). The plain baseline of bench/labels.py (per true slide and
channel: 24 Welch log band energies, log centroid, kurtosis; StandardScaler; RBF SVM, C = 10) is trained on the true
slides alone and with copies of every training slide resampled by each ``--factors`` pair (``10/11`` is 10 samples for
every 11: the slide played 10 % faster, its spectrum 10 % higher), and tested on the unchanged test slides.

Usage: python bench/speed_augment.py [--scenes "hand;robot"] [--mixed] [--other-units 1,2,3,4] [--out DIR]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from labels import dataset, plain_features
from scipy import signal
from scratch import scratch
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler
from sklearn.svm import SVC

from tactiled.learn.dataset import load_recordings

SETS = {"none": (), "±5 %": ((20, 21), (21, 20)), "±10 %": ((10, 11), (11, 10)), "±5, ±10 %": ((20, 21), (21, 20), (10, 11), (11, 10))}


def slide_rows(paths: list[Path], factors: tuple[tuple[int, int], ...]) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]:
    """{(up, down): (features (n, F), surfaces (n,))} of every true slide, resampled by up/down ((1, 1): as recorded)."""
    out: dict[tuple[int, int], tuple[list[list[float]], list[str]]] = {f: ([], []) for f in ((1, 1), *factors)}
    for _name, rec in load_recordings(paths):
        volts = rec.samples.astype(np.float64) * rec.volts_per_count
        for a, b, surface in rec.slides():
            for (up, down), (rows, labels) in out.items():
                x = volts[a:b] if up == down else signal.resample_poly(volts[a:b], up, down, axis=0)
                rows.append(plain_features(x, rec.fs))
                labels.append(surface)
    return {f: (np.array(r), np.array(y)) for f, (r, y) in out.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="hand;robot;continuous;one-channel;fluctuating;hot-gain;grating;continuous,one-channel")
    ap.add_argument("--mixed", action="store_true", help="bench/labels.py's far-apart set of 8 grades and 7 gratings")
    ap.add_argument("--other-units", default="1,2,3,4")
    ap.add_argument("--out", help="folder for the recordings (default: a temporary one)")
    args = ap.parse_args()
    root = scratch(args.out, "tactiled-speed-")
    units = [int(u) for u in args.other_units.split(",")]
    print(f"| scene | copies | same unit | {' | '.join(f'unit {u}' for u in units)} | other units, mean |")
    print(f"|---|---|---|{'---|' * len(units)}---|")
    every = tuple(f for fs in SETS.values() for f in fs)
    for scene in args.scenes.split(";"):
        train = slide_rows(dataset(root / scene / "train", scene, 100, 3, 3, args.mixed), every)
        tests = {"same": slide_rows(dataset(root / scene / "same", scene, 200, 2, 3, args.mixed), ())[(1, 1)]}
        for u in units:
            tests[f"unit {u}"] = slide_rows(dataset(root / scene / f"unit{u}", scene, 200 + 100 * u, 2, 3, args.mixed, unit=u, specimen=u), ())[(1, 1)]
        for name, factors in SETS.items():
            x = np.concatenate([train[f][0] for f in ((1, 1), *factors)])
            y = np.concatenate([train[f][1] for f in ((1, 1), *factors)])
            clf = make_pipeline(StandardScaler(), SVC(C=10.0)).fit(x, y)
            acc = {k: 100 * float(np.mean(clf.predict(tx) == ty)) for k, (tx, ty) in tests.items()}
            other = np.mean([acc[f"unit {u}"] for u in units])
            print(f"| {scene}{' (far apart)' if args.mixed else ''} | {name} | " + " | ".join(f"{a:.1f}" for a in acc.values())
                  + f" | {other:.1f} |", flush=True)


if __name__ == "__main__":
    main()
