"""``tactiled evaluate``: the papers' experiments by grouped cross-validation (mean ± sd over folds).

(a) classifiers: ELM against kNN (k = 1, 5, 9) and SVM (linear, RBF), and the papers'
    plain ELM (Huang's U(−1, 1) weights, pseudo-inverse, no ridge);
(b) start point × duration of the analysis window;
(c) sampling rate: 20 kHz decimated with anti-aliasing (scipy.signal.decimate) to 10, 5, 2, 1 kHz;
(d) number of selected features;
(e) without labels: K-means (squared Euclidean, cityblock, cosine) and a SOM, Hungarian-scored;
(f) error against run time: accuracy beside the compute time per slide (features + inference)
    and the slide time that must pass before the decision.

Folds never split a recording; scaling and forward selection are fitted inside each
training fold only. One selection per (window, fold) is shared by the classifiers tested on it.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import signal

from tactiled.analysis import AnalysisSettings
from tactiled.cluster import hungarian_accuracy, kmeans, som_clusters
from tactiled.config import Config
from tactiled.features import FeaturePlan, feature_names
from tactiled.model import make_classifier
from tactiled.recording import Recording
from tactiled.train import SELECTION_HIDDEN, Folds, SlideSet, collect, forward_select, grouped_folds, measure_onset_lag, standardise

Progress = Callable[[str], None]
CLASSIFIERS: dict[str, tuple[str, dict[str, Any]]] = {
    "ELM": ("elm", {"n_hidden": 200, "alpha": 1e-6}),
    "ELM (plain: U(-1,1), pinv)": ("elm", {"n_hidden": 200, "alpha": 0.0, "init": "huang"}),
    "kNN k=1": ("knn", {"n_neighbors": 1}),
    "kNN k=5": ("knn", {"n_neighbors": 5}),
    "kNN k=9": ("knn", {"n_neighbors": 9}),
    "SVM linear": ("svm", {"kernel": "linear", "C": 1.0}),
    "SVM RBF": ("svm", {"kernel": "rbf", "C": 10.0, "gamma": "scale"}),
}


def _mk(kind: str, params: dict[str, Any], seed: int, calibrate: bool = False) -> Callable[[], Any]:
    def make() -> Any:
        est = make_classifier(kind, params, seed)
        if kind == "elm":
            est.set_params(calibrate=calibrate)
        return est

    return make


class Evaluator:
    """Holds the recordings, folds and caches of features and selections."""

    def __init__(self, recs: Sequence[tuple[str, Recording]], config: Config, *, folds: int = 5, max_features: int = 6,
                 seed: int = 0, progress: Progress | None = None) -> None:
        self.recs = list(recs)
        self.config = config
        self.n_folds = folds
        self.max_features = max_features
        self.seed = seed
        self.progress = progress or (lambda m: None)
        self.fs = self.recs[0][1].fs
        self.channels = self.recs[0][1].channels
        self.lag, _ = measure_onset_lag([r for _, r in self.recs], config)
        self._features: dict[tuple[Any, ...], SlideSet] = {}
        self._selection: dict[tuple[Any, ...], list[list[int]]] = {}

    def settings(self, start_s: float, duration_s: float, level: int = 4) -> AnalysisSettings:
        base = AnalysisSettings.from_config(self.config, self.channels)
        names = tuple(feature_names(self.channels, level, self.config.features.domains, self.config.features.stats))
        return replace(base, start_s=start_s, duration_s=duration_s, onset_lag_s=self.lag, level=level, names=names)

    def features(self, st: AnalysisSettings, recs: Sequence[tuple[str, Recording]] | None = None, key: Any = None) -> SlideSet:
        k = (st.start_s, st.duration_s, st.level, key)
        if k not in self._features:
            self._features[k] = collect(recs or self.recs, self.config, st)
        return self._features[k]

    def folds(self, ds: SlideSet) -> Folds:
        return grouped_folds(ds.y, ds.groups, self.n_folds, self.seed)

    def selections(self, ds: SlideSet, key: Any, folds: Folds, max_features: int | None = None) -> list[list[int]]:
        """Forward selection (ELM criterion, grouped inner CV) on each outer training fold."""
        m = max_features or self.max_features
        k = (key, m)
        if k not in self._selection:
            xin = ds.inputs
            make = _mk("elm", {**CLASSIFIERS["ELM"][1], "n_hidden": SELECTION_HIDDEN}, self.seed)
            self._selection[k] = [forward_select(make, xin[tr], ds.y[tr], ds.groups[tr], m, None if max_features else 0.005, seed=self.seed)[0]
                                  for tr, _ in folds]
        return self._selection[k]

    def cv(self, ds: SlideSet, folds: Folds, sel: list[list[int]], kind: str, params: dict[str, Any]) -> dict[str, Any]:
        """Accuracy per fold of a classifier on each fold's selected features, and its inference time."""
        xin = ds.inputs
        accs, infer = [], []
        for (tr, te), cols in zip(folds, sel, strict=True):
            mean, scale = standardise(xin[tr][:, cols])
            est = _mk(kind, params, self.seed)().fit((xin[tr][:, cols] - mean) / scale, ds.y[tr])
            t0 = time.perf_counter()
            pred = est.predict((xin[te][:, cols] - mean) / scale)
            infer.append((time.perf_counter() - t0) / len(te))
            accs.append(float(np.mean(pred == ds.y[te])))
        return {"mean": float(np.mean(accs)), "sd": float(np.std(accs)), "folds": accs, "infer_ms": float(np.mean(infer) * 1e3),
                "n_features": [len(c) for c in sel]}

    def feature_ms(self, ds: SlideSet, sel: list[list[int]], st: AnalysisSettings) -> float:
        """Median time to compute the largest fold's selected features on one window, ms."""
        names = [ds.names[j] for j in max(sel, key=len)]
        plan = FeaturePlan(names, st.wavelet, st.mode)
        n = max(round(st.duration_s * self.fs), plan.min_samples())
        x = np.random.default_rng(0).standard_normal((n, self.channels)) * 0.05
        times = []
        for _ in range(20):
            t0 = time.perf_counter()
            plan.compute(x)
            times.append(time.perf_counter() - t0)
        return float(np.median(times) * 1e3)

    # ---- experiments ---------------------------------------------------------------------

    def classifiers(self) -> dict[str, Any]:
        st = self.settings(self.config.window.start_s, self.config.window.duration_s)
        ds = self.features(st)
        folds = self.folds(ds)
        sel = self.selections(ds, "base", folds)
        self.progress(f"(a) classifiers on {len(ds.y)} slides, features per fold {[len(s) for s in sel]}")
        out = {name: self.cv(ds, folds, sel, kind, params) for name, (kind, params) in CLASSIFIERS.items()}
        every = [list(range(ds.x.shape[1]))] * len(folds)
        out["ELM, all features"] = self.cv(ds, folds, every, "elm", CLASSIFIERS["ELM"][1])
        out["SVM RBF, all features"] = self.cv(ds, folds, every, "svm", CLASSIFIERS["SVM RBF"][1])
        selected = [[ds.names[j] for j in s] for s in sel]
        return {"slides": len(ds.y), "surfaces": len(set(ds.y.tolist())), "files": len(self.recs), "onset_lag_ms": self.lag * 1e3,
                "selected": selected, "results": out}

    def window_grid(self, starts: Sequence[float], durations: Sequence[float]) -> list[dict[str, Any]]:
        rows = []
        for s in starts:
            for d in durations:
                st = self.settings(s, d)
                ds = self.features(st)
                if len(ds.y) < 10:
                    rows.append({"start_s": s, "duration_s": d, "skipped": ds.skipped})
                    continue
                folds = self.folds(ds)
                sel = self.selections(ds, ("grid", s, d), folds)
                res = {name: self.cv(ds, folds, sel, *CLASSIFIERS[name]) for name in ("ELM", "kNN k=9", "SVM RBF")}
                feat_ms = self.feature_ms(ds, sel, st)
                rows.append({"start_s": s, "duration_s": d, "slides": len(ds.y), "results": res, "feature_ms": feat_ms,
                             "decision_s": self.lag + s + d})
                self.progress(f"(b) window start {s} s, duration {d} s: ELM {res['ELM']['mean']:.3f}")
        return rows

    def sampling_rates(self, rates: Sequence[float]) -> list[dict[str, Any]]:
        rows = []
        st0 = self.settings(self.config.window.start_s, self.config.window.duration_s)
        for rate in rates:
            recs = [(n, decimate(r, rate)) for n, r in self.recs] if rate < self.fs else self.recs
            n_win = round(st0.duration_s * rate)
            level = 4
            while level > 1 and FeaturePlan(feature_names(self.channels, level)).min_samples() > n_win:
                level -= 1
            st = self.settings(st0.start_s, st0.duration_s, level)
            ds = self.features(st, recs, key=("rate", rate))
            folds = self.folds(ds)
            sel = self.selections(ds, ("rate", rate), folds)
            res = self.cv(ds, folds, sel, *CLASSIFIERS["ELM"])
            rows.append({"fs": rate, "level": level, "slides": len(ds.y), "ELM": res})
            self.progress(f"(c) {rate:g} Hz (level {level}): ELM {res['mean']:.3f}")
        return rows

    def feature_counts(self, up_to: int) -> list[dict[str, Any]]:
        st = self.settings(self.config.window.start_s, self.config.window.duration_s)
        ds = self.features(st)
        folds = self.folds(ds)
        full = self.selections(ds, "count", folds, max_features=up_to)
        rows: list[dict[str, Any]] = []
        for n in range(1, up_to + 1):
            sel = [s[:n] for s in full]
            rows.append({"n": n, "ELM": self.cv(ds, folds, sel, *CLASSIFIERS["ELM"]), "kNN k=9": self.cv(ds, folds, sel, *CLASSIFIERS["kNN k=9"])})
        self.progress(f"(d) features 1..{up_to}: ELM {[round(r['ELM']['mean'], 3) for r in rows]}")
        return rows

    def unsupervised(self, repeats: int = 5) -> dict[str, Any]:
        st = self.settings(self.config.window.start_s, self.config.window.duration_s)
        ds = self.features(st)
        xin = ds.inputs
        k = len(set(ds.y.tolist()))
        folds = self.folds(ds)
        sel = self.selections(ds, "base", folds)
        common = sorted(set(sel[0]).intersection(*map(set, sel[1:]))) or sel[0]
        sets = {"all features": list(range(xin.shape[1])), "selected (supervised SFS)": common}
        out: dict[str, Any] = {}
        for set_name, cols in sets.items():
            mean, scale = standardise(xin[:, cols])
            z = (xin[:, cols] - mean) / scale
            for method in ("K-means sqeuclidean", "K-means cityblock", "K-means cosine", "SOM"):
                accs = []
                for r in range(repeats):
                    labels = som_clusters(z, k, seed=self.seed + r) if method == "SOM" else kmeans(z, k, method.split()[1], seed=self.seed + r)
                    accs.append(hungarian_accuracy(labels, ds.y))
                out[f"{method}, {set_name}"] = {"mean": float(np.mean(accs)), "sd": float(np.std(accs)), "runs": accs}
        self.progress("(e) clustering done")
        return {"features": {k2: [ds.names[j] for j in v] if len(v) < 20 else f"{len(v)} features" for k2, v in sets.items()}, "results": out}


def decimate(rec: Recording, rate: float) -> Recording:
    """``rec`` at ``rate`` Hz: anti-aliased decimation (scipy.signal.decimate, zero phase) of the volts."""
    factor = rec.fs / rate
    if abs(factor - round(factor)) > 1e-9:
        raise ValueError(f"{rate:g} Hz is not an integer division of {rec.fs:g} Hz")
    q = round(factor)
    volts = rec.volts()
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
    return Recording(samples=np.ascontiguousarray(volts), fs=rate, slide_start=start, slide_stop=stop, surface=rec.surface, label=rec.label,
                     meta=rec.meta)


def run_evaluation(recs: Sequence[tuple[str, Recording]], config: Config, report: Path, *, experiments: str = "abcdef", folds: int = 5,
                   quick: bool = False, seed: int = 0, progress: Progress | None = None) -> dict[str, Any]:
    """Run the experiments, write report.md, report.json and PNG figures into ``report``; return the results."""
    ev = Evaluator(recs, config, folds=folds, max_features=3 if quick else 6, seed=seed, progress=progress)
    starts, durations = ((0.1, 0.3), (0.25, 0.5)) if quick else ((0.0, 0.15, 0.3, 0.5), (0.1, 0.25, 0.5, 0.8))
    rates = (20000.0, 5000.0) if quick else (20000.0, 10000.0, 5000.0, 2000.0, 1000.0)
    results: dict[str, Any] = {"files": len(recs), "folds": folds, "fs": ev.fs, "channels": ev.channels, "onset_lag_ms": ev.lag * 1e3}
    t0 = time.perf_counter()
    if "a" in experiments:
        results["classifiers"] = ev.classifiers()
    if "b" in experiments or "f" in experiments:
        results["window_grid"] = ev.window_grid(starts, durations)
    if "c" in experiments and ev.fs >= max(rates):
        results["sampling_rate"] = ev.sampling_rates([r for r in rates if r <= ev.fs and ev.fs % r == 0])
    if "d" in experiments:
        results["feature_count"] = ev.feature_counts(4 if quick else 10)
    if "e" in experiments:
        results["unsupervised"] = ev.unsupervised(2 if quick else 5)
    results["seconds"] = time.perf_counter() - t0
    report.mkdir(parents=True, exist_ok=True)
    (report / "report.json").write_text(json.dumps(results, indent=1))
    figures = write_figures(results, report)
    (report / "report.md").write_text(markdown(results, figures))
    return results


def _pm(r: dict[str, Any]) -> str:
    return f"{100 * r['mean']:.1f} ± {100 * r['sd']:.1f} %"


def markdown(res: dict[str, Any], figures: list[str]) -> str:
    out = [f"# Evaluation report\n\n{res['files']} recordings at {res['fs']:g} Hz, {res['channels']} channels; grouped {res['folds']}-fold "
           f"cross-validation (mean ± sd over folds); detector onset lag {res['onset_lag_ms']:.1f} ms; {res['seconds']:.0f} s.\n"]
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
        out += [f"| {r['fs']:g} Hz | {r['level']} | {r['slides']} | {_pm(r['ELM'])} |" for r in res["sampling_rate"]]
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
        out.append("## (f) Error against run time\n\nCompute per slide = features of the selected plan + inference; decision time = onset lag + "
                   "start + duration (slide time that must pass before the label).\n\n| start s | duration s | classifier | error | compute ms | decision s |\n"
                   "|---|---|---|---|---|---|")
        for r in res["window_grid"]:
            if "results" in r:
                for name, v in r["results"].items():
                    out.append(f"| {r['start_s']} | {r['duration_s']} | {name} | {100 * (1 - v['mean']):.1f} % | {r['feature_ms'] + v['infer_ms']:.2f} | "
                               f"{r['decision_s']:.3f} |")
        out.append("")
    out += [f"![{f}]({f})\n" for f in figures]
    return "\n".join(out) + "\n"


def write_figures(res: dict[str, Any], report: Path) -> list[str]:
    """error_vs_runtime.png (and nothing else needs a figure); [] when matplotlib is missing."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    if "window_grid" not in res:
        return []
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
    return ["error_vs_runtime.png"]
