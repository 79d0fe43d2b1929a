"""Training: recordings → slides → windows → features → forward selection → model file.

Slides come from ground truth (``slide_start``/``slide_stop``/``surface``) or, for files
with only a file-level ``label``, from the daemon's own detector. Windows are placed where
live use places them: the detector's onset lags the true start of motion, so the lag is
measured on the training files (median over matched slides), stored in the model, and
added to ground-truth onsets.
"""

from __future__ import annotations

import functools
import logging
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from tactiled.analysis import Analyser, AnalysisSettings
from tactiled.config import Config
from tactiled.detect import SlideDetector, SlideEnd
from tactiled.errors import RecordingError, TactiledError
from tactiled.features import classifier_inputs
from tactiled.model import Model, make_classifier
from tactiled.recording import Recording, load_recording

log = logging.getLogger(__name__)
Progress = Callable[[str], None]


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def load_recordings(paths: Sequence[str | Path], progress: Progress | None = None) -> list[tuple[str, Recording]]:
    """Load every file; a malformed one is reported (one line) and skipped."""
    out = []
    for p in paths:
        try:
            out.append((str(p), load_recording(p)))
        except RecordingError as exc:
            (progress or _stderr)(f"tactiled: skipped: {exc}")
    return out


def detect_slides(rec: Recording, config: Config) -> list[tuple[int, int]]:
    """(start, stop) positions of the slides the daemon's detector finds in ``rec``."""
    det = SlideDetector(config.detector, rec.fs, rec.channels)
    volts = rec.volts()
    valid = rec.valid_mask()
    volts[~valid] = 0.0
    return [(e.start, e.stop) for e in det.feed(0, volts, valid) if isinstance(e, SlideEnd) and e.reason != "too_short"]


def measure_onset_lag(recs: Sequence[Recording], config: Config) -> tuple[float, npt.NDArray[np.float64]]:
    """Median lag (s) of detected onsets behind true starts, and every matched lag."""
    lags = []
    for rec in recs:
        truth = rec.slides()
        if not truth:
            continue
        for start, stop in detect_slides(rec, config):
            for t_start, t_stop, _ in truth:
                if start < t_stop and stop > t_start:
                    lags.append((start - t_start) / rec.fs)
                    break
    arr = np.asarray(lags, dtype=np.float64)
    return (float(np.median(arr)) if arr.size else 0.0), arr


@dataclass
class SlideSet:
    """Features of every slide: X (k, F) in ``names`` order, labels, groups (file number), provenance."""

    x: npt.NDArray[np.float64]
    y: npt.NDArray[np.str_]
    groups: npt.NDArray[np.int64]
    names: list[str]
    files: list[str]
    starts: npt.NDArray[np.int64]
    stops: npt.NDArray[np.int64]
    skipped: dict[str, int]

    @functools.cached_property
    def inputs(self) -> npt.NDArray[np.float64]:
        """``x`` as the classifiers see it (:func:`tactiled.features.classifier_inputs`), computed once."""
        return classifier_inputs(self.x, self.names)


def slide_windows(rec: Recording, config: Config) -> tuple[list[tuple[int, int, str | None]], bool]:
    """The slides of ``rec`` (ground truth if present, else detected with the file label); and whether from truth."""
    truth = rec.slides()
    if truth:
        return truth, True
    return [(a, b, rec.label) for a, b in detect_slides(rec, config)], False


def collect(recs: Sequence[tuple[str, Recording]], config: Config, settings: AnalysisSettings,
            progress: Progress | None = None, require_labels: bool = True) -> SlideSet:
    """Analyse every slide's window with ``settings`` (all of ``settings.names``)."""
    rows, labels, groups, files, starts, stops = [], [], [], [], [], []
    skipped: dict[str, int] = {}
    for g, (name, rec) in enumerate(recs):
        analyser = Analyser(settings, rec.volts_per_count, rec.is_integer, config.classifier.max_saturated, config.classifier.max_lost)
        valid = rec.valid_mask()
        slides, from_truth = slide_windows(rec, config)
        for start, stop, label in slides:
            if require_labels and label is None:
                skipped["unlabelled"] = skipped.get("unlabelled", 0) + 1
                continue
            lo, hi = settings.window(start, stop, rec.fs, from_truth=from_truth)
            hi = min(hi, rec.samples.shape[0])
            res = analyser.analyse(rec.samples[lo:hi], valid[lo:hi])
            if res.features is None:
                skipped[res.reason or "?"] = skipped.get(res.reason or "?", 0) + 1
                continue
            rows.append(res.features)
            labels.append(label or "")
            groups.append(g)
            files.append(name)
            starts.append(start)
            stops.append(stop)
        if progress and (g + 1) % 10 == 0:
            progress(f"features: {g + 1}/{len(recs)} files, {len(rows)} slides")
    f = len(settings.names)
    return SlideSet(np.asarray(rows, dtype=np.float64).reshape(-1, f), np.asarray(labels, dtype=np.str_), np.asarray(groups, dtype=np.int64),
                    list(settings.names), files, np.asarray(starts, dtype=np.int64), np.asarray(stops, dtype=np.int64), skipped)


Folds = list[tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]]


def grouped_folds(y: npt.NDArray[Any], groups: npt.NDArray[np.int64], n_splits: int, seed: int = 0) -> Folds:
    """Folds that never split a recording; stratified by label where possible."""
    from sklearn.model_selection import StratifiedGroupKFold

    n_groups = len(np.unique(groups))
    n = max(2, min(n_splits, n_groups))
    if n_groups < 2:
        raise TactiledError("cross-validation needs at least two recordings")
    return list(StratifiedGroupKFold(n_splits=n, shuffle=True, random_state=seed).split(np.zeros(len(y)), y, groups))


def standardise(train: npt.NDArray[np.float64]) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Mean and scale of the training rows; a constant column gets scale 1 (it becomes zeros)."""
    mean = train.mean(axis=0)
    scale = train.std(axis=0)
    scale[scale < 1e-12 * (1.0 + np.abs(mean))] = 1.0
    return mean, scale


def cv_accuracy(make: Callable[[], Any], x: npt.NDArray[np.float64], y: npt.NDArray[Any],
                folds: Sequence[tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]]) -> npt.NDArray[np.float64]:
    """Accuracy per fold of ``make()`` with standardisation fitted on each training fold."""
    scores = []
    for tr, te in folds:
        mean, scale = standardise(x[tr])
        est = make().fit((x[tr] - mean) / scale, y[tr])
        scores.append(float(np.mean(est.predict((x[te] - mean) / scale) == y[te])))
    return np.asarray(scores)


def forward_select(make: Callable[[], Any], x: npt.NDArray[np.float64], y: npt.NDArray[Any], groups: npt.NDArray[np.int64],
                   max_features: int, tol: float | None, n_splits: int = 3, seed: int = 0,
                   progress: Progress | None = None) -> tuple[list[int], list[float]]:
    """Sequential forward selection by grouped cross-validated accuracy.

    Starts empty, adds the feature that maximises the mean CV accuracy, and stops at
    ``max_features`` or, with ``tol``, when the best gain is below ``tol``. Constant
    columns are never candidates. Returns (column indices, score after each addition).
    """
    folds = grouped_folds(y, groups, n_splits, seed)
    candidates = [j for j in range(x.shape[1]) if np.ptp(x[:, j]) > 1e-12 * (1 + np.abs(x[:, j]).max())]
    selected: list[int] = []
    history: list[float] = []
    best = -np.inf
    while len(selected) < max_features and candidates:
        scores = [cv_accuracy(make, x[:, [*selected, j]], y, folds).mean() for j in candidates]
        k = int(np.argmax(scores))
        if tol is not None and selected and scores[k] - best < tol:
            break
        best = scores[k]
        selected.append(candidates.pop(k))
        history.append(float(best))
        if progress:
            progress(f"select: {len(selected)} features, CV accuracy {best:.3f}")
    return selected, history


SELECTION_HIDDEN = 50  # the ELM that ranks candidate features: 3x faster than 200 units, same ranking measured

DEFAULT_PARAMS: dict[str, dict[str, Any]] = {
    "elm": {"n_hidden": 200, "alpha": 1e-6},
    "knn": {"n_neighbors": 9},
    "svm": {"kernel": "rbf", "C": 10.0, "gamma": "scale"},
}


def fit_model(ds: SlideSet, settings: AnalysisSettings, kind: str, params: dict[str, Any], features: int | str, seed: int,
              fs: float, channels: int, progress: Progress | None = None) -> Model:
    """Select features on ``ds`` (grouped CV inside it only), fit, and return the model."""
    if len(np.unique(ds.y)) < 2:
        raise TactiledError(f"training needs at least two surfaces, got {sorted(set(ds.y.tolist()))}")
    sel_params = {**params, "n_hidden": SELECTION_HIDDEN} if kind == "elm" else params

    def make() -> Any:
        est = make_classifier(kind, sel_params, seed)
        if kind == "elm":
            est.set_params(calibrate=False)
        return est

    xin = ds.inputs
    if str(features) == "all":
        cols = list(range(ds.x.shape[1]))
        history: list[float] = []
    else:
        max_f, tol = (12, 0.005) if features == "auto" else (int(features), None)
        cols, history = forward_select(make, xin, ds.y, ds.groups, max_f, tol, seed=seed, progress=progress)
    x = xin[:, cols]
    mean, scale = standardise(x)
    est = make_classifier(kind, params, seed).fit((x - mean) / scale, ds.y)
    used = replace(settings, names=tuple(ds.names[j] for j in cols))
    summary = {"slides": len(ds.y), "files": len(set(ds.files)), "classes": sorted(set(ds.y.tolist())),
               "selection_cv_accuracy": history, "skipped": ds.skipped}
    classes = [str(c) for c in est.classes_]
    train_x = (x - mean) / scale if kind != "elm" else None
    train_y = ds.y if kind != "elm" else None
    return Model(kind, params, classes, used, fs, channels, mean, scale, est, seed, summary, "", train_x, train_y)
