"""Which whole-slide spectral representation survives another unit of the sensor? Tried before choosing, kept as a record.

Per scene: a training set on unit 0 and test sets on the same unit and on units 1 and 2 (new specimens each), as
bench/labels.py makes them. Per true slide, per channel: the log energy in 24 log-spaced bands from 20 Hz to
0.45 fs (Welch, 1024-sample segments at 20 kHz scaled to the rate) and the kurtosis. Representations:

- ``plain``: the band levels as they are (the plain baseline's);
- ``shape``: each channel's levels less their mean across bands, with that mean as one more feature;
- ``shape-only``: the same without the mean (blind to gain);
- ``slope``: differences between neighbouring bands, with the mean level;
- ``cepstrum``: the first 8 DCT coefficients of each channel's levels;
- each also trained with augmentation: 4 copies of every training slide with a random gain (±1.6 dB per channel) and
  a random smooth bump (±3 dB, 1.5–4 bands wide) on its levels.

Then a unit calibration: the levels of a new unit corrected by its mean offset from unit 0 per band, estimated on
the first recording of 5 (or all 15) known surfaces on that unit, and tested on its other recordings (``full``: per
band; ``degN``: a polynomial of degree N in log frequency through the offsets).

Classifier: StandardScaler and an RBF SVM (C = 10), as in the plain baseline.

Usage: python bench/unit_shift.py [--scenes robot,hand,continuous] [--out DIR]
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import numpy as np
from scipy import fft, signal, stats
from scratch import scratch
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler
from sklearn.svm import SVC

from tactiled.learn.dataset import load_recordings
from tactiled.sim.simulate import write_dataset

MODES = ("plain", "shape", "shape-only", "slope", "cepstrum")


def slide_levels(paths: list[Path]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(levels (n, C, 24) natural-log band energies, kurtosis (n, C), surface (n,), recording name (n,)) of every true slide."""
    levels, kurt, surface, names = [], [], [], []
    for name, rec in load_recordings(paths):
        volts = rec.samples.astype(np.float64) * rec.volts_per_count
        nper = max(64, round(1024 * rec.fs / 20000))
        edges = np.geomspace(20.0, 0.45 * rec.fs, 25)
        for a, b, s in rec.slides():
            x = volts[a:b]
            f, p = signal.welch(x, fs=rec.fs, nperseg=min(nper, len(x)), axis=0)
            levels.append([[np.log(p[(f >= lo) & (f < hi), c].sum() + 1e-20) for lo, hi in itertools.pairwise(edges)] for c in range(x.shape[1])])
            kurt.append(np.nan_to_num(stats.kurtosis(x, axis=0)))
            surface.append(s)
            names.append(Path(name).name)
    return np.array(levels), np.array(kurt), np.array(surface), np.array(names)


def features(levels: np.ndarray, kurt: np.ndarray, mode: str) -> np.ndarray:
    """Rows (n, F) of one representation."""
    mean = levels.mean(axis=2, keepdims=True)
    part = {"plain": levels, "shape": np.concatenate([levels - mean, mean], axis=2), "shape-only": levels - mean,
            "slope": np.concatenate([np.diff(levels, axis=2), mean], axis=2), "cepstrum": fft.dct(levels, norm="ortho", axis=2)[:, :, :8]}[mode]
    return np.hstack([part.reshape(len(part), -1), kurt])


def augment(levels: np.ndarray, kurt: np.ndarray, y: np.ndarray, copies: int, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """The training slides plus ``copies`` of each with a random gain per channel and a random smooth bump on the levels."""
    out_l, out_k, out_y = [levels], [kurt], [y]
    bands = np.arange(levels.shape[2])
    for _ in range(copies):
        gain = rng.uniform(-1, 1, levels.shape[:2])[:, :, None] * 0.16 * np.log(10)
        centre = rng.uniform(0, len(bands), levels.shape[:2])[:, :, None]
        width = rng.uniform(1.5, 4.0, levels.shape[:2])[:, :, None]
        bump = rng.uniform(-1, 1, levels.shape[:2])[:, :, None] * 0.3 * np.log(10) * np.exp(-0.5 * ((bands - centre) / width) ** 2)
        out_l.append(levels + gain + bump)
        out_k.append(kurt)
        out_y.append(y)
    return np.concatenate(out_l), np.concatenate(out_k), np.concatenate(out_y)


def smooth(offset: np.ndarray, degree: int) -> np.ndarray:
    """A polynomial of ``degree`` in log band centre through each channel's offsets (C, 24)."""
    edges = np.log(np.geomspace(20.0, 9000.0, 25))
    x = (edges[:-1] + edges[1:]) / 2
    return np.array([np.polyval(np.polyfit(x, o, degree), x) for o in offset])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="robot,hand,continuous")
    ap.add_argument("--out", help="folder for the recordings (default: a temporary one)")
    args = ap.parse_args()
    root = scratch(args.out, "tactiled-unit-")
    print("| scene | representation | augmented | same unit | unit 1 | unit 2 |")
    print("|---|---|---|---|---|---|")
    calib = []
    for scene in args.scenes.split(","):
        sets = {"train": write_dataset(root / scene / "train", scene=scene, seed=100, files_per_surface=3, slides_per_file=3),
                "same": write_dataset(root / scene / "same", scene=scene, seed=200, files_per_surface=2, slides_per_file=3)}
        for u in (1, 2):
            sets[f"unit {u}"] = write_dataset(root / scene / f"other{u}", scene=scene, seed=200 + 100 * u, files_per_surface=2,
                                              slides_per_file=3, unit=u, specimen=u)
        data = {k: slide_levels(v) for k, v in sets.items()}
        lt, kt, yt, _ = data["train"]
        for mode in MODES:
            for copies in (0, 4):
                lv, kv, yv = augment(lt, kt, yt, copies, np.random.default_rng(0)) if copies else (lt, kt, yt)
                clf = make_pipeline(StandardScaler(), SVC(C=10.0)).fit(features(lv, kv, mode), yv)
                acc = [100 * np.mean(clf.predict(features(data[k][0], data[k][1], mode)) == data[k][2]) for k in ("same", "unit 1", "unit 2")]
                print(f"| {scene} | {mode} | {'yes' if copies else 'no'} | " + " | ".join(f"{a:.1f} %" for a in acc) + " |", flush=True)
        clf = make_pipeline(StandardScaler(), SVC(C=10.0)).fit(features(lt, kt, "plain"), yt)
        surfaces = sorted(set(yt), key=lambda s: float(s.removeprefix("Ra")))
        ref = {s: lt[yt == s].mean(axis=0) for s in surfaces}
        for k in ("same", "unit 1", "unit 2"):
            lv, kv, yv, names = data[k]
            for n_cal in (5, 15):
                known = {surfaces[i] for i in (range(1, 15, 3) if n_cal == 5 else range(15))}
                cal = np.array([nm.endswith("_00.npz") and s in known for s, nm in zip(yv, names, strict=True)])
                test = np.array([nm.endswith("_01.npz") for nm in names])
                offset = np.mean([lv[cal & (yv == s)].mean(axis=0) - ref[s] for s in known], axis=0)
                row = {"none": 0.0, "full": offset, **{f"deg{d}": smooth(offset, d) for d in (0, 1, 2, 3)}}
                acc = {name: 100 * np.mean(clf.predict(features(lv[test] - off, kv[test], "plain")) == yv[test]) for name, off in row.items()}
                calib.append(f"| {scene} | {k} | {n_cal} | " + " | ".join(f"{a:.1f}" for a in acc.values()) + " |")
    print("\nunit calibration (plain representation; accuracy % on each set's second recordings)\n")
    print("| scene | test set | surfaces calibrated on | none | full | deg0 | deg1 | deg2 | deg3 |")
    print("|---|---|---|---|---|---|---|---|---|")
    print("\n".join(calib))


if __name__ == "__main__":
    main()
