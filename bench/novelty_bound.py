"""Oracle bound on telling the left-out grades from known ones: can ANY novelty score on these features reach 80 %?

Per scene, the files and seeds of bench/labels.py's leave-out protocol (unit 0; training: 3 files x 3 slides per
surface, seed 100; same-unit test: 2 files x 3 slides, seed 200; Ra0.61, Ra1.40, Ra3.19 left out, the three grades
of ``LEAVE_OUT``). The population is the union of the training and test slides of all 15 grades: positives are the
left-out grades' slides, negatives the known ones. Two feature sets:

- **model**: the features of the model ``tactiled train`` (defaults) makes from the 12 known grades' training files,
  each slide's mean features standardised as its classifier sees them (bench/novelty.py's ``slide_rows``);
- **plain**: bench/labels.py's plain spectral baseline (``plain_features``: per channel the log energy in 24 log-spaced
  bands of the whole-slide Welch PSD, log centroid, kurtosis; true slide bounds), standardised on the known training slides.

Scores, each read off the ROC at the threshold that rejects 5 % and 10 % of the known slides (the largest share of
left-out slides caught at that false-alarm rate), with the ROC AUC:

- **oracle LR / oracle SVM**: a supervised binary classifier (StandardScaler, then logistic regression or an RBF SVM,
  ``class_weight="balanced"``) trained to separate left-out slides from known ones; C (and gamma) chosen by an inner
  grouped 5-fold CV (ROC AUC) inside each outer fold; out-of-fold scores from leave-one-recording-out over the union.
  It is shown the unknown class, so no novelty detector on the same features does better, up to noise (and up to how
  well it learns from 45 positive slides): the ceiling.
- **oracle 15-grade SVM**: a 15-grade classifier (the plain baseline's StandardScaler + RBF SVM, C=10, sigmoid-calibrated)
  trained on every grade, left-out ones included; the score is its probability of a left-out grade (leave one
  recording out). With 45 positive slides the binary separators are data-limited; this one uses the grades' structure.
- **centroid**: distance to the nearest known surface's centroid (the mean of its training slides);
- **3-NN**: mean distance to the 3 nearest known training slides;
- **ratio**: the model's distance ratio (tactiled's ``novelty_parts``: nearest surface's 3-NN distance over the next one's).

The unsupervised scores use only the known grades' training slides as reference, each slide scored against those of
the *other* recordings (so a training slide is scored leave-one-recording-out, a test slide against all of them).
A "test only" read-off restricts both classes to the same-unit test slides (the population bench/labels.py reports).

Usage: nice -n 10 python bench/novelty_bound.py [--scenes "robot;hand;one-channel"] [--out DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from labels import LEAVE_OUT, plain_rows, ra  # bench/ is first on sys.path when run as a script
from novelty import scores as ratio_scores
from novelty import slide_rows
from scratch import scratch

from tactiled.config import Config
from tactiled.learn.dataset import load_recordings
from tactiled.learn.train import train
from tactiled.sim.simulate import write_dataset

RATES = (0.05, 0.10)


class _K:
    """What bench/novelty.py's ``scores`` reads of a model when given the training rows: its ``k``."""

    def __init__(self, k: int) -> None:
        self.novelty_k = k


def per_recording(recs: list[tuple[str, Any]], rows: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, labels, recording index) of every slide, ``rows`` applied to one recording at a time."""
    xs, ys, gs = [], [], []
    for g, rec in enumerate(recs):
        x, y = rows([rec])
        xs.append(x)
        ys.append(y)
        gs.append(np.full(len(y), g))
    return np.vstack(xs), np.concatenate(ys).astype(str), np.concatenate(gs)


def read_off(s: np.ndarray, pos: np.ndarray) -> dict[str, float]:
    """Share of positives caught at the thresholds rejecting at most 5 % / 10 % of negatives, and the ROC AUC."""
    from sklearn.metrics import roc_auc_score, roc_curve

    fpr, tpr, _ = roc_curve(pos, s)
    out = {f"caught@{int(100 * r)}": float(tpr[fpr <= r + 1e-12].max()) for r in RATES}
    out["auc"] = float(roc_auc_score(pos, s))
    return out


def oracle(x: np.ndarray, pos: np.ndarray, groups: np.ndarray, kind: str) -> np.ndarray:
    """Out-of-fold decision scores of the supervised separator, leave one recording out, hyperparameters by inner CV."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.model_selection import GridSearchCV, LeaveOneGroupOut, StratifiedGroupKFold
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler
    from sklearn.svm import SVC

    f = x.shape[1]
    if kind == "LR":
        est = make_pipeline(StandardScaler(), LogisticRegression(class_weight="balanced", max_iter=5000))
        grid = {"logisticregression__C": [0.01, 0.1, 1.0, 10.0, 100.0]}
    else:
        est = make_pipeline(StandardScaler(), SVC(kernel="rbf", class_weight="balanced"))
        grid = {"svc__C": [0.1, 1.0, 10.0, 100.0, 1000.0], "svc__gamma": [g / f for g in (0.1, 0.3, 1.0, 3.0, 10.0, 30.0)]}
    out = np.zeros(len(pos))
    for tr, te in LeaveOneGroupOut().split(x, pos, groups):
        inner = StratifiedGroupKFold(n_splits=5, shuffle=True, random_state=0)
        search = GridSearchCV(est, grid, scoring="roc_auc", cv=inner.split(x[tr], pos[tr], groups[tr]))
        out[te] = search.fit(x[tr], pos[tr]).decision_function(x[te])
    return out


def oracle_grades(x: np.ndarray, y: np.ndarray, groups: np.ndarray, gone: set[str]) -> np.ndarray:
    """Out-of-fold P(a left-out grade) of a 15-grade classifier (StandardScaler, RBF SVM C=10 as the plain baseline,
    sigmoid-calibrated), leave one recording out: an oracle that also knows which grade each slide is."""
    from sklearn.calibration import CalibratedClassifierCV
    from sklearn.model_selection import LeaveOneGroupOut
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler
    from sklearn.svm import SVC

    out = np.zeros(len(y))
    for tr, te in LeaveOneGroupOut().split(x, y, groups):
        clf = make_pipeline(StandardScaler(), CalibratedClassifierCV(SVC(C=10.0), ensemble=False)).fit(x[tr], y[tr])
        out[te] = clf.predict_proba(x[te])[:, np.isin(clf.classes_, sorted(gone))].sum(axis=1)
    return out


def unsupervised(z: np.ndarray, y: np.ndarray, groups: np.ndarray, ref: np.ndarray, k: int) -> dict[str, np.ndarray]:
    """Centroid, 3-NN and ratio scores of every row against the reference rows ``ref`` (bool) of the other recordings."""
    out = {"centroid": np.zeros(len(z)), "3-NN": np.zeros(len(z)), "ratio": np.zeros(len(z))}
    for g in np.unique(groups):
        rows = groups == g
        keep = ref & (groups != g)
        tz, ty = z[keep], y[keep]
        cents = np.array([tz[ty == s].mean(axis=0) for s in np.unique(ty)])
        out["centroid"][rows] = np.sqrt(((z[rows, None, :] - cents[None]) ** 2).sum(axis=2)).min(axis=1)
        d = np.sqrt(((z[rows, None, :] - tz[None]) ** 2).sum(axis=2))
        out["3-NN"][rows] = np.sort(d, axis=1)[:, :3].mean(axis=1)
        out["ratio"][rows] = ratio_scores(_K(k), z[rows], tz, ty)["ratio"]  # type: ignore[arg-type]
    return out


def scene(spec: str, root: Path, config: Config) -> dict[str, Any]:
    name = "leave-" + spec.replace(",", "+")
    tr = write_dataset(root / name / "train", scene=spec, seed=100, files_per_surface=3, slides_per_file=3)
    te = write_dataset(root / name / "test", scene=spec, seed=200, files_per_surface=2, slides_per_file=3)
    recs = load_recordings(tr + te)
    is_train_rec = np.array([i < len(tr) for i in range(len(recs))])
    surfaces = sorted({s for _, r in recs for _, _, s in r.slides()}, key=ra)
    gone = {surfaces[i] for i in LEAVE_OUT}
    keep = [p for p in tr if not any(f"_{g}_" in p.name for g in gone)]
    t0 = time.perf_counter()
    model = train(keep, config, progress=lambda m: None).model
    train_s = time.perf_counter() - t0
    feats = {"model": per_recording(recs, lambda r: slide_rows(r, config, model)), "plain": per_recording(recs, plain_rows)}
    out: dict[str, Any] = {"left_out": sorted(gone, key=ra), "model_features": list(model.names), "model_kind": model.kind,
                           "train_s": train_s, "sets": {}}
    for fname, (x, y, g) in feats.items():
        pos = np.isin(y, sorted(gone))
        in_train = is_train_rec[g]
        ref = in_train & ~pos
        if fname == "plain":  # standardised on the known training slides
            mu, sd = x[ref].mean(axis=0), x[ref].std(axis=0)
            x = (x - mu) / np.where(sd > 0, sd, 1.0)
        sc = {f"oracle {k}": oracle(x, pos, g, k) for k in ("LR", "SVM")}
        sc["oracle 15-grade SVM"] = oracle_grades(x, y, g, gone)
        sc.update(unsupervised(x, y, g, ref, model.novelty_k))
        test = ~in_train
        out["sets"][fname] = {
            "dims": int(x.shape[1]),
            "slides": {"known train": int((in_train & ~pos).sum()), "known test": int((test & ~pos).sum()),
                       "left-out train": int((in_train & pos).sum()), "left-out test": int((test & pos).sum())},
            "union": {k: read_off(s, pos) for k, s in sc.items()},
            "test only": {k: read_off(s[test], pos[test]) for k, s in sc.items()},
        }
    return out


def main() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="robot;hand;one-channel", help="scene specs separated by ';'")
    ap.add_argument("--out", default=None, help="directory for the simulated files (default: a temporary one)")
    ap.add_argument("--json", default=None, help="write every number here")
    args = ap.parse_args()
    config = Config()
    root = scratch(args.out, "tactiled-bound-")
    result: dict[str, Any] = {}
    t0 = time.perf_counter()
    for spec in args.scenes.split(";"):
        r = result[spec] = scene(spec, root, config)
        print(f"\n{spec}: left out {', '.join(r['left_out'])}; model {r['model_kind']} on {len(r['model_features'])} features "
              f"({', '.join(r['model_features'])}); train {r['train_s']:.0f} s")
        for fname, s in r["sets"].items():
            print(f"  {fname} ({s['dims']} dims) slides: " + ", ".join(f"{k} {v}" for k, v in s["slides"].items()))
        print("| feature set | score | union: caught @5 % / @10 % known rejected | AUC | test only: @5 % / @10 % | AUC |")
        print("|---|---|---|---|---|---|")
        for fname, s in r["sets"].items():
            for k, u in s["union"].items():
                t = s["test only"][k]
                print(f"| {fname} | {k} | {100 * u['caught@5']:.1f} / {100 * u['caught@10']:.1f} % | {u['auc']:.3f} "
                      f"| {100 * t['caught@5']:.1f} / {100 * t['caught@10']:.1f} % | {t['auc']:.3f} |", flush=True)
        if args.json:
            Path(args.json).write_text(json.dumps(result, indent=1))
    print(f"\ntotal {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
