"""``tactiled evaluate``: the papers' experiments, and the default method's, by grouped cross-validation (mean ± sd over folds).

(a) classifiers: ELM against kNN (k = 1, 5, 9), SVM (linear, RBF), a regularised linear
    model, and the papers' plain ELM (Huang's U(−1, 1) weights, pseudo-inverse, no ridge);
(b) start point × duration of the analysis window;
(c) sampling rate: the recordings' own rate decimated with anti-aliasing (scipy.signal.decimate) by 2, 4, 10 and 20
    (from 20 kHz: 10, 5, 2, 1 kHz; ``--quick``: by 4); lost samples stay lost, with every row the filter carries them to;
(d) number of selected features;
(e) without labels: K-means (squared Euclidean, cityblock, cosine) and a SOM, Hungarian-scored;
(f) error against run time: accuracy beside the compute time per slide (features + inference)
    and the slide time that must pass before the decision;
(g) the default method (what ``tactiled train`` picks): its leaderboard, its accuracy
    against the slide time used before deciding (windows fused so far) with the compute per
    decision, and how well its confidence is calibrated (ECE, Brier, reliability diagram).

(a)–(f) use the papers' single window per slide (DWT statistics, forward selection inside
each training fold). Slides come from the daemon's detector paired with the ground truth
(:mod:`tactiled.learn.dataset`), and every true slide counts: one without a usable window is wrong.
Folds never split a recording; there are as many as the surface with fewest recordings has, at most the folds asked
for, and the report gives the number used. Every input needs two surfaces, each with two recordings.
"""

from __future__ import annotations

import functools
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy import signal

from tactiled.config import Config
from tactiled.core.analysis import AnalysisSettings
from tactiled.core.features import FeaturePlan, classifier_inputs
from tactiled.errors import TactiledError
from tactiled.files.recording import Recording, merge_ranges
from tactiled.learn.cluster import hungarian_accuracy, kmeans, som_clusters
from tactiled.learn.dataset import LabelledSlide, Progress, SlideCounts, WindowSet, check_distinct, collect_windows, find_slides
from tactiled.learn.model import decision_scores, fit_pipeline, optimistic_reason, softmax
from tactiled.learn.score import calibration_scores
from tactiled.learn.search import (
    Candidate,
    accuracy_of,
    fit_calibration,
    fold_slide_scores,
    grouped_splits,
    search,
    sfs_columns,
    slide_folds,
    window_oof,
    window_settings,
)
from tactiled.learn.train import check_two_recordings, class_table, file_labels

Folds = list[tuple[Any, Any]]
CLASSIFIERS: dict[str, tuple[str, dict[str, Any]]] = {
    "ELM": ("elm", {"n_hidden": 200, "alpha": 1e-6}),
    "ELM (plain: U(-1,1), pinv)": ("elm", {"n_hidden": 200, "alpha": 0.0, "init": "huang"}),
    "kNN k=1": ("knn", {"n_neighbors": 1}),
    "kNN k=5": ("knn", {"n_neighbors": 5}),
    "kNN k=9": ("knn", {"n_neighbors": 9}),
    "SVM linear": ("svm", {"kernel": "linear", "C": 1.0}),
    "SVM RBF": ("svm", {"kernel": "rbf", "C": 10.0, "gamma": "scale"}),
    "linear (logistic)": ("linear", {"C": 1.0, "max_iter": 1000}),
}


class Evaluator:
    """Holds the recordings, their slides, folds and caches of features and selections."""

    def __init__(self, recs: Sequence[tuple[str, Recording]], config: Config, *, folds: int = 5, max_features: int = 6,
                 seed: int = 0, progress: Progress | None = None, sfs_pool: int = 0) -> None:
        """``sfs_pool`` > 0: forward selection considers only that many features (largest ANOVA F in the fold)."""
        self.recs = list(recs)
        self.sfs_pool = sfs_pool
        self.config = config
        self.n_folds = folds
        self.max_features = max_features
        self.seed = seed
        self.progress = progress or (lambda m: None)
        self.fs = self.recs[0][1].fs
        self.channels = self.recs[0][1].channels
        self.found: dict[Any, tuple[list[list[LabelledSlide]], SlideCounts]] = {None: find_slides(self.recs, config)}
        check_distinct(self.recs)
        table = class_table(self.found[None][0], file_labels(self.recs, self.found[None][0], self.progress))
        empty = [k for k, (n, _, _) in table.items() if n == 0]
        if empty:  # as train's slide rule: a surface named only by files the detector found no slide in (it was left out unsaid)
            raise TactiledError(f"surface(s) {', '.join(empty)}: no slide detected in any of their recordings, so nothing to evaluate them on")
        if len(table) < 2:  # as train (tactiled.learn.search): one surface gives nothing to tell apart
            raise TactiledError(f"evaluation needs at least two surfaces, got {sorted(table)}")
        check_two_recordings(table)
        slides = [s for per_file in self.found[None][0] for s in per_file]
        self.folds_used = len(grouped_splits(np.array([s.label or "" for s in slides], dtype=np.str_), np.array([s.file for s in slides]), folds,
                                             seed))
        self._features: dict[tuple[Any, ...], WindowSet] = {}
        self._selection: dict[tuple[Any, ...], list[list[int]]] = {}

    def settings(self, start_s: float, duration_s: float, fs: float | None = None) -> AnalysisSettings | None:
        """One window per slide, ``duration_s`` long, ``start_s`` after its start; DWT statistics (fewer levels if it must)."""
        return window_settings(self.config, self.channels, fs or self.fs, duration_s, ["dwt"], start_s=start_s, max_windows=1)

    def features(self, st: AnalysisSettings, recs: Sequence[tuple[str, Recording]] | None = None, key: Any = None) -> WindowSet:
        """The windows of ``recs`` (default: all) under ``st``, cached per start, duration, DWT level and ``key`` (which recordings)."""
        k = (st.start_s, st.duration_s, st.level, key)
        if k not in self._features:
            if key not in self.found:
                self.found[key] = find_slides(recs or self.recs, self.config)
            self._features[k] = collect_windows(recs or self.recs, self.config, st, found=self.found[key], jobs=None)
        return self._features[k]

    def folds(self, ws: WindowSet) -> Folds:
        """Folds of ``ws``'s slides, grouped by file: (train, test) slide indices."""
        return slide_folds(ws, self.n_folds, self.seed)

    def classes(self, ws: WindowSet) -> tuple[list[str], Any]:
        """(sorted surfaces, (s,) index of each slide's surface among them, -1 when unlabelled) of ``ws``."""
        classes = sorted({s.label for s in ws.slides if s.label is not None})
        return classes, np.array([classes.index(s.label) if s.label in classes else -1 for s in ws.slides])

    def selections(self, ws: WindowSet, key: Any, folds: Folds, n_features: int | None = None) -> list[list[int]]:
        """Forward selection (ELM criterion, grouped inner CV) on each outer training fold's windows."""
        k = (key, n_features)
        if k not in self._selection:
            self._selection[k] = [sfs_columns(ws, np.flatnonzero(np.isin(ws.slide, tr)), self.seed, 3, n_features or "auto",
                                                      self.sfs_pool)
                                  for tr, _ in folds]
        return self._selection[k]

    def cv(self, ws: WindowSet, folds: Folds, sel: list[list[int]], kind: str, params: dict[str, Any]) -> dict[str, Any]:
        """Slide accuracy per fold of a classifier on each fold's selected features, and its inference time per slide."""
        classes, y_idx = self.classes(ws)
        accs = []
        for (tr, te), cols in zip(folds, sel, strict=True):
            scores = fold_slide_scores(ws, np.asarray(cols, dtype=np.intp), kind, params, tr, te, classes, self.seed)
            accs.append(accuracy_of(scores, y_idx[te]))
        return {"mean": float(np.mean(accs)), "sd": float(np.std(accs)), "folds": accs, "infer_ms": self._infer_ms(ws, sel[0], kind, params),
                "n_features": [len(c) for c in sel]}

    def _infer_ms(self, ws: WindowSet, cols: list[int], kind: str, params: dict[str, Any]) -> float:
        rows = np.flatnonzero(ws.y != "")
        if len(np.unique(ws.y[rows])) < 2:
            return 0.0
        pipe, _ = fit_pipeline(ws.x[rows][:, cols], ws.y[rows], [ws.names[j] for j in cols], kind, params, self.seed)
        x = ws.x[rows[:1]][:, cols]
        t0 = time.perf_counter()
        for _ in range(20):
            decision_scores(pipe[-1], pipe[:-1].transform(x))
        return (time.perf_counter() - t0) / 20 * 1e3

    def feature_ms(self, names: Sequence[str], st: AnalysisSettings, fs: float | None = None) -> float:
        """Median time to compute ``names`` on one window of ``st``, ms."""
        plan = FeaturePlan(names, st.wavelet, st.mode, fs=fs or self.fs, centred=st.centred)
        n = max(round(st.duration_s * (fs or self.fs)), plan.min_samples())
        x = np.random.default_rng(0).standard_normal((n, self.channels)) * 0.05
        times = []
        for _ in range(15):
            t0 = time.perf_counter()
            plan.compute(x)
            times.append(time.perf_counter() - t0)
        return float(np.median(times) * 1e3)

    # ---- experiments ---------------------------------------------------------------------

    def base(self) -> tuple[AnalysisSettings, WindowSet]:
        """The papers' settings (one 0.5 s window 0.3 s after the start, DWT statistics) and their windows; ValueError if fs cannot hold a DWT."""
        st = self.settings(0.3, 0.5)
        if st is None:
            raise ValueError(f"a 0.5 s window cannot hold a DWT at {self.fs:g} Hz")
        return st, self.features(st)

    def classifiers(self) -> dict[str, Any]:
        """(a): each classifier's slide accuracy and inference time (ms) on the base windows with per-fold forward selection.

        Also ELM and SVM RBF on all features, the features selected per fold and the detector's counts.
        """
        _, ws = self.base()
        folds = self.folds(ws)
        sel = self.selections(ws, "base", folds)
        self.progress(f"(a) classifiers on {len(ws.slides)} slides, features per fold {[len(s) for s in sel]}")
        out = {name: self.cv(ws, folds, sel, kind, params) for name, (kind, params) in CLASSIFIERS.items()}
        every = [list(range(ws.x.shape[1]))] * len(folds)
        out["ELM, all features"] = self.cv(ws, folds, every, *CLASSIFIERS["ELM"])
        out["SVM RBF, all features"] = self.cv(ws, folds, every, *CLASSIFIERS["SVM RBF"])
        selected = [[ws.names[j] for j in s] for s in sel]
        c = ws.counts
        return {"slides": len(ws.slides), "surfaces": len(self.classes(ws)[0]), "files": len(self.recs), "selected": selected, "results": out,
                "detector": {"truth": c.truth, "detected": c.detected, "missed": sum(c.missed.values()), "false": sum(c.false.values())}}

    def window_grid(self, starts: Sequence[float], durations: Sequence[float]) -> list[dict[str, Any]]:
        """(b), (f): per window start × duration (s): ELM, kNN k=9 and SVM RBF accuracy, feature time (ms) and decision time (s)."""
        rows = []
        for s in starts:
            for d in durations:
                st = self.settings(s, d)
                if st is None:
                    rows.append({"start_s": s, "duration_s": d, "skipped": "window too short for a DWT"})
                    continue
                ws = self.features(st)
                folds = self.folds(ws)
                sel = self.selections(ws, ("grid", s, d), folds)
                res = {name: self.cv(ws, folds, sel, *CLASSIFIERS[name]) for name in ("ELM", "kNN k=9", "SVM RBF")}
                feat_ms = self.feature_ms([ws.names[j] for j in max(sel, key=len)], st)
                rows.append({"start_s": s, "duration_s": d, "slides": len(ws.slides), "results": res, "feature_ms": feat_ms, "decision_s": s + d})
                self.progress(f"(b) window start {s} s, duration {d} s: ELM {res['ELM']['mean']:.3f}")
        return rows

    def sampling_rates(self, rates: Sequence[float]) -> list[dict[str, Any]]:
        """(c): ELM accuracy on the recordings decimated to each of ``rates`` (Hz), with the DWT levels that fit."""
        rows = []
        for rate in rates:
            recs = [(n, decimate(r, rate)) for n, r in self.recs] if rate < self.fs else self.recs
            st = self.settings(0.3, 0.5, rate)
            if st is None:
                rows.append({"fs": rate, "skipped": "0.5 s too short for a DWT"})
                continue
            ws = self.features(st, recs, key=("rate", rate))
            folds = self.folds(ws)
            sel = self.selections(ws, ("rate", rate), folds)
            res = self.cv(ws, folds, sel, *CLASSIFIERS["ELM"])
            rows.append({"fs": rate, "level": st.level, "slides": len(ws.slides), "ELM": res})
            self.progress(f"(c) {rate:g} Hz (level {st.level}): ELM {res['mean']:.3f}")
        return rows

    def feature_counts(self, up_to: int) -> list[dict[str, Any]]:
        """(d): ELM and kNN k=9 accuracy with forward selection stopped at 1 .. ``up_to`` features."""
        _, ws = self.base()
        folds = self.folds(ws)
        rows: list[dict[str, Any]] = []
        for n in range(1, up_to + 1):
            sel = self.selections(ws, "count", folds, n_features=n)
            rows.append({"n": n, "ELM": self.cv(ws, folds, sel, *CLASSIFIERS["ELM"]), "kNN k=9": self.cv(ws, folds, sel, *CLASSIFIERS["kNN k=9"])})
        self.progress(f"(d) features 1..{up_to}: ELM {[round(r['ELM']['mean'], 3) for r in rows]}")
        return rows

    def unsupervised(self, repeats: int = 5) -> dict[str, Any]:
        """(e): K-means (three metrics) and SOM accuracy, clusters Hungarian-matched to surfaces, over ``repeats`` seeds.

        On all features and on those every fold's forward selection picked.
        """
        _, ws = self.base()
        xin = classifier_inputs(ws.x, ws.names)
        k = len(self.classes(ws)[0])
        folds = self.folds(ws)
        sel = self.selections(ws, "base", folds)
        common = sorted(set(sel[0]).intersection(*map(set, sel[1:]))) or sel[0]
        sets = {"all features": list(range(xin.shape[1])), "selected (supervised SFS)": common}
        out: dict[str, Any] = {}
        for set_name, cols in sets.items():
            z = xin[:, cols]
            z = (z - z.mean(axis=0)) / np.where(z.std(axis=0) > 1e-12, z.std(axis=0), 1.0)
            for method in ("K-means sqeuclidean", "K-means cityblock", "K-means cosine", "SOM"):
                accs = []
                for r in range(repeats):
                    labels = som_clusters(z, k, seed=self.seed + r) if method == "SOM" else kmeans(z, k, method.split()[1], seed=self.seed + r)
                    # slides without a window cannot be clustered: they count as wrong
                    accs.append(hungarian_accuracy(labels, ws.y) * len(ws.y) / max(1, len(ws.slides)))
                out[f"{method}, {set_name}"] = {"mean": float(np.mean(accs)), "sd": float(np.std(accs)), "runs": accs}
        self.progress("(e) clustering done")
        return {"features": {k2: [ws.names[j] for j in v] if len(v) < 20 else f"{len(v)} features" for k2, v in sets.items()}, "results": out}

    def default_method(self, candidates: Sequence[Candidate] | None, times: Sequence[float]) -> dict[str, Any]:
        """(g): the search's leaderboard and winner, and the winner's accuracy against the slide time used before deciding."""
        res = search(self.recs, self.config, folds=self.n_folds, seed=self.seed, candidates=candidates, progress=self.progress,
                     found=self.found[None])
        model = res.model
        st = model.settings
        ws = self.features(AnalysisSettings(**{**st.__dict__, "names": st.names}), key=None)
        classes, y_idx = self.classes(ws)
        folds = self.folds(ws)
        oof = window_oof(ws, np.arange(len(ws.names), dtype=np.intp), model.kind, model.params, folds, classes, self.seed)
        feat_ms = self.feature_ms(ws.names, st)
        infer_ms = self._infer_ms(ws, list(range(len(ws.names))), model.kind, model.params)
        curve = []
        for t in [*times, float("inf")]:
            scores = np.full((len(ws.slides), len(classes)), -np.inf)
            n_used = np.zeros(len(ws.slides))
            for i, s in enumerate(ws.slides):
                rows = np.flatnonzero((ws.slide == i) & ((ws.spans[:, 1] - s.start) <= t * self.fs))
                if len(rows):
                    scores[i] = oof[rows].mean(axis=0)
                    n_used[i] = len(rows)
            decided = np.isfinite(scores).any(axis=1)
            curve.append({"time_s": None if t == float("inf") else t, "accuracy": accuracy_of(scores, y_idx), "decided": float(decided.mean()),
                          "windows": float(n_used[decided].mean()) if decided.any() else 0.0,
                          "compute_ms": float((feat_ms + infer_ms) * (n_used[decided].mean() if decided.any() else 0.0))})
        self.progress(f"(g) default method {res.winner}: nested CV {res.nested['mean']:.3f}")
        why = optimistic_reason(res.nested)
        return {"winner": res.winner, "nested": res.nested, "optimistic": why is not None, **({"optimistic_reason": why} if why else {}),
                "leaderboard": res.leaderboard, "feature_ms": feat_ms, "infer_ms": infer_ms, "curve": curve, "calibration": self.calibration(res)}

    def calibration(self, res: Any) -> dict[str, Any]:
        """(g) ECE, Brier and the reliability table of the chosen model's confidence, cross-fitted: each outer fold's slides
        are calibrated by a temperature and map fitted on the other folds' out-of-fold scores (the model file's are fitted on
        all of them)."""
        if res.oof is None:
            return calibration_scores(np.zeros(0), np.zeros(0, dtype=bool))
        scores, y_idx, groups = res.oof
        ok = (y_idx >= 0) & np.isfinite(scores).any(axis=1)
        confidence, right = np.zeros(len(y_idx)), np.zeros(len(y_idx), dtype=bool)
        for train, test in grouped_splits(y_idx, groups, self.n_folds, self.seed):
            temperature, knots, _ = fit_calibration(scores[train], y_idx[train])
            p = softmax(scores[test], temperature)
            confidence[test] = np.interp(p.max(axis=1), knots[0], knots[1])
            right[test] = np.argmax(p, axis=1) == y_idx[test]
        return calibration_scores(confidence[ok], right[ok])


LOST_REACH_TOL = 1e-5  # decimate: an output row is lost where lost input rows can move it by this share of their largest |value| or more


@functools.cache
def decimation_reach(step: int) -> int:
    """Input rows either side of a row that one stage of :func:`decimate` (scipy.signal.decimate by ``step``: an order-8
    Chebyshev I filter run forward and backward, sosfiltfilt) lets it move by :data:`LOST_REACH_TOL` or more of its
    |value|: the sum of |impulse response| beyond it is smaller. Plus sosfiltfilt's edge padding, whose odd
    extension carries the rows near an end (the first one into the whole pad) further in."""
    sos = signal.cheby1(8, 0.05, 0.8 / step, output="sos")  # what scipy.signal.decimate uses for ftype="iir"
    half = 400 * step  # the response falls below 1e-6 within ~80 steps
    impulse = np.zeros(2 * half + 1)
    impulse[half] = 1.0
    h = np.abs(signal.sosfiltfilt(sos, impulse))
    by_distance = h[half:].copy()
    by_distance[1:] += h[:half][::-1]
    tail = np.cumsum(by_distance[::-1])[::-1]  # tail[d]: the sum of |h| at distances d and more
    padlen = 3 * (2 * len(sos) + 1 - min(int((sos[:, 2] == 0).sum()), int((sos[:, 5] == 0).sum())))  # sosfiltfilt's default
    return int(np.count_nonzero(tail >= LOST_REACH_TOL)) + padlen


def _decimated_lost(lost: npt.NDArray[np.int64], n: int, stages: Sequence[int]) -> npt.NDArray[np.int64]:
    """``lost`` ranges of ``n`` input rows after :func:`decimate`'s ``stages``: every output row a lost input row reaches."""
    ranges = merge_ranges(lost)
    for step in stages:
        reach = decimation_reach(step)
        lo = np.clip(ranges[:, 0] - reach, 0, n)
        hi = np.clip(ranges[:, 0] + ranges[:, 1] + reach, 0, n)
        lo, hi = -(-lo // step), -(-hi // step)  # output row j is input row j * step
        keep = hi > lo
        ranges = merge_ranges(np.column_stack([lo[keep], hi[keep] - lo[keep]]))
        n = -(-n // step)
    return ranges.astype(np.int64).reshape(-1, 2)


def decimate(rec: Recording, rate: float) -> Recording:
    """``rec`` at ``rate`` Hz: anti-aliased decimation (scipy.signal.decimate, zero phase) of the volts. Every output row
    a lost input row reaches through the filter (:func:`decimation_reach`) is lost, so a window is refused for lost
    samples at every rate alike; ``disconnected`` positions move to the first output row after them."""
    factor = rec.fs / rate
    if abs(factor - round(factor)) > 1e-9:
        raise ValueError(f"{rate:g} Hz is not an integer division of {rec.fs:g} Hz")
    q = round(factor)
    volts = rec.volts()
    n = volts.shape[0]
    stages = []
    while q > 1:  # decimate in stages of at most 10, as scipy recommends
        step = next(s for s in (10, 5, 4, 2, q) if q % s == 0)
        stages.append(step)
        q //= step
    for step in stages:
        volts = signal.decimate(volts, step, axis=0, zero_phase=True)
    total = round(factor)
    start = stop = None
    if rec.slide_start is not None and rec.slide_stop is not None:
        start = rec.slide_start // total
        stop = np.maximum(rec.slide_stop // total, start + 1)
    lost = _decimated_lost(rec.lost, n, stages) if len(rec.lost) else np.zeros((0, 2), dtype=np.int64)
    disconnected = np.unique(-(-np.asarray(rec.disconnected, dtype=np.int64) // total))
    return Recording(samples=np.ascontiguousarray(volts), fs=rate, slide_start=start, slide_stop=stop, surface=rec.surface, label=rec.label,
                     meta=rec.meta, lost=lost, disconnected=disconnected)


QUICK_SFS_POOL = 16  # evaluate --quick: candidates per forward-selection step
RATE_FACTORS, RATE_FACTORS_QUICK = (1, 2, 4, 10, 20), (1, 4)  # (c): the recordings' rate divided by these (20 kHz: 20, 10, 5, 2, 1 kHz)


def run_evaluation(recs: Sequence[tuple[str, Recording]], config: Config, report: Path, *, experiments: str = "abcdefg", folds: int = 5,
                   quick: bool = False, seed: int = 0, progress: Progress | None = None) -> dict[str, Any]:
    """Run the experiments, write report.md, report.json and PNG figures into ``report``; return the results."""
    ev = Evaluator(recs, config, folds=folds, max_features=3 if quick else 6, seed=seed, progress=progress, sfs_pool=QUICK_SFS_POOL if quick else 0)
    starts, durations = ((0.1, 0.3), (0.25, 0.5)) if quick else ((0.0, 0.15, 0.3, 0.5), (0.1, 0.25, 0.5, 0.8))
    rates = [ev.fs / q for q in (RATE_FACTORS_QUICK if quick else RATE_FACTORS)]
    results: dict[str, Any] = {"files": len(recs), "folds": ev.folds_used, "folds_requested": folds, "fs": ev.fs, "channels": ev.channels,
                               "sfs_pool": ev.sfs_pool}
    t0 = time.perf_counter()
    if "a" in experiments:
        results["classifiers"] = ev.classifiers()
    if "b" in experiments or "f" in experiments:
        results["window_grid"] = ev.window_grid(starts, durations)
    if "c" in experiments:
        results["sampling_rate"] = ev.sampling_rates(rates)
    if "d" in experiments:
        results["feature_count"] = ev.feature_counts(3 if quick else 6)
    if "e" in experiments:
        results["unsupervised"] = ev.unsupervised(2 if quick else 5)
    if "g" in experiments:
        quick_set = [Candidate(("psd",), "linear", 0.5), Candidate(("dwt",), "linear", 0.5)]
        results["default_method"] = ev.default_method(quick_set if quick else None, (0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0))
    results["seconds"] = time.perf_counter() - t0
    report.mkdir(parents=True, exist_ok=True)
    (report / "report.json").write_text(json.dumps(results, indent=1))
    figures = write_figures(results, report)
    if figures is None and progress is not None:  # matplotlib missing: the command says so, as the report does
        progress(FIGURES_NOT_DRAWN)
    (report / "report.md").write_text(markdown(results, figures))
    return results


def _pm(r: dict[str, Any]) -> str:
    return f"{100 * r['mean']:.1f} ± {100 * r['sd']:.1f} %"


def markdown(res: dict[str, Any], figures: list[str] | None) -> str:
    """report.md: the results of :func:`run_evaluation` as Markdown sections and tables, then the ``figures`` (PNG names;
    None: they were not drawn, matplotlib missing, which the report says)."""
    channels = f"{res['channels']} channel{'s' if res['channels'] != 1 else ''}"
    out = [f"# Evaluation report\n\n{res['files']} recordings at {res['fs']:g} Hz, {channels}; grouped {res['folds']}-fold{_folds_note(res)} "
           f"cross-validation (mean ± sd over folds; slides from the daemon's detector paired with the ground truth, every true slide counted); "
           f"{res['seconds']:.0f} s."
           + (f" Quick run: forward selection among the {res['sfs_pool']} features of largest ANOVA F in each fold." if res.get("sfs_pool") else "")
           + "\n"]
    if "classifiers" in res:
        c = res["classifiers"]
        out.append(f"## (a) Classifiers\n\n{c['slides']} slides, {c['surfaces']} surfaces. Features selected per fold (ELM criterion): "
                   f"{'; '.join(', '.join(s) for s in c['selected'])}.\n\n| classifier | accuracy | inference per slide |\n|---|---|---|")
        out += [f"| {name} | {_pm(r)} | {r['infer_ms']:.3f} ms |" for name, r in c["results"].items()]
        out.append("")
    if "window_grid" in res:
        out.append("## (b) Start point × duration (error against run time in (f))\n\n"
                   "| start s | duration s | slides | ELM | kNN k=9 | SVM RBF |\n|---|---|---|---|---|---|")
        for r in res["window_grid"]:
            if "results" in r:
                out.append(f"| {r['start_s']} | {r['duration_s']} | {r['slides']} | {_pm(r['results']['ELM'])} | {_pm(r['results']['kNN k=9'])} | "
                           f"{_pm(r['results']['SVM RBF'])} |")
            else:
                out.append(f"| {r['start_s']} | {r['duration_s']} | — | skipped: {r['skipped']} | | |")
        out.append("")
    if "sampling_rate" in res:
        out.append("## (c) Sampling rate (anti-aliased decimation)\n\n| fs | DWT levels | slides | ELM |\n|---|---|---|---|")
        out += [f"| {r['fs']:g} Hz | {r['level']} | {r['slides']} | {_pm(r['ELM'])} |" if "ELM" in r else f"| {r['fs']:g} Hz | — | — | {r['skipped']} |"
                for r in res["sampling_rate"]]
        out.append("")
    if "feature_count" in res:
        out.append("## (d) Number of selected features\n\n| features | ELM | kNN k=9 |\n|---|---|---|")
        out += [f"| {r['n']} | {_pm(r['ELM'])} | {_pm(r['kNN k=9'])} |" for r in res["feature_count"]]
        out.append("")
    if "unsupervised" in res:
        out.append("## (e) Without labels (Hungarian matching of clusters to surfaces; mean ± sd over seeds)\n\n| method | accuracy |\n|---|---|")
        out += [f"| {name} | {_pm(r)} |" for name, r in res["unsupervised"]["results"].items()]
        out.append(f"\nSelected set: {res['unsupervised']['features']['selected (supervised SFS)']}.\n")
    if "window_grid" in res:
        out.append("## (f) Error against run time\n\nCompute per slide = features of the selected plan + inference; decision time = "
                   "start + duration (slide time that must pass before the label).\n\n| start s | duration s | classifier | error | compute ms | decision s |\n"
                   "|---|---|---|---|---|---|")
        for r in res["window_grid"]:
            if "results" in r:
                for name, v in r["results"].items():
                    out.append(f"| {r['start_s']} | {r['duration_s']} | {name} | {100 * (1 - v['mean']):.1f} % | {r['feature_ms'] + v['infer_ms']:.2f} | "
                               f"{r['decision_s']:.3f} |")
        out.append("")
    if "default_method" in res:
        g = res["default_method"]
        caveat = f", optimistic ({g['optimistic_reason']})" if g.get("optimistic_reason") else ""  # the words train prints
        out.append(f"## (g) The default method: `tactiled train`'s choice\n\nWinner: **{g['winner']}**; nested CV accuracy {_pm(g['nested'])}{caveat} "
                   f"(outer-fold picks: {', '.join(g['nested']['picks'])}). The choice is the simplest candidate within one standard error "
                   "of the best mean (marked *).\n\n| candidate | accuracy |\n|---|---|")
        out += [f"| {r['candidate']}{' *' if r.get('chosen') else ''} | {_pm(r)} |" for r in g["leaderboard"]]
        out.append(f"\nAccuracy against the slide time used before deciding (windows fused so far; a slide with no window yet counts as wrong); "
                   f"compute per decision = windows × ({g['feature_ms']:.2f} ms features + {g['infer_ms']:.3f} ms inference).\n\n"
                   "| slide time used | accuracy | decided | windows | compute ms |\n|---|---|---|---|---|")
        out += [f"| {'whole slide' if r['time_s'] is None else str(r['time_s']) + ' s'} | {100 * r['accuracy']:.1f} % | {100 * r['decided']:.0f} % | "
                f"{r['windows']:.1f} | {r['compute_ms']:.2f} |" for r in g["curve"]]
        cal = g.get("calibration", {})
        if cal.get("ece") is not None:
            out.append(f"\nConfidence (the probability that the label is right), cross-fitted on held-out recordings: expected calibration "
                       f"error {cal['ece']:.3f} (10 equal-width bins{_calibrated(cal)}), Brier score {cal['brier']:.3f}.\n\n"
                       "| confidence bin | slides | mean confidence | accuracy |\n|---|---|---|---|")
            out += [f"| {lo:.1f}–{lo + 0.1:.1f} | {n} | {c:.3f} | {a:.3f} |" for lo, n, c, a in cal["reliability"]]
        out.append("")
    if figures is None:
        out.append(f"F{FIGURES_NOT_DRAWN[1:]}.\n")
    out += [f"![{f}]({f})\n" for f in figures or []]
    return "\n".join(out) + "\n"


def _folds_note(res: dict[str, Any]) -> str:
    """Why fewer folds were used than ``--folds`` asked for, for the report; nothing when as many."""
    asked = res.get("folds_requested", res["folds"])
    return f" ({asked} asked for: the surface with fewest recordings has {res['folds']})" if asked != res["folds"] else ""


def _calibrated(cal: dict[str, Any]) -> str:
    """What a perfectly calibrated model's ECE would be on as many slides (tactiled.learn.score.calibrated_ece), for the report."""
    null = cal.get("ece_calibrated")
    return f"; a perfectly calibrated model would show {null[0]:.3f}, and up to {null[1]:.3f} in 95 % of draws, on these slides" if null else ""


FIGURES_NOT_DRAWN = "figures not drawn: matplotlib is not installed; to get them: pip install 'tactiled[report]'"


def write_figures(res: dict[str, Any], report: Path) -> list[str] | None:
    """error_vs_decision_time.png and reliability.png ((g)) and error_vs_runtime.png ((f)), their names; None when there
    are figures to draw and matplotlib is missing (:data:`FIGURES_NOT_DRAWN`)."""
    if "default_method" not in res and "window_grid" not in res:
        return []
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    names = []
    if "default_method" in res:
        g = res["default_method"]
        pts = [(r["time_s"], 100 * (1 - r["accuracy"]), r["compute_ms"]) for r in g["curve"] if r["time_s"] is not None]
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=g["winner"])
        whole = 100 * (1 - g["curve"][-1]["accuracy"])
        ax.axhline(whole, ls="--", color="grey", label=f"whole slide: {whole:.1f} %")
        for t, e, c in pts:
            ax.annotate(f"{c:.1f} ms", (t, e), textcoords="offset points", xytext=(4, 4), fontsize=7)
        names.append(_save_axes(plt, fig, ax, report / "error_vs_decision_time.png", "slide time used before deciding, s (labels: compute per "
                                "decision)", "error, %", "Default method: error against decision time"))
        table = g.get("calibration", {}).get("reliability", [])
        if table:
            fig, ax = plt.subplots(figsize=(4.5, 4.5))
            ax.plot([0, 1], [0, 1], ls="--", color="grey", label="calibrated")
            ax.plot([r[2] for r in table], [r[3] for r in table], "o-", label=f"default method (ECE {g['calibration']['ece']:.3f})")
            for _, n, c, a in table:
                ax.annotate(str(n), (c, a), textcoords="offset points", xytext=(4, -10), fontsize=7)
            ax.set_xlim(0, 1)
            ax.set_ylim(0, 1)
            names.append(_save_axes(plt, fig, ax, report / "reliability.png", "confidence (mean in bin)", "accuracy in bin",
                                    "Reliability diagram (labels: slides)"))
    if "window_grid" not in res:
        return names
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    markers = {"ELM": "o", "kNN k=9": "s", "SVM RBF": "^"}
    for name, marker in markers.items():
        pts = [(r["feature_ms"] + r["results"][name]["infer_ms"], r["decision_s"], 100 * (1 - r["results"][name]["mean"]))
               for r in res["window_grid"] if "results" in r]
        if pts:
            c, d, e = zip(*pts, strict=True)
            axes[0].scatter(c, e, marker=marker, label=name)
            axes[1].scatter(d, e, marker=marker, label=name)
    axes[0].set_xlabel("compute per slide (features + inference), ms")
    axes[1].set_xlabel("slide time before the decision, s")
    for ax in axes:
        ax.set_ylabel("error, %")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle("Error against run time (window start × duration grid)")
    fig.tight_layout()
    fig.savefig(report / "error_vs_runtime.png", dpi=110)
    plt.close(fig)
    return [*names, "error_vs_runtime.png"]


def _save_axes(plt: Any, fig: Any, ax: Any, path: Path, xlabel: str, ylabel: str, title: str) -> str:
    """Label, grid, legend and title ``ax``; write ``fig`` to ``path`` (PNG) and close it; returns the file's name."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path.name
