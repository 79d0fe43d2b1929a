"""Honest scores: a model run end to end (replay's pipeline) over recordings, against every true slide.

With per-slide ground truth, each true slide is paired with the pipeline's slide that
overlaps it most (:func:`tactiled.core.matching.match_slides`); a true slide without a label
(missed by the detector, or abstained) counts as wrong. With a file-level ``label`` only,
the slides are the detector's and each should carry that label. Accuracy is over every
true slide; coverage is the fraction that got a label; abstentions are listed by reason. Slides of a surface the model
was not taught count as wrong in ``accuracy`` (no label can be right) and are listed apart (``untaught``: how many of them
came out unknown, the right answer there; ``untaught_labelled``: how many were labelled).

Three figures keep them apart: ``taught_accuracy`` (the headline) is over the slides of taught surfaces only (an unknown
or no label wrong there, as everywhere); ``untaught_unknown_share`` is the share of the slides of untaught surfaces called
unknown (their right answer); ``open_set_accuracy`` counts every slide, one of an untaught surface right iff called
unknown. ``accuracy`` keeps its meaning (right labels over every slide) for the benches that read it. The calibration scores (expected
calibration error, Brier score, reliability) are over the slides of taught surfaces only (``calibration_slides``): a
label's confidence is the probability that it is right for a surface the model was trained on, and says nothing of others.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from tactiled.config import Config
from tactiled.core.events import SlideResult
from tactiled.files.recording import Recording
from tactiled.run.replay import pair_results, replay_all

NO_LABEL = ""  # the confusion matrix's last column, a slide given no label: a name no surface has (surface_name_problem refuses it)


def confusion(y_true: Sequence[str], y_pred: Sequence[str | None], classes: Sequence[str]) -> dict[str, Any]:
    """Per-class recall and the confusion matrix: rows the surfaces (``classes`` of the result without its last entry), columns
    the same surfaces then :data:`NO_LABEL` (a slide given no label), so that no surface's column is the no-label one."""
    labels = sorted(set(classes) | set(y_true) | {p for p in y_pred if p is not None})
    row = {c: i for i, c in enumerate(labels)}
    cm = np.zeros((len(labels), len(labels) + 1), dtype=int)
    for t, p in zip(y_true, y_pred, strict=True):
        cm[row[t], len(labels) if p is None else row[p]] += 1
    recall = {c: float(cm[i, i] / cm[i].sum()) for i, c in enumerate(labels) if cm[i].sum()}
    return {"classes": [*labels, NO_LABEL], "confusion": cm.tolist(), "recall": recall}


def score(recs: Sequence[tuple[str, Recording]], results: Sequence[Sequence[SlideResult]], classes: Sequence[str]) -> dict[str, Any]:
    """Scores over every true slide of ``recs`` given the pipeline's ``results`` per recording."""
    y_true: list[str] = []
    y_pred: list[str | None] = []
    reasons: Counter[str] = Counter()
    extra = 0
    per_file: list[dict[str, Any]] = []
    conf: list[float] = []
    hit: list[bool] = []
    top_right = 0  # the top class right, labelled or not (what the accuracy would be without abstaining)
    untaught: dict[str, list[int]] = {}  # surfaces the model was not taught: [slides, called unknown] (the right answer there)
    taught = set(classes)
    for (name, rec), res in zip(recs, results, strict=True):
        truth, paired, unpaired = pair_results(rec, res)
        extra += unpaired
        right = 0
        for t, r in zip(truth, paired, strict=True):
            y_true.append(t)
            y_pred.append(None if r is None else r.label)
            if r is None:
                reasons["missed_by_detector"] += 1
            elif r.label is None:
                reasons[r.reason or "?"] += 1
            right += r is not None and r.label == t
            if t in taught and r is not None and r.confidence is not None and r.top:  # confidence is defined for a taught surface only
                conf.append(r.confidence)
                hit.append(r.top[0][0] == t)  # the top class, labelled or not (an unknown surface still has one)
            top_right += r is not None and bool(r.top) and r.top[0][0] == t
            if t not in taught:
                row = untaught.setdefault(t, [0, 0, 0])
                row[0] += 1
                row[1] += int(r is not None and r.reason == "unknown_surface")
                row[2] += int(r is not None and r.label is not None)
        per_file.append({"file": name, "slides": len(truth), "correct": right, "unpaired_detections": unpaired})
    n = len(y_true)
    hits = np.array([p == t for p, t in zip(y_pred, y_true, strict=True)], dtype=bool)
    correct = int(hits.sum())
    files = np.repeat([f["file"] for f in per_file], [f["slides"] for f in per_file])
    labelled = sum(p is not None for p in y_pred)
    out: dict[str, Any] = {"n": n, "correct": correct, "accuracy": correct / n if n else 0.0, "labelled": labelled, "coverage": labelled / n if n else 0.0,
           "accuracy_of_labelled": correct / labelled if labelled else None, "abstained": dict(reasons), "unpaired_detections": extra,
           "files": per_file, "unknown": reasons.get("unknown_surface", 0), "top_accuracy": top_right / n if n else 0.0,
           "interval95": recording_interval(hits, files)}
    out.update(calibration_scores(np.array(conf), np.array(hit, dtype=bool)))
    out.update(confusion(y_true, y_pred, classes))
    out["calibration_slides"] = len(conf)
    out["untaught"] = {k: v[:2] for k, v in sorted(untaught.items())}
    out["untaught_labelled"] = {k: v[2] for k, v in sorted(untaught.items())}
    out.update(open_set_scores(hits, files, np.array([t in taught for t in y_true], dtype=bool), sum(v[1] for v in untaught.values())))
    return out


def open_set_scores(hits: npt.NDArray[np.bool_], files: npt.NDArray[Any], taught: npt.NDArray[np.bool_], untaught_unknown: int) -> dict[str, Any]:
    """The slides of taught surfaces and of untaught ones scored apart, then together.

    ``hits`` (n,): each true slide's label right; ``files`` (n,): its recording; ``taught`` (n,): its surface one the model
    was taught; ``untaught_unknown``: how many slides of untaught surfaces came out unknown. ``taught_accuracy`` (None
    without such a slide) and its ``taught_interval95`` (:func:`recording_interval`) are over the taught slides;
    ``untaught_unknown_share`` (None without an untaught slide) over the others; ``open_set_accuracy`` over all n (0.0
    when n is 0), an untaught slide right iff called unknown.
    """
    n, n_taught = len(hits), int(taught.sum())
    right = int(hits[taught].sum())
    return {"taught_n": n_taught, "taught_correct": right, "taught_accuracy": right / n_taught if n_taught else None,
            "taught_interval95": recording_interval(hits[taught], files[taught]),
            "untaught_n": n - n_taught, "untaught_unknown": untaught_unknown,
            "untaught_unknown_share": untaught_unknown / (n - n_taught) if n > n_taught else None,
            "open_set_correct": right + untaught_unknown, "open_set_accuracy": (right + untaught_unknown) / n if n else 0.0}


def recording_interval(hits: npt.NDArray[np.bool_], groups: npt.NDArray[Any], level: float = 0.95,
                       resamples: int = 2000, seed: int = 0, weights: npt.NDArray[np.float64] | None = None) -> list[float] | None:
    """[low, high] of the slide accuracy ``hits`` (n,) at ``level``, resampling whole recordings (``groups`` (n,)); each
    slide weighing ``weights`` (n,) if given (``train``'s choice on surfaces recorded unevenly).

    A percentile bootstrap over recordings, not slides: slides of one recording share its day, specimen and fingertip, so
    they say less than as many independent slides, and a new recording can miss by as much as the recordings differ.
    Where every slide is right (or every one wrong) the resamples cannot vary: the rule of three over the m recordings
    gives [1 - 3/m, 1] (or [0, 3/m]). Otherwise the recordings are resampled with one more of each outcome, of the average
    size, all right and all wrong (as Agresti and Coull add two successes and two failures to a proportion): where one
    recording of eleven held the only error, the plain bootstrap gave [0.95, 1], narrower than the [0.70, 1] of ten
    recordings without one (an outside audit); so smoothed, [0.74, 1]. None with fewer than 3 recordings.
    """
    from scipy import stats

    names, idx = np.unique(np.asarray(groups).astype(str), return_inverse=True)
    if len(names) < 3:
        return None
    if hits.all() or not hits.any():
        m = len(names)
        return [1.0 - min(1.0, 3.0 / m), 1.0] if hits.all() else [0.0, min(1.0, 3.0 / m)]
    w = np.ones(len(hits)) if weights is None else np.asarray(weights, dtype=np.float64)
    right = np.bincount(idx, weights=hits * w, minlength=len(names))
    count = np.bincount(idx, weights=w, minlength=len(names))
    size = float(count.mean())
    right, count = np.r_[right, size, 0.0], np.r_[count, size, size]  # a recording all right and one all wrong, of the average size
    res = stats.bootstrap((right, count), lambda r, c, axis: r.sum(axis=axis) / c.sum(axis=axis), paired=True, vectorized=True,
                          confidence_level=level, n_resamples=resamples, method="percentile", random_state=seed)
    return [float(res.confidence_interval.low), float(res.confidence_interval.high)]


def calibration_scores(confidence: npt.NDArray[np.float64], right: npt.NDArray[np.bool_], bins: int = 10) -> dict[str, Any]:
    """How well ``confidence`` (n,) predicts ``right`` (n,): expected calibration error, Brier score and the reliability diagram.

    ECE: over ``bins`` equal-width bins of confidence in [0, 1], the slide-weighted mean of |accuracy - mean confidence|.
    Brier: the mean of (confidence - right)². ``reliability``: per non-empty bin, [low edge, slides, mean confidence, accuracy].
    None for both when there is no slide.
    """
    n = len(confidence)
    if not n:
        return {"ece": None, "brier": None, "reliability": [], "ece_calibrated": None}
    which = np.minimum((np.clip(confidence, 0.0, 1.0) * bins).astype(int), bins - 1)
    ece, table = 0.0, []
    for b in range(bins):
        m = which == b
        if m.any():
            c, a = float(confidence[m].mean()), float(right[m].mean())
            ece += m.sum() / n * abs(a - c)
            table.append([b / bins, int(m.sum()), round(c, 4), round(a, 4)])
    return {"ece": ece, "brier": float(np.mean((confidence - right) ** 2)), "reliability": table,
            "ece_calibrated": calibrated_ece(confidence, bins)}


def calibrated_ece(confidence: npt.NDArray[np.float64], bins: int = 10, draws: int = 2000, seed: int = 0) -> list[float]:
    """[median, 95th percentile] of the ECE that a perfectly calibrated model with these ``confidence`` s (n,) would show on
    n slides: each slide right with probability its confidence, ``draws`` times (fewer when n is large: at most 2e6 slide
    draws in all, at least 100; seeded: the same answer every time).

    ECE is biased upwards on few slides: with confidences near 0.5 and 90 slides a calibrated model's median ECE is about
    0.1, so a measured ECE is only evidence of miscalibration where it lies beyond these numbers.
    """
    c = np.clip(np.asarray(confidence, dtype=np.float64), 0.0, 1.0)
    draws = int(max(100, min(draws, 2_000_000 // max(c.size, 1))))
    onehot = np.eye(bins)[np.minimum((c * bins).astype(int), bins - 1)]  # (n, bins)
    right = np.random.default_rng(seed).random((draws, c.size)) < c  # (draws, n)
    ece = np.abs(right @ onehot - c @ onehot).sum(axis=1) / c.size  # (draws,)
    return [round(float(np.median(ece)), 4), round(float(np.quantile(ece, 0.95)), 4)]


def score_recordings(recs: Sequence[tuple[str, Recording]], config: Config, model: Any, jobs: int | None = None,
                     done: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Replay every recording through the pipeline with ``model`` (on ``jobs`` processes, None: every core) and score it (:func:`score`)."""
    results = list(replay_all([rec for _, rec in recs], config, model, jobs, done))
    return score(recs, results, model.classes)
