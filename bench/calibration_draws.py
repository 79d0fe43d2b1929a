"""Calibration and the nested estimate over several training sets per scene: temperature scaling against Platt scaling.

One training set (``--seeds``, 3 files x 3 slides per surface by default) says little about a confidence map fitted on
its 135 out-of-fold slides, or about a nested estimate from them: both move with the draw. For each scene and training
seed this trains ``tactiled train``'s default search (its winner and nested CV), refits the winner on the outer folds and
on every slide exactly as ``train`` does, and scores the true slides of one fixed same-unit test set (seed 200, 10 files x
3 slides per surface: 450 slides) with two confidences fitted on the same out-of-fold slide scores:

- ``temperature``: ``train``'s (:func:`tactiled.learn.search.fit_calibration`): temperature scaling, no map on top;
- ``platt``: what ``train`` did before 2026-11-26, written out here: a label-smoothed temperature, then Platt scaling of
  the top probability's logit (isotonic regression from 200 slides), kept within [1/(n+2), 1 - 1/(n+2)].

Labels are the same for both (a temperature never changes the top class). Prints one row per draw (accuracy, ECE of
each, nested CV minus test accuracy, the nested CV's 95 % interval over recordings) and a summary; true slides and the
winner's own windows, not the daemon's detector (``bench/labels.py`` is the end-to-end measurement; on the draws measured
both gave the same ECE to 0.002).

Usage: python bench/calibration_draws.py [--scenes "hand;hot-gain"] [--seeds 100,101] [--files 3] [--test-files 10]
       [--out DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path
from typing import Any

import numpy as np
from scratch import scratch

from tactiled.config import Config
from tactiled.core.analysis import window_settings
from tactiled.learn import search as S
from tactiled.learn.dataset import collect_windows, load_recordings
from tactiled.learn.model import fit_temperature, softmax
from tactiled.learn.score import calibration_scores
from tactiled.learn.train import train
from tactiled.sim.simulate import write_dataset


def platt_map(oof: np.ndarray, y: np.ndarray, temperature: float) -> np.ndarray:
    """The confidence map ``train`` fitted before 2026-11-26: knots (2, 101) from the top probability at ``temperature``."""
    from sklearn.isotonic import IsotonicRegression
    from sklearn.linear_model import LogisticRegression

    ok = (y >= 0) & np.isfinite(oof).any(axis=1)
    p = softmax(oof[ok], temperature)
    top, right = p.max(axis=1), (p.argmax(axis=1) == y[ok]).astype(np.float64)
    n = len(top)
    grid = np.linspace(0.0, 1.0, 101)
    if n < 10 or right.min() == right.max():
        value = np.full_like(grid, (right.sum() + 1.0) / (n + 2.0))
    elif n >= 200:
        value = IsotonicRegression(y_min=0.0, y_max=1.0, out_of_bounds="clip").fit(top, right).predict(grid)
    else:
        def logit(q: np.ndarray) -> np.ndarray:
            q = np.clip(q, 1e-6, 1 - 1e-6)
            return np.log(q / (1 - q))

        fit = LogisticRegression(C=100.0).fit(logit(top)[:, None], right)
        value = fit.predict_proba(logit(grid)[:, None])[:, 1] if fit.coef_[0, 0] > 0 else np.full_like(grid, right.mean())
    value = np.clip(np.maximum.accumulate(value), 1.0 / (n + 2), 1.0 - 1.0 / (n + 2))
    return np.vstack([grid, value])


def one_draw(spec: str, seed: int, root: Path, files: int, test_files: int, config: Config) -> dict[str, Any]:
    """ECE of both confidences and nested CV minus test accuracy for training seed ``seed`` of scene ``spec``."""
    name = spec.replace(",", "+")
    tr_paths = write_dataset(root / name / f"train{seed}", scene=spec, seed=seed, files_per_surface=files, slides_per_file=3)
    test_dir = root / name / "test"
    te_paths = sorted(test_dir.glob("*.npz")) or write_dataset(test_dir, scene=spec, seed=200, files_per_surface=test_files, slides_per_file=3)
    res = train(tr_paths, config, progress=lambda m: None)
    tr, te = load_recordings(tr_paths), load_recordings(te_paths)
    c = next(c for c in S.default_candidates() if c.name == res.winner)
    fs, channels = tr[0][1].fs, tr[0][1].channels
    st = window_settings(config, channels, fs, c.duration_s, S.base_families(c.families), start_s=c.start_s, max_windows=c.max_windows)
    assert st is not None
    wtr, wte = collect_windows(tr, config, st, jobs=1), collect_windows(te, config, st, jobs=1)
    if c.fusion == "features":
        wtr, wte = wtr.averaged(), wte.averaged()
    classes = sorted({s.label for s in wtr.slides if s.label})
    ytr = np.array([classes.index(str(s.label)) for s in wtr.slides])
    yte = np.array([classes.index(str(s.label)) for s in wte.slides])
    oof = np.full((len(wtr.slides), len(classes)), -np.inf)
    for a, b in S.slide_folds(wtr, 5, 0):
        cols, pipe, _ = S.fit_candidate(wtr, S._window_rows(wtr, a), c, 0, 3)
        oof[b] = S.slide_scores(wtr, pipe, cols, b, classes)
    cols, pipe, _ = S.fit_candidate(wtr, S._window_rows(wtr, np.arange(len(wtr.slides))), c, 0, 3)
    scores = S.slide_scores(wte, pipe, cols, np.arange(len(wte.slides)), classes)
    t_new, knots_new, _ = S.fit_calibration(oof, ytr)
    t_old = fit_temperature(oof, ytr)
    knots_old = platt_map(oof, ytr, t_old)
    right = softmax(scores, t_new).argmax(axis=1) == yte
    out: dict[str, Any] = {"scene": spec, "seed": seed, "winner": res.winner, "accuracy": float(right.mean()), "nested": res.nested["mean"],
                           "interval": res.nested.get("interval95")}
    for key, t, knots in (("temperature", t_new, knots_new), ("platt", t_old, knots_old)):
        conf = np.interp(softmax(scores, t).max(axis=1), knots[0], knots[1])
        out[key] = {"ece": calibration_scores(conf, right)["ece"], "mean_confidence": float(conf.mean())}
    return out


def _band(interval: list[float] | None) -> str:
    return f"{100 * interval[0]:.1f}–{100 * interval[1]:.1f} %" if interval else "-"


def main() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", default="hand;hot-gain;one-channel;fluctuating,one-channel", help="scene specs separated by ';'")
    ap.add_argument("--seeds", default="100,101,102,103", help="training-set seeds (bench/labels.py's is 100)")
    ap.add_argument("--files", type=int, default=3, help="training files per surface")
    ap.add_argument("--test-files", type=int, default=10, help="test files per surface")
    ap.add_argument("--out", default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    root = scratch(args.out, "tactiled-caldraws-")
    config = Config()
    rows: list[dict[str, Any]] = []
    print("| scene | seed | winner | accuracy | ECE: temperature / Platt | mean confidence: temperature / Platt | nested CV - test "
          "| nested CV's 95 % interval over recordings |")
    print("|---|---|---|---|---|---|---|---|", flush=True)
    for spec in args.scenes.split(";"):
        for seed in (int(s) for s in args.seeds.split(",")):
            r = one_draw(spec, seed, root, args.files, args.test_files, config)
            rows.append(r)
            print(f"| {spec} | {seed} | {r['winner']} | {100 * r['accuracy']:.1f} % | {r['temperature']['ece']:.3f} / {r['platt']['ece']:.3f} | "
                  f"{r['temperature']['mean_confidence']:.3f} / {r['platt']['mean_confidence']:.3f} | "
                  f"{100 * (r['nested'] - r['accuracy']):+.1f} | {_band(r['interval'])} |", flush=True)
            if args.json:
                Path(args.json).write_text(json.dumps(rows, indent=1))
    for key in ("temperature", "platt"):
        e = [r[key]["ece"] for r in rows]
        print(f"{key}: ECE <= 0.05 on {sum(x <= 0.05 for x in e)} of {len(e)} draws; mean {statistics.mean(e):.3f}, max {max(e):.3f}")
    lower = sum(r["temperature"]["ece"] < r["platt"]["ece"] for r in rows)
    gaps = [100 * (r["nested"] - r["accuracy"]) for r in rows]
    print(f"temperature below Platt on {lower} of {len(rows)} draws; nested CV - test: mean {statistics.mean(gaps):+.1f}, "
          f"sd {statistics.pstdev(gaps):.1f} points, within 5 points on {sum(abs(g) <= 5 for g in gaps)} of {len(gaps)}")
    inside = [r for r in rows if r["interval"] and r["interval"][0] <= r["accuracy"] <= r["interval"][1]]
    widths = [100 * (r["interval"][1] - r["interval"][0]) for r in rows if r["interval"]]
    print(f"test accuracy inside the nested CV's 95 % interval over recordings on {len(inside)} of {len(rows)} draws; "
          f"interval width median {statistics.median(widths):.1f} points" if widths else "no interval")


if __name__ == "__main__":
    main()
