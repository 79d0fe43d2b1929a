"""Model selection: which features, classifier and windows work on the user's recordings.

A candidate combines a feature family set (:data:`tactiled.core.features.FAMILIES`: the papers'
DWT statistics, log band energies of the Welch PSD, texture descriptors), a classifier
(ELM, kNN, SVM, regularised linear), a window placement (length, first window's offset
from the slide's start, how many windows), and optionally forward feature selection. The
default space (:func:`default_candidates`) leads with :data:`SPECTRUM`, the plain whole-slide
spectral classifier (log band energies of the slide's Welch spectrum, log centroid, kurtosis;
RBF SVM): by cross-validation the choice is never below it by more than one standard error. The
papers' method (:data:`PAPER`: DWT statistics of one 0.5 s window 0.3 s after the start,
sequential forward selection, ELM) is ``--method paper``: its forward selection alone takes minutes.

Every candidate is scored by grouped cross-validation (folds never split a recording, and spread each surface's
recordings over the folds: :func:`grouped_splits`) at
the level that matters: the label of each whole slide, from its windows' fused scores,
over every slide (a slide with no usable window counts as wrong); selection and scaling
are fitted inside each training fold only. The leaderboard lists mean ± sd over outer
folds. The winner is the simplest candidate whose mean is within one standard error of
the best mean (:func:`choose`; the standard error at least a proportion's over the slides, :func:`within_one_se`), and
with ``gain`` within one of the best of those under another unit's film gains (:func:`gain_scales`): with few
recordings the top of the leaderboard is within noise, and the simpler candidate is the safer bet on new data. Its accuracy is estimated
honestly by nested cross-validation: in each outer fold, the same rule on an inner grouped
CV of the training files alone picks a candidate, which is then scored on the held-out
files (where a surface has a single file in an outer fold's training part, as with two recordings per surface, the
inner folds there split by slide: grouped by file they could test nothing; where it has a single slide, that fold
scores the winner itself; the outer folds stay grouped). The winner is refitted on every recording; its temperature and its confidence
calibration (:func:`fit_calibration`) are fitted on its out-of-fold slide scores, and its
unknown-surface thresholds (:func:`fit_novelty`): by default (``spectrum``) a distance threshold on the shape of the
slide's spectrum (per channel, log band powers less their mean, whatever features the classifier reads), which 95 % of
the slides of *other recordings* of their own surface stay within; ``far``, on the classifier's standardised features,
beyond the step between taught surfaces; ``combined`` also one on the distance ratios of slides to other recordings'
slides, weighing a caught untaught slide by the share of them expected (``untaught``, :data:`UNTAUGHT_SHARE`) against a
rejected known one.

``speed`` (``train --speed-copies``, off by default): every candidate also learns from two speed-perturbed copies of each
training slide, resampled as if slid that much slower and faster (:func:`~tactiled.learn.dataset.speed_copies`); the copies
follow their slide into its training folds and are never scored, and the novelty and calibration are fitted on the slides
as recorded (docs/evaluation.md measured it on the same unit and on other units of the sensor).

``ensemble`` (``train --ensemble``, off by default: docs/evaluation.md measured it on every scene and it cost some
scenes 6 of 90 slides): when the winner shares :data:`SPECTRUM`'s windows, the model multiplies the winner's
probabilities by SPECTRUM's (:func:`ensemble_of`; its temperature and calibration fitted on the two candidates'
out-of-fold scores combined, its provisional-label calibration on their combined prefixes, its novelty the winner's),
always or only when that combination's out-of-fold accuracy is within one standard error of the winner's. The model
file then states the ensemble's nested estimate (each outer fold's pick with SPECTRUM), the winner alone's kept beside it;
where no ensemble can be made (the winner is SPECTRUM, or does not share its windows), train says so.

Work is spread over every core with joblib; ``scheduler`` (a dask.distributed address)
sends it to a cluster through joblib's Dask backend instead.
"""

from __future__ import annotations

import contextlib
import functools
import math
import socket
import time
import warnings
from collections import Counter
from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from tactiled.config import Config
from tactiled.core.analysis import AnalysisSettings, window_settings
from tactiled.core.features import channel_columns, feature_degree, name_family
from tactiled.errors import TactiledError
from tactiled.files.recording import Recording
from tactiled.learn.dataset import (
    PIECE,
    PIECE_WINDOWS,
    LabelledSlide,
    Progress,
    SlideCounts,
    WindowSet,
    collect_windows,
    find_slides,
    speed_ratios,
)
from tactiled.learn.model import (
    NOVELTY_SCORES,
    SHAPE_SCALE_FLOOR,
    Model,
    decision_scores,
    ensemble_scores,
    fit_pipeline,
    fit_temperature,
    nearest_surface_distances,
    novelty_parts,
    over_thresholds,
    pairwise_distances,
    prefix_fused,
    softmax,
    surface_distances,
    surface_scale_for,
    take_columns,
)
from tactiled.learn.score import recording_interval

FloatArray = npt.NDArray[np.float64]

PARAMS: dict[str, dict[str, Any]] = {
    "elm": {"n_hidden": 200, "alpha": 1e-3},
    "knn": {"n_neighbors": 5},
    "svm": {"kernel": "rbf", "C": 10.0, "gamma": "scale"},
    "linear": {"C": 10.0, "max_iter": 2000},
}
WEIGHTED_KINDS = ("svm", "linear")  # the classifiers that weigh each surface alike (class_weight) on surfaces recorded unevenly
KIND_RANK: dict[str, int] = {"linear": 0, "svm": 1, "knn": 2, "elm": 3}
PAPER_PARAMS: dict[str, Any] = {"n_hidden": 200, "alpha": 1e-6}
# train --ensemble: off, always (when the winner may have SPECTRUM as a partner: can_partner), guarded (then only within one
# standard error of the winner's out-of-fold accuracy)
ENSEMBLE_MODES = ("off", "always", "guarded")
ENSEMBLE_DEFAULT = "off"
# train --untaught-share: the share of slides expected on surfaces a model was never taught; a novelty threshold is worth
# what it catches of them, weighed by this, less the known slides it rejects, weighed by the rest (novelty_threshold)
UNTAUGHT_SHARE = 0.1
# train --novelty: the unknown-surface tests a model gets. "spectrum" (the default): the distance from the slide's
# spectral shape (tactiled.core.features.spectral_shape of the psd bands, which the model computes whatever its classifier
# reads; model format 8) to the nearest taught surface, over the distance that 95 % of other recordings' slides of known
# surfaces stay within. The classifier's features are picked to tell the taught surfaces apart, and what a new surface
# differs in may not be among them. "far": on the classifier's standardised features, only the distance test of
# "combined" (a slide farther from every taught surface than they are from one another), never the distance ratio (a
# slide between two taught surfaces), whose cost on another unit of the sensor cross-validation on one unit cannot see
# (docs/evaluation.md). Both are stored as "combined" with no ratio threshold. The others: tactiled.learn.model.NOVELTY_SCORES.
NOVELTY_TESTS = ("spectrum", "far", *NOVELTY_SCORES)
NOVELTY_DEFAULT = "spectrum"
# train --speed-copies: per cent slower and faster of the two resampled copies of each training slide (0, the default: none;
# docs/evaluation.md measured 5 %: the plain spectral candidates gain on new recordings of the same unit, train's choice
# does not, on the same unit or another)
SPEED_DEFAULT = 0.0
# train --gain-tolerance: how far each film's gain may lie from the recording unit's on another unit of the sensor (a
# swapped or re-glued fingertip, another amplifier), as a fraction. The search also scores every candidate on its held-out
# slides with every film's gain that much higher or lower (gain_scales), and of the candidates within one standard error of
# the best it keeps those within one standard error of the best of them under another gain (choose): a model that tells
# surfaces apart by one film's level alone is not chosen when one as accurate holds under a gain change. 0: as recorded
# only. 0.2 (±1.6 dB): docs/evaluation.md, *Another film gain in the choice*
GAIN_DEFAULT = 0.2
# named feature sets: "spectrum" is the plain whole-slide spectral classifier's input (log band energies of the
# Welch PSD, log spectral centroid, kurtosis of each channel); "tex.<name>" is one texture descriptor
ALIASES: dict[str, tuple[str, ...]] = {"spectrum": ("psd", "tex.centroid", "tex.kurtosis")}
# whole-slide candidates: one row per slide, the mean of its windows' features (for psd, the slide's Welch spectrum);
# windows of 0.25 s back to back over the whole slide
SLIDE_PLACEMENTS: tuple[tuple[float, float, int], ...] = ((0.0, 0.25, 0),)
SLIDE_COMBINATIONS: tuple[tuple[tuple[str, ...], str, int], ...] = (
    (("spectrum",), "svm", 0), (("spectrum",), "linear", 0), (("spectrum",), "knn", 0), (("psd", "tex"), "svm", 0), (("dwt",), "svm", 8),
)
# per-window candidates: each window classified, the slide's scores averaged; (start_s, duration_s, max_windows)
PLACEMENTS: tuple[tuple[float, float, int], ...] = ((0.0, 0.25, 0), (0.0, 0.5, 0))
# (families, classifier, k): k > 0 keeps the k features with the largest ANOVA F (fitted in each training fold)
COMBINATIONS: tuple[tuple[tuple[str, ...], str, int], ...] = (
    (("psd",), "linear", 0), (("psd", "tex"), "svm", 0), (("psd", "tex"), "knn", 4), (("dwt",), "svm", 8),
)


def base_families(families: Sequence[str]) -> list[str]:
    """The feature families (:data:`tactiled.core.features.FAMILIES`) that ``families`` (names, aliases, ``tex.<name>``) need."""
    out: list[str] = []
    for f in families:
        for part in ALIASES.get(f, (f,)):
            base = part.split(".")[0]
            if base not in out:
                out.append(base)
    return out


def selects(families: Sequence[str], name: str) -> bool:
    """Whether feature ``name`` belongs to ``families`` (families, :data:`ALIASES`, or ``tex.<name>`` for one descriptor)."""
    fam = name_family(name)
    for f in families:
        for part in ALIASES.get(f, (f,)):
            if part == fam or ("." in part and name.endswith("." + part)):
                return True
    return False


@dataclass(frozen=True)
class Candidate:
    """One way to build a model: feature families, classifier kind, window placement, and whether forward selection picks the features."""

    families: tuple[str, ...]
    kind: str
    duration_s: float
    start_s: float = 0.0
    max_windows: int = 0
    sfs: bool = False
    fusion: str = "scores"  # scores: average the windows' scores; features: classify the slide's average features
    kbest: int = 0  # keep the k features with the largest ANOVA F (0: all)
    # the surfaces were recorded unevenly (surface_weights): an svm or linear classifier weighs each alike (scikit-learn's
    # class_weight "balanced"). Not part of what the candidate is: equal, and named, as without it.
    balanced: bool = field(default=False, compare=False)

    @property
    def name(self) -> str:
        """A readable name: families[+best k | +sfs] / classifier / duration s[ from start s][ x1][ / slide mean]."""
        where = f" from {self.start_s:g} s" if self.start_s else ""
        count = " x1" if self.max_windows == 1 else ""
        whole = " / slide mean" if self.fusion == "features" else ""
        chosen = f"+best{self.kbest}" if self.kbest else "+sfs" if self.sfs else ""
        return f"{'+'.join(self.families)}{chosen} / {self.kind} / {self.duration_s:g} s{where}{count}{whole}"

    @property
    def params(self) -> dict[str, Any]:
        """Classifier parameters: the papers' ELM's with forward selection, else the kind's defaults; ``kbest`` added when set,
        ``class_weight`` when :attr:`balanced` (svm and linear)."""
        base = PAPER_PARAMS if self.sfs else PARAMS[self.kind]
        weighed = {"class_weight": "balanced"} if self.balanced and self.kind in WEIGHTED_KINDS and not self.sfs else {}
        return {**base, **({"kbest": self.kbest} if self.kbest else {}), **weighed}

    @property
    def placement(self) -> tuple[float, float, int]:
        """(start_s, duration_s, max_windows): where the windows lie in a slide (s, s, count; 0 all)."""
        return self.start_s, self.duration_s, self.max_windows


# the papers' method: DWT statistics of one 0.5 s window 0.3 s after the start, forward selection, ELM
PAPER = Candidate(("dwt",), "elm", 0.5, 0.3, 1, True)


# the plain whole-slide spectral classifier: log band energies, log centroid and kurtosis of the slide, standardised, RBF SVM
SPECTRUM = Candidate(("spectrum",), "svm", 0.25, fusion="features")


def default_candidates() -> list[Candidate]:
    """The search space of ``tactiled train``: the whole-slide candidates first (the spectral baseline leads), then per-window ones.

    The papers' method (forward selection over an ELM: minutes of fitting) is ``--method paper``, not part of the default.
    """
    return ([Candidate(fams, kind, d, start, n, fusion="features", kbest=k) for start, d, n in SLIDE_PLACEMENTS for fams, kind, k in SLIDE_COMBINATIONS]
            + [Candidate(fams, kind, d, start, n, kbest=k) for start, d, n in PLACEMENTS for fams, kind, k in COMBINATIONS])


def quick_candidates() -> list[Candidate]:
    """``tactiled train --method quick``: a first model in seconds (log band energies and texture, linear and kNN, 0.5 s windows)."""
    return [Candidate(("psd", "tex"), "linear", 0.5), Candidate(("psd", "tex"), "knn", 0.5, kbest=8)]


@dataclass
class SearchResult:
    """The leaderboard (one row per candidate, best first), the winner, its nested CV accuracy and its model."""

    leaderboard: list[dict[str, Any]]
    winner: str
    nested: dict[str, Any]
    model: Model
    slides: int
    files: int
    per_class: dict[str, tuple[int, int, int]]
    counts: dict[str, Any]
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)
    models: dict[str, Model] = field(default_factory=dict)
    oof: tuple[FloatArray, npt.NDArray[np.intp], npt.NDArray[Any]] | None = None  # the winner's out-of-fold slide scores, true class, group


# ---- folds and slide-level scoring ------------------------------------------------------------------------------


def grouped_splits(y: npt.NDArray[Any], groups: npt.NDArray[Any], n_splits: int, seed: int) -> list[tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]]:
    """Folds that never split a group (a recording), each class's recordings spread over the folds.

    The number of folds is ``n_splits`` or, when a class has fewer recordings, that class's count (at least 2), and the
    folds are stratified by recording: a test fold then holds at most about one recording per surface, and every surface
    it tests keeps all its other recordings for training. Folds that ignored the classes put two or three recordings of
    one surface in a single test fold, leaving one or none to train on; with one slide per recording that scored
    whole-slide candidates 50 points below their test accuracy. When a class has a single recording (``train
    --group-by slide`` makes each slide a group), the folds are grouped only.
    """
    from sklearn.model_selection import GroupKFold, StratifiedGroupKFold

    y, groups = np.asarray(y), np.asarray(groups)
    n_groups = len(np.unique(groups))
    if n_groups < 2:
        raise TactiledError("cross-validation needs at least two recordings")
    fewest = fewest_groups(y, groups)
    if fewest < 2:
        k = max(2, min(n_splits, n_groups))
        return list(GroupKFold(n_splits=k, shuffle=True, random_state=seed).split(np.zeros(len(y)), y, groups))
    k = max(2, min(n_splits, int(fewest)))
    with warnings.catch_warnings():  # unlabelled slides (a "class" of a few members) do not set k: no warning for them
        warnings.filterwarnings("ignore", "The least populated class", UserWarning)
        return list(StratifiedGroupKFold(n_splits=k, shuffle=True, random_state=seed).split(np.zeros(len(y)), y, groups))


def fewest_groups(y: npt.NDArray[Any], groups: npt.NDArray[Any]) -> int:
    """The number of groups (recordings) of the labelled class with fewest; 0 if none is labelled (unlabelled: "" or -1)."""
    y, groups = np.asarray(y), np.asarray(groups)
    labelled = (y != "") if y.dtype.kind in "US" else (y >= 0)
    pairs = {(str(a), str(b)) for a, b in zip(y[labelled], groups[labelled], strict=True)}
    return int(min(np.unique([a for a, _ in pairs], return_counts=True)[1], default=0))


def slide_folds(ws: WindowSet, n_splits: int, seed: int) -> list[tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]]:
    """Grouped (by file), label-stratified where possible folds of the slides of ``ws`` (slide indices)."""
    return grouped_splits(ws.slide_labels(), np.array([s.file for s in ws.slides]), n_splits, seed)


def _window_rows(ws: WindowSet, slides: npt.NDArray[np.intp]) -> npt.NDArray[np.intp]:
    """The rows of the slides ``slides`` to train on: their windows and their speed-perturbed copies'."""
    return np.flatnonzero(np.isin(ws.slide, slides))


def gain_option(gain: float) -> float:
    """``train --gain-tolerance`` ``gain`` (a fraction) if it is one (finite, 0 to 1), else a one-line :class:`TactiledError`
    naming the option."""
    if not (math.isfinite(gain) and 0 <= gain <= 1):
        raise TactiledError(f"--gain-tolerance: must be within 0 and 1, got {gain!r}")
    return gain


def speed_option(speed: float) -> tuple[tuple[int, int], ...]:
    """The resampling ratios of ``train --speed-copies`` ``speed`` (:func:`~tactiled.learn.dataset.speed_ratios`), or a one-line
    :class:`TactiledError` naming the option."""
    try:
        return speed_ratios(speed)
    except ValueError as exc:
        raise TactiledError(f"--speed-copies: {exc}") from None


def _scored_rows(ws: WindowSet, slides: npt.NDArray[np.intp]) -> npt.NDArray[np.intp]:
    """The rows of the slides ``slides`` to score: their windows as recorded, never a copy's."""
    return np.flatnonzero(np.isin(ws.slide, slides) & ws.originals())


def slide_scores(ws: WindowSet, pipe: Any, cols: Sequence[int], test: npt.NDArray[np.intp], classes: list[str],
                 scale: FloatArray | None = None) -> FloatArray:
    """Fused scores (len(test), K) of the slides ``test`` from a fitted pipeline: the mean of their windows' scores.

    Columns follow ``classes``; classes the pipeline never saw and slides without windows get -inf. ``scale`` (len(cols),):
    each raw feature multiplied by it first (:func:`gain_scales`: the slides as another film gain would give them).
    """
    out = np.full((len(test), len(classes)), -np.inf)
    te = _scored_rows(ws, test)
    if not len(te):
        return out
    x = ws.x[te][:, cols]
    raw = decision_scores(pipe[-1], pipe[:-1].transform(x if scale is None else x * scale))
    where = {s: i for i, s in enumerate(test)}
    sums = np.zeros((len(test), raw.shape[1]))
    counts = np.zeros(len(test))
    pos = np.array([where[s] for s in ws.slide[te]])
    np.add.at(sums, pos, raw)
    np.add.at(counts, pos, 1)
    has = counts > 0
    index = {c: i for i, c in enumerate(classes)}
    for j, c in enumerate(pipe[-1].classes_):
        out[has, index[str(c)]] = sums[has, j] / counts[has]
    return out


def fold_slide_scores(ws: WindowSet, cols: npt.NDArray[np.intp], kind: str, params: dict[str, Any], train: npt.NDArray[np.intp],
                      test: npt.NDArray[np.intp], classes: list[str], seed: int) -> FloatArray:
    """:func:`slide_scores` of the test slides from a pipeline fitted on the train slides' windows (columns ``cols``)."""
    tr = _window_rows(ws, train)
    if len(np.unique(ws.y[tr])) < 2:
        return np.full((len(test), len(classes)), -np.inf)
    pipe, _ = fit_pipeline(ws.x[tr][:, cols], ws.y[tr], [ws.names[j] for j in cols], kind, params, seed)
    return slide_scores(ws, pipe, list(cols), test, classes)


def hits_of(scores: FloatArray, y_idx: npt.NDArray[np.intp]) -> npt.NDArray[np.bool_]:
    """Per slide (rows of ``scores`` (n, K)), whether its argmax is ``y_idx``; a row with no finite score is wrong."""
    decided = np.isfinite(scores).any(axis=1)
    pred = np.where(decided, np.argmax(np.where(np.isfinite(scores), scores, -np.inf), axis=1), -1)
    out: npt.NDArray[np.bool_] = pred == y_idx
    return out


def accuracy_of(scores: FloatArray, y_idx: npt.NDArray[np.intp], weights: FloatArray | None = None) -> float:
    """Slide accuracy: the mean of :func:`hits_of`, each slide weighing its surface's ``weights`` entry (K,) if given
    (:func:`surface_weights`); 0 without slides."""
    if not len(y_idx):
        return 0.0
    hits = hits_of(scores, y_idx)
    if weights is None:
        return float(np.mean(hits))
    w = weights[y_idx]
    return float(np.sum(w * hits) / np.sum(w))


IMBALANCE = 3  # surfaces whose slide counts differ this many times or more weigh alike in the choice (surface_weights)


def surface_weights(y_idx: npt.NDArray[np.intp], k: int) -> FloatArray | None:
    """(K,) each surface's weight per slide, n / (K n_k), where the labelled slides' counts ``y_idx`` (n,) (-1: none) differ
    :data:`IMBALANCE` times or more: then the choice, its fold accuracies and its estimates weigh each surface alike, as a
    lab meets its surfaces in use whatever it recorded of each (with 2 recordings of one surface and 12 of another, the
    choice by slides picked a kNN that called 51 of 60 slides of a balanced test the larger surface). None otherwise: a
    set recorded about evenly is judged by slides, as before (to the bit)."""
    counts = np.bincount(y_idx[y_idx >= 0], minlength=k).astype(np.float64)
    if counts.min() <= 0 or counts.max() < IMBALANCE * counts.min():
        return None
    out: FloatArray = counts.sum() / (k * counts)
    return out


def _interval_text(band: list[float] | None, over: str = "recordings") -> str:
    """`` (95 % interval over recordings 52–69 %)`` of :func:`recording_interval`, or nothing; ``over``: what the groups
    it resampled are (``slides`` for ``train --group-by slide``)."""
    return f" (95 % interval over {over} {100 * band[0]:.0f}–{100 * band[1]:.0f} %)" if band else ""  # as Model.describe rounds it


def reasons_text(skipped: dict[str, int]) -> str:
    """``window_too_short 6, saturated 2``: why slides had no usable window (:attr:`WindowSet.skipped`), most frequent first."""
    return ", ".join(f"{why} {n}" for why, n in sorted(skipped.items(), key=lambda kv: (-kv[1], kv[0])))


# {surface: (slides, slides with a usable window, recordings with one, {reason: slides without a usable window})}
UsableTable = dict[str, tuple[int, int, int, dict[str, int]]]


def usable_table(sets: Sequence[WindowSet]) -> UsableTable:
    """Per surface, what the window sets ``sets`` (every set has the same slides in the same order) can learn from: a slide
    is usable when one of them has a window of it; a slide usable in none is counted under its reason in the first."""
    first = sets[0]
    out: dict[str, tuple[int, int, set[int], dict[str, int]]] = {}
    for k, s in enumerate(first.slides):
        if s.label is None:
            continue
        n, ok, files, why = out.setdefault(s.label, (0, 0, set(), {}))
        reason = None if any(ws.reasons[k] is None for ws in sets) else first.reasons[k]
        if reason is None:
            files.add(s.file)
        else:
            why[reason] = why.get(reason, 0) + 1
        out[s.label] = (n + 1, ok + (reason is None), files, why)
    return {k: (n, ok, len(files), why) for k, (n, ok, files, why) in sorted(out.items())}


def without_surfaces(ws: WindowSet, drop: set[str]) -> WindowSet:
    """``ws`` without the slides (and their windows) of the surfaces ``drop``; the others keep their order."""
    keep = np.array([s.label not in drop for s in ws.slides], dtype=bool)
    index = np.cumsum(keep) - 1  # a kept slide's new index
    rows = keep[ws.slide] if len(ws.slide) else np.zeros(0, dtype=bool)
    return replace(ws, x=ws.x[rows], y=ws.y[rows], groups=ws.groups[rows], slide=index[ws.slide[rows]].astype(np.int64),
                   spans=ws.spans[rows], slides=[s for s, k in zip(ws.slides, keep, strict=True) if k],
                   reasons=[r for r, k in zip(ws.reasons, keep, strict=True) if k], copy=None if ws.copy is None else ws.copy[rows])


# ---- parallel execution -----------------------------------------------------------------------------------------


CONNECT_S = 10.0  # how long a scheduler may take to answer


def check_scheduler(scheduler: str) -> None:
    """Raise :class:`TactiledError` (one line) unless ``scheduler`` is an address dask.distributed can parse and, for
    TCP (``tcp://``, ``tls://``), one that accepts a connection: a refused one is said at once (dask's client retries it
    for :data:`CONNECT_S`), so ``train`` can check before it analyses any recording. On ``tcp://`` the peer must also
    begin dask's handshake (a scheduler sends its first at once) within :data:`CONNECT_S`: dask's client waits for ever
    on a port that accepts and says nothing (another service's)."""
    try:
        from distributed.comm import parse_address
        from distributed.comm.addressing import parse_host_port
        from distributed.comm.registry import get_backend
    except ImportError:
        raise TactiledError("--scheduler needs dask.distributed: pip install 'tactiled[cluster]'") from None
    try:
        scheme, location = parse_address(scheduler, strict=True)
        get_backend(scheme)
        host, port = parse_host_port(location) if scheme in ("tcp", "tls") else (None, None)
    except ValueError as exc:  # not an address dask knows: no scheme://host:port
        raise TactiledError(f"--scheduler {scheduler}: not a scheduler address (tcp://host:port): {exc}") from None
    if host is None:
        return
    try:
        conn = socket.create_connection((host, port), timeout=CONNECT_S)
    except OSError as exc:  # refused, no route, unknown host, or no answer (TimeoutError)
        raise TactiledError(f"--scheduler {scheduler}: cannot connect: {exc.strerror or exc}") from None
    with conn:
        if scheme == "tcp":  # (over tls the client speaks first)
            try:
                first = conn.recv(1)
            except OSError:  # TimeoutError: no answer; a reset
                first = b""
            if not first:
                raise TactiledError(f"--scheduler {scheduler}: accepts connections but does not answer as a dask scheduler "
                                    f"(no handshake within {CONNECT_S:g} s)")


@contextlib.contextmanager
def parallel_backend(scheduler: str | None) -> Iterator[None]:
    """joblib on every local core, or on a dask.distributed cluster at ``scheduler`` (``tcp://host:port``)."""
    import joblib

    if not scheduler:
        with joblib.parallel_config(n_jobs=-1):
            yield
        return
    try:
        from dask.distributed import Client
    except ImportError:
        raise TactiledError("--scheduler needs dask.distributed: pip install 'tactiled[cluster]'") from None
    try:  # train() has checked the address (check_scheduler); a scheduler gone since is said here
        client = Client(scheduler, timeout=f"{CONNECT_S:g}s")
    except ValueError as exc:
        raise TactiledError(f"--scheduler {scheduler}: not a scheduler address (tcp://host:port): {exc}") from None
    except (OSError, TimeoutError) as exc:
        raise TactiledError(f"--scheduler {scheduler}: cannot connect: {exc}") from None
    try:
        with joblib.parallel_config(backend="dask"):
            yield
    finally:
        client.close()


# ---- the search ---------------------------------------------------------------------------------------------------


def _key(c: Candidate) -> tuple[Any, ...]:
    key = (*c.placement, c.families)
    return (*key, "features") if c.fusion == "features" else key


def _columns(ws: WindowSet, families: Sequence[str]) -> npt.NDArray[np.intp]:
    return np.array([j for j, n in enumerate(ws.names) if selects(families, n)], dtype=np.intp)


def fit_candidate(ws: WindowSet, rows: npt.NDArray[np.intp], c: Candidate, seed: int, inner_folds: int = 3) -> tuple[list[int], Any, Any]:
    """(columns, fitted pipeline, refit data) of candidate ``c`` on the windows ``rows``; forward selection first if ``c.sfs``."""
    cols = [int(j) for j in _columns(ws, c.families)]
    if c.sfs:
        cols = [cols[j] for j in sfs_columns(_restrict(ws, cols), rows, seed, inner_folds)]
    pipe, refit = fit_pipeline(ws.x[rows][:, cols], ws.y[rows], [ws.names[j] for j in cols], c.kind, c.params, seed)
    if "select" in pipe.named_steps:  # bake the selection into the columns: the model then computes only those features
        cols = [cols[j] for j in np.flatnonzero(pipe.named_steps["select"].get_support())]
        params = {k: v for k, v in c.params.items() if k != "kbest"}
        pipe, refit = fit_pipeline(ws.x[rows][:, cols], ws.y[rows], [ws.names[j] for j in cols], c.kind, params, seed)
    return cols, pipe, refit


def _restrict(ws: WindowSet, cols: list[int]) -> WindowSet:
    if len(cols) == len(ws.names):
        return ws
    return replace(ws, x=ws.x[:, cols], names=[ws.names[j] for j in cols])


def gain_scales(names: Sequence[str], tolerance: float) -> list[FloatArray]:
    """:func:`gain_patterns` of ``names`` (computed once per set of names: every fold of every candidate asks)."""
    return list(gain_patterns(tuple(names), tolerance))


@functools.lru_cache(maxsize=16)
def gain_patterns(names: tuple[str, ...], tolerance: float) -> tuple[FloatArray, ...]:
    """Multipliers (F,) of raw features ``names``, one per pattern of film gains another unit of the sensor can have: every
    film's gain ``g = 1 + tolerance`` times what was recorded, every film's 1/g times, and (two films or more) the odd
    films' g times and the even ones' 1/g times, and the reverse. Every pattern moves every film, as another unit does: a
    model that reads one film's level meets every change, one that reads the films' levels against each other meets the
    opposite ones, one that reads the spectrum's shape none. A feature of degree d (:func:`~tactiled.core.features.
    feature_degree`: 2 for an energy or a band power, 1 for an rms, 0 for a shape) scales by gain**d, exactly. Nothing (an
    empty tuple) for a tolerance of 0."""
    if tolerance <= 0:
        return ()
    degrees = np.array([feature_degree(n) for n in names], dtype=np.float64)
    films = channel_columns(names)
    g = 1.0 + tolerance
    patterns = [[g] * len(films), [1 / g] * len(films)]
    if len(films) > 1:
        patterns += [[g if k % 2 == 0 else 1 / g for k in range(len(films))], [1 / g if k % 2 == 0 else g for k in range(len(films))]]
    out = []
    for pattern in patterns:
        scale = np.ones(len(names))
        for cols, gain in zip(films, pattern, strict=True):
            scale[cols] = gain ** degrees[cols]
        scale.setflags(write=False)  # cached: shared by every caller
        out.append(scale)
    return tuple(out)


def candidate_fold(ws: WindowSet, c: Candidate, train: npt.NDArray[np.intp], test: npt.NDArray[np.intp], classes: list[str], seed: int,
                   inner_folds: int, gain: float = GAIN_DEFAULT) -> FloatArray:
    """Fused scores (1 + P, len(test), K) of the test slides from candidate ``c`` fitted on the train slides (selection inside
    them only): as recorded, then under each of the P film gains of :func:`gain_scales` (``gain``: its tolerance; none at 0)."""
    tr = _window_rows(ws, train)
    if len(np.unique(ws.y[tr])) < 2:
        return np.full((1 + len(gain_scales(ws.names, gain)), len(test), len(classes)), -np.inf)
    cols, pipe, _ = fit_candidate(ws, tr, c, seed, inner_folds)
    return np.stack([slide_scores(ws, pipe, cols, test, classes, None if scale is None else scale[cols])
                     for scale in [None, *gain_scales(ws.names, gain)]])


def candidate_folds(ws: WindowSet, c: Candidate, splits: list[tuple[Any, Any, list[tuple[Any, Any]]]], classes: list[str], seed: int,
                    inner_folds: int, gain: float = GAIN_DEFAULT) -> list[tuple[FloatArray, list[FloatArray]]]:
    """:func:`candidate_fold` on every (outer train, outer test, inner folds) split: the outer scores and each inner fold's."""
    return [(candidate_fold(ws, c, tr, te, classes, seed, inner_folds, gain),
             [candidate_fold(ws, c, itr, ite, classes, seed, inner_folds, gain) for itr, ite in inner]) for tr, te, inner in splits]


def gain_accuracies(scores: FloatArray, y_idx: npt.NDArray[np.intp], weights: FloatArray | None = None) -> tuple[float, float | None]:
    """(the accuracy as recorded, the mean accuracy under the P film gains or None without them) of one fold's
    :func:`candidate_fold` scores (1 + P, n, K); ``weights``: :func:`accuracy_of`'s."""
    nominal = accuracy_of(scores[0], y_idx, weights)
    if len(scores) == 1:
        return nominal, None
    return nominal, float(np.mean([accuracy_of(sc, y_idx, weights) for sc in scores[1:]]))


def search(recs: Sequence[tuple[str, Recording]], config: Config, *, folds: int = 5, inner_folds: int = 3, seed: int = 0,
           candidates: Sequence[Candidate] | None = None, progress: Progress | None = None, scheduler: str | None = None,
           found: tuple[list[list[LabelledSlide]], SlideCounts] | None = None, method: str = "search", keep_models: bool = False,
           novelty: str = NOVELTY_DEFAULT, ensemble: str = ENSEMBLE_DEFAULT, untaught: float = UNTAUGHT_SHARE,
           speed: float = SPEED_DEFAULT, check_usable: Callable[[UsableTable], Collection[str]] | None = None,
           group_by: str = "file", gain: float = GAIN_DEFAULT) -> SearchResult:
    """Score every candidate, pick and refit the winner (see the module docstring).

    ``keep_models``: also refit every other candidate (``SearchResult.models``, by name; the winner alone under its name
    when the model is an ensemble), to compare them on held-out recordings.
    ``novelty``: the models' unknown-surface tests (:data:`NOVELTY_TESTS`); ``untaught``: the share of
    slides expected on untaught surfaces, which weighs its threshold (:func:`novelty_threshold`).
    ``ensemble`` (:data:`ENSEMBLE_MODES`): whether the winner and :data:`SPECTRUM` make one model (:func:`ensemble_of`) when the
    winner may have a partner (:func:`can_partner`): ``off`` never, ``always``, or ``guarded``, only when the ensemble's
    out-of-fold accuracy is within one standard error of the winner's (:func:`within_one_se` on the same outer folds).
    ``speed``: per cent slower and faster of the two speed-perturbed copies of each training slide every candidate also
    learns from (:func:`~tactiled.learn.dataset.speed_ratios`; 0: none).
    ``check_usable``: once every window set is analysed, before any fold, it is given the slides each surface has with a
    usable window (:func:`usable_table`); it raises, or returns the surfaces to train without. ``group_by``: what the
    slides' ``file`` numbers are, ``file`` or ``slide`` (``train --group-by slide``: the nested estimate is then
    optimistic, its interval over slides, and ``nested`` says ``grouped_by: slide``). ``gain`` (``train --gain-tolerance``):
    every candidate is also scored on its held-out slides as another film gain would give them (:func:`gain_scales`), and
    the choice, outer and inner, keeps of the candidates within one standard error of the best those within one standard
    error of the best of them under another gain (:func:`choose`); the leaderboard and the nested estimate stay
    accuracies as recorded.
    """
    gain_option(gain)
    if ensemble not in ENSEMBLE_MODES:
        raise TactiledError(f"--ensemble: must be one of {', '.join(ENSEMBLE_MODES)}, got {ensemble!r}")
    speeds = speed_option(speed)
    say = progress or (lambda m: None)
    t0 = time.perf_counter()
    fs, channels = recs[0][1].fs, recs[0][1].channels
    found = found or find_slides(recs, config)
    wanted = list(candidates if candidates is not None else default_candidates())
    sets: dict[tuple[Any, ...], tuple[AnalysisSettings, WindowSet]] = {}
    windows_of: dict[tuple[Any, ...], WindowSet] = {}  # each candidate's windows, one row per window (a whole-slide one's before averaging)
    usable: list[Candidate] = []
    slide_rows: dict[tuple[Any, ...], WindowSet] = {}  # each placement's whole-slide rows, averaged once for all its families
    for c in wanted:
        key: tuple[Any, ...] = (*c.placement, c.families)
        fams = sorted({f for w in wanted if w.placement == c.placement for f in base_families(w.families)})
        full = (*c.placement, tuple(fams))
        if full not in sets:
            # the spectrum test reads the psd bands whatever the candidates read; the DWT may not fit such windows: without it
            tries = [sorted({*fams, "psd"})] if novelty == "spectrum" else []
            tries += [fams, [f for f in fams if f != "dwt"]]
            st = next((st for st in (window_settings(config, channels, fs, c.duration_s, fam, c.start_s, c.max_windows) for fam in tries)
                       if st is not None), None)
            if st is not None:
                say(f"features of {c.duration_s:g} s windows from {c.start_s:g} s ({len(st.names)} features)")
                sets[full] = (st, collect_windows(recs, config, st, progress, found=found, jobs=None, speeds=speeds))
                skipped = dict(sets[full][1].skipped)
                unlabelled = skipped.pop("unlabelled", 0)
                if unlabelled:
                    say(f"  {unlabelled} slides without a surface (their recordings name none) are not learnt")
                if skipped:
                    say(f"  slides without a usable {c.duration_s:g} s window: {reasons_text(skipped)}")
        if full in sets and all(any(name_family(n) == f for n in sets[full][1].names) for f in base_families(c.families)):
            if c.fusion == "features":
                key = (*key, "features")
                if full not in slide_rows:
                    whole = slide_rows[full] = sets[full][1].averaged()
                    pieces = whole.slide[whole.copy == PIECE] if whole.copy is not None else np.array([], dtype=np.int64)
                    if len(pieces):
                        say(f"whole-slide candidates of {c.duration_s:g} s windows also learn the {len(np.unique(pieces))} slides of "
                            f"{2 * PIECE_WINDOWS} windows or more as {len(pieces)} pieces of {PIECE_WINDOWS}")
                sets[key] = (sets[full][0], slide_rows[full])
            else:
                sets[key] = sets[full]
            windows_of[key] = sets[full][1]
            usable.append(c)
    if not usable:
        raise TactiledError(f"no candidate fits: windows too short for the feature families at {fs:g} Hz; record longer slides")
    if check_usable is not None:
        drop = set(check_usable(usable_table(list(windows_of.values()))))
        if drop:  # every set loses the same slides, so they keep the same slides in the same order
            distinct = {id(ws): ws for ws in [*(ws for _, ws in sets.values()), *windows_of.values()]}
            trimmed = {i: without_surfaces(ws, drop) for i, ws in distinct.items()}
            sets = {k: (st, trimmed[id(ws)]) for k, (st, ws) in sets.items()}
            windows_of = {k: trimmed[id(ws)] for k, ws in windows_of.items()}
    first = sets[_key(usable[0])][1]
    classes = sorted({s.label for s in first.slides if s.label is not None})
    if len(classes) < 2:
        raise TactiledError(f"training needs at least two surfaces, got {classes}")
    y_idx = np.array([classes.index(s.label) if s.label in classes else -1 for s in first.slides])
    files = np.array([s.file for s in first.slides])  # every window set has these slides in this order
    weights = surface_weights(y_idx, len(classes))  # None unless the surfaces' slide counts differ IMBALANCE times or more
    if weights is not None:  # the classifiers that can weigh each surface alike do (equal candidates all the same)
        usable = [replace(c, balanced=True) for c in usable]
    outer = slide_folds(first, folds, seed)
    nested_on = len(usable) > 1
    # every window set has the same slides in the same order, so one set of inner folds per outer fold serves every candidate
    made = [_inner_folds(first, tr, inner_folds, seed) if nested_on else ("file", []) for tr, _ in outer]
    grouping, inner = [how for how, _ in made], [folds_in for _, folds_in in made]
    if "none" in grouping:
        say("nested CV: an outer training fold holds a single slide of some surface, so no inner folds can choose the "
            "candidate there: that fold scores the winner itself, and the nested estimate is optimistic")
    elif "slide" in grouping:
        say("nested CV: an outer training fold holds a single recording of some surface, so the inner folds that choose "
            "the candidate there split recordings by slide (their scores are optimistic; only the outer folds are reported)")
    # every window set has the same slides in the same order (detection does not depend on the window)
    tasks = []
    for c in usable:  # one task per candidate (its data crosses to a worker once); per outer fold for the slow forward selection
        splits = [(tr, te, folds_in) for (tr, te), folds_in in zip(outer, inner, strict=True)]
        parts = [[sp] for sp in splits] if c.sfs else [splits]
        tasks += [(candidate_folds, (sets[_key(c)][1], c, part, classes, seed, inner_folds, gain)) for part in parts]
    fits = [sum(1 + len(inner) for _, _, inner in t[1][2]) for t in tasks]  # model fits per task: each outer fold and its inner folds
    say(f"cross-validating {len(usable)} candidate(s) over {len(outer)} outer" + (f" x {inner_folds} inner" if nested_on else "")
        + f" folds: {sum(fits)} fits")
    results = iter(_run_with_progress(tasks, say, scheduler, [t[1][1].sfs for t in tasks], fits))
    board: list[dict[str, Any]] = []
    oof: dict[str, FloatArray] = {}
    inner_acc: dict[str, list[list[tuple[float, float | None]]]] = {}  # per candidate, per outer fold: each inner fold's accuracies
    stressed_folds: list[list[float]] = []  # per candidate, per outer fold: the accuracy under another film gain (--gain-tolerance)
    for c in usable:
        ws = sets[_key(c)][1]
        scores = np.full((len(ws.slides), len(classes)), -np.inf)
        accs, stressed, per_outer_inner = [], [], []
        per_fold = [r for _ in range(len(outer) if c.sfs else 1) for r in next(results)]
        for (_, te), folds_in, (sc, inner_scores) in zip(outer, inner, per_fold, strict=True):
            scores[te] = sc[0]
            nominal, under = gain_accuracies(sc, y_idx[te], weights)
            accs.append(nominal)
            stressed += [] if under is None else [under]
            per_outer_inner.append([gain_accuracies(isc, y_idx[ite], weights) for (_itr, ite), isc in zip(folds_in, inner_scores, strict=True)])
        oof[c.name] = scores
        inner_acc[c.name] = per_outer_inner
        stressed_folds.append(stressed)
        board.append({"candidate": c.name, "families": list(c.families), "classifier": c.kind, "start_s": c.start_s, "duration_s": c.duration_s,
                      "max_windows": c.max_windows, "sfs": c.sfs, "fusion": c.fusion, "mean": float(np.mean(accs)), "sd": float(np.std(accs)), "folds": accs,
                      **({"gain_mean": float(np.mean(stressed))} if stressed else {})})
    means = [float(r["mean"]) for r in board]
    order = sorted(range(len(board)), key=lambda i: -means[i])  # stable: ties keep the cheaper candidate
    chosen = choose(usable, [r["folds"] for r in board], stressed_folds if gain else None, len(y_idx))
    board[chosen]["chosen"] = True
    leaderboard = [board[i] for i in order]
    best = usable[chosen]
    # nested: per outer fold, the rule applied to the inner folds' accuracies, its pick scored on that fold
    nested_accs, picks = [], []
    for o in range(len(outer)):
        pick = (choose(usable, [[a for a, _ in inner_acc[c.name][o]] for c in usable],
                       [[float(u) for _, u in inner_acc[c.name][o] if u is not None] for c in usable] if gain else None,
                       len(outer[o][0]))
                if nested_on and grouping[o] != "none" else chosen)
        picks.append(usable[pick].name)
        nested_accs.append(float(board[pick]["folds"][o]))
    nested_hits = np.concatenate([hits_of(oof[name][te], y_idx[te]) for name, (_, te) in zip(picks, outer, strict=True)])
    nested_y = np.concatenate([y_idx[te] for _, te in outer])
    band = recording_interval(nested_hits, np.concatenate([files[te] for _, te in outer]), weights=None if weights is None else weights[nested_y])
    nested: dict[str, Any] = {"mean": float(np.mean(nested_accs)), "sd": float(np.std(nested_accs)), "folds": nested_accs, "picks": picks, "interval95": band,
              **per_surface(nested_hits, nested_y, classes), **({"weighted": True} if weights is not None else {}),
              **({"inner_grouped_by": "none" if "none" in grouping else "slide"} if set(grouping) - {"file"} else {}),
              **({"grouped_by": "slide"} if group_by == "slide" else {})}
    shown = leaderboard[:12] + ([board[chosen]] if board[chosen] not in leaderboard[:12] else [])
    summary: dict[str, Any] = {"cv_accuracy": nested, "winner": best.name, "leaderboard": shown, "files": len(recs),
                               **({"speed_copies": speed} if speeds else {}),  # without copies, the model file as before them
                               **({"gain_tolerance": gain} if gain else {})}
    alone = _refit(sets, best, oof[best.name], y_idx, classes, config, fs, channels, seed, inner_folds, method, summary, novelty, untaught,
                   windows_of[_key(best)])
    model, members, scores = alone, [(best, alone.temperature)], oof[best.name]
    if ensemble != "off" and not can_partner(best, usable):
        say(f"--ensemble {ensemble}: no ensemble: " + (
            f"the choice is {SPECTRUM.name} itself" if best == SPECTRUM else
            f"{SPECTRUM.name} was not among the candidates scored" if SPECTRUM not in usable else
            f"the choice's windows are not {SPECTRUM.name}'s (0.25 s from the start, all of them)"))
    if ensemble != "off" and can_partner(best, usable):
        own_t = fit_temperature(oof[best.name], y_idx)  # the winner's temperature as a member (label-smoothed, as the partner's)
        spectrum = usable[usable.index(SPECTRUM)]  # the one scored (balanced where the surfaces were recorded unevenly)
        partner = _fit_member(sets, spectrum, oof[SPECTRUM.name], y_idx, classes, config, fs, channels, seed, inner_folds, method)
        both = ensemble_scores(oof[best.name], own_t, oof[SPECTRUM.name], partner.temperature)
        folds_both = [accuracy_of(both[te], y_idx[te], weights) for _, te in outer]
        within = 1 in within_one_se([board[chosen]["folds"], folds_both])
        info = {"partner": SPECTRUM.name, "mean": float(np.mean(folds_both)), "sd": float(np.std(folds_both)), "folds": folds_both,
                "within_one_se": within, "mode": ensemble, "used": ensemble == "always" or within}
        board[chosen]["ensemble"] = info
        if info["used"]:
            model = ensemble_of(alone, own_t, partner, both, y_idx, sets[_key(best)][1].names)
            # the model written is the ensemble: its file states the ensemble's nested estimate (the winner alone's is kept)
            info["alone_nested"] = nested
            nested = _nested_ensemble(oof, usable, picks, outer, y_idx, files, {best.name: own_t}, partner.temperature, nested, classes, weights)
            band = nested["interval95"]
            model.summary = {**model.summary, "cv_accuracy": nested, "ensemble": info}
            members, scores = [(best, own_t), (spectrum, partner.temperature)], both  # the one fitted (balanced where weighted)
        else:
            alone.summary = {**alone.summary, "ensemble": info}
    said = f" with {SPECTRUM.name} (ensemble)" if model.partner is not None else ""
    ens = board[chosen].get("ensemble")
    ens_cv = f"; ensemble CV {ens['mean']:.3f}" if ens else ""
    alone_cv = f" (the choice alone: {ens['alone_nested']['mean']:.3f})" if ens and "alone_nested" in ens else ""
    say(f"winner {best.name}{said}: {board[chosen]['mean']:.3f} ± {board[chosen]['sd']:.3f} (best mean {leaderboard[0]['mean']:.3f}){ens_cv}; "
        f"nested CV {'of the ensemble ' if alone_cv else ''}{nested['mean']:.3f}{_interval_text(band, 'slides' if group_by == 'slide' else 'recordings')}"
        f"{alone_cv}" + ("; optimistic: the folds split recordings (--group-by slide)" if group_by == "slide" else "") + "; fitted on every slide")
    # provisional labels come from the first windows of a slide: their own calibration (the winner alone's too, when it is
    # kept beside the ensemble, so that it is the model train --ensemble off makes)
    for m, of in [(model, members), *([(alone, members[:1])] if keep_models and model is not alone else [])]:
        if best.max_windows != 1:
            say("calibrating provisional labels on out-of-fold slide prefixes")
            m.early_calibration, early_info = fit_early_calibration(windows_of[_key(best)], of, outer, classes, m.temperature, seed, inner_folds)
            m.summary = {**m.summary, "early_calibration": early_info}
    ws = sets[_key(best)][1]
    result = SearchResult(leaderboard, best.name, nested, model, len(ws.slides), len(recs), ws.per_class(), _counts(ws),
                          time.perf_counter() - t0, oof=(scores, y_idx, files))
    if keep_models:
        result.models = {c.name: alone if c == best else _refit(sets, c, oof[c.name], y_idx, classes, config, fs, channels, seed,
                                                                   inner_folds, method, summary, novelty, untaught, windows_of[_key(c)])
                         for c in usable}
    return result


def per_surface(hits: npt.NDArray[np.bool_], y_idx: npt.NDArray[np.intp], classes: Sequence[str]) -> dict[str, Any]:
    """``recall`` per surface of ``classes`` (those with slides) and the ``balanced`` accuracy (their mean; None without
    any) of slides whose true class indices are ``y_idx`` and whose answers were right or not (``hits``)."""
    recall = {k: float(hits[y_idx == i].mean()) for i, k in enumerate(classes) if np.any(y_idx == i)}
    return {"recall": recall, "balanced": float(np.mean(list(recall.values()))) if recall else None}


def _nested_ensemble(oof: dict[str, FloatArray], usable: Sequence[Candidate], picks: Sequence[str], outer: Sequence[tuple[Any, Any]],
                     y_idx: npt.NDArray[np.intp], files: npt.NDArray[Any], temperatures: dict[str, float], partner_temperature: float,
                     alone: dict[str, Any], classes: Sequence[str], weights: FloatArray | None = None) -> dict[str, Any]:
    """The nested estimate of ``train --ensemble``'s model, in the form of :func:`search`'s ``nested``: in each outer fold, the
    candidate the inner folds picked (``picks``) with :data:`SPECTRUM` as its partner where it may have one
    (:func:`can_partner`; alone where not), scored on that fold's out-of-fold scores ``oof``. Each member's temperature is
    as the ensemble's (``temperatures`` of the winner, else fitted on the pick's out-of-fold scores; ``partner_temperature``),
    as for the ensemble's own cross-validated accuracy. ``guarded``'s check is not repeated inside the folds. ``alone``: the
    picks' own nested estimate, whose grouping notes (``grouped_by``, ``inner_grouped_by``) it keeps."""
    by_name = {c.name: c for c in usable}
    accs, hits = [], []
    for name, (_, te) in zip(picks, outer, strict=True):
        sc = oof[name][te]
        if can_partner(by_name[name], usable):
            t = temperatures.get(name)
            t = fit_temperature(oof[name], y_idx) if t is None else t
            sc = ensemble_scores(sc, t, oof[SPECTRUM.name][te], partner_temperature)
        accs.append(accuracy_of(sc, y_idx[te], weights))
        hits.append(hits_of(sc, y_idx[te]))
    ys = np.concatenate([y_idx[te] for _, te in outer])
    band = recording_interval(np.concatenate(hits), np.concatenate([files[te] for _, te in outer]), weights=None if weights is None else weights[ys])
    return {"mean": float(np.mean(accs)), "sd": float(np.std(accs)), "folds": accs, "picks": list(picks), "interval95": band,
            "model": "ensemble", **per_surface(np.concatenate(hits), np.concatenate([y_idx[te] for _, te in outer]), classes),
            **{k: v for k, v in alone.items() if k in ("grouped_by", "inner_grouped_by", "weighted")}}


def can_partner(best: Candidate, usable: Sequence[Candidate]) -> bool:
    """Whether the winner ``best`` may make an ensemble with :data:`SPECTRUM`: it is not SPECTRUM, SPECTRUM was scored
    (one of ``usable``), and both place their windows alike (0.25 s from the start, all of them), so that one analysis
    computes both members' features."""
    return best != SPECTRUM and SPECTRUM in usable and best.placement == SPECTRUM.placement


def ensemble_of(first: Model, first_temperature: float, partner: Model, oof: FloatArray, y_idx: npt.NDArray[np.intp],
                order: Sequence[str]) -> Model:
    """The ensemble of two members fitted alone (``first``: the winner, with its novelty, and ``first_temperature``, its
    label-smoothed temperature as a member; ``partner``: from :func:`_fit_member`), both over one analysis.

    Its features are the union of the members' (in ``order``, the window set's columns), its temperature and calibration
    map are fitted on the ensemble's out-of-fold slide scores ``oof`` (slides, K) (:func:`~tactiled.learn.model.ensemble_scores`
    of the members' out-of-fold scores, each softened by its own temperature) against ``y_idx`` (:func:`calibrate`). Novelty stays the first
    member's (its standardised slide-mean features, its thresholds): a slide unlike the training slides in the winner's
    features is what it was before the partner was added.
    """
    names = tuple(n for n in order if n in set(first.names) | set(partner.names))
    model = replace(first, settings=replace(first.settings, names=names), member_names=first.inputs, member_temperature=first_temperature,
                    partner=partner, fingerprint="", summary=dict(first.summary))
    calibrate(model, oof, y_idx)
    return model


def _refit(sets: dict[tuple[Any, ...], tuple[AnalysisSettings, WindowSet]], c: Candidate, oof: FloatArray, y_idx: npt.NDArray[np.intp],
           classes: list[str], config: Config, fs: float, channels: int, seed: int, inner_folds: int, method: str,
           summary: dict[str, Any], novelty: str = NOVELTY_DEFAULT, untaught: float = UNTAUGHT_SHARE, windows: WindowSet | None = None) -> Model:
    """Candidate ``c`` fitted on every labelled slide (:func:`_fit_member`), its temperature and calibration fitted on its
    out-of-fold slide scores ``oof`` (:func:`calibrate`), its novelty on its slides' mean features (the ``spectrum`` test:
    the spectral shape of the window set's psd columns, added to the model's analysis; ``far`` where the set has none;
    with the slides' ``windows``, one row per window, its provisional labels' thresholds: :func:`fit_prefix_novelty`)."""
    model = _fit_member(sets, c, oof, y_idx, classes, config, fs, channels, seed, inner_folds, method)
    ws = sets[_key(c)][1]
    model.summary = {**summary, "slides": len(ws.slides), "windows": int(np.sum((ws.y != "") & ws.originals())), "classes": classes,
                     "per_class": {k: list(v) for k, v in ws.per_class().items()}, "skipped": ws.skipped, "detector": _counts(ws)}
    calibrate(model, oof, y_idx)
    slides = ws if c.fusion == "features" else ws.averaged()  # one row per slide: the mean of its windows' raw features
    labelled = np.flatnonzero((slides.y != "") & slides.originals())  # the slides as recorded: a copy is no new recording
    shape = tuple(n for n in slides.names if name_family(n) == "psd") if novelty == "spectrum" else ()
    if shape:
        names = model.names + tuple(n for n in shape if n not in model.names)
        model.member_names = model.names if names != model.names else None
        model.settings, model.novelty_names = replace(model.settings, names=names), shape
    elif novelty == "spectrum":
        novelty = "far"
        model.summary = {**model.summary, "notes": [*model.summary.get("notes", []),
                                                    "no psd band fits these windows: unknown surfaces by the far test on the classifier's features"]}
    means = take_columns(slides.x[labelled], slides.names, model.names)
    fit_model_novelty(model, model.novelty_features(means), slides.y[labelled], slides.groups[labelled], novelty, untaught)
    if shape and windows is not None:
        fit_prefix_novelty(model, windows)
    return model


def fit_prefix_novelty(model: Model, windows: WindowSet, reject: float = 0.05, most: int = 40, fewest: int = 20) -> None:
    """The novelty thresholds of provisional labels (``model.novelty_prefix``), for a spectrum-test model whose novelty is
    fitted: a slide's first w windows estimate its spectrum less well than all of them, so their distance to the taught
    surfaces runs larger. For w = 1, 2, ... (at most ``most``, while ``fewest`` slides have w windows), the (1 - ``reject``)
    quantile of the distances from the first w windows of each training slide (``windows``: one row per window) to the
    other recordings' slides, as a multiple (at least 1) of the whole-slide threshold; as that threshold, over the slides
    whose surface another recording holds (at least ``fewest`` of them)."""
    if model.novelty_x is None or model.novelty_y is None or model.novelty_groups is None or not math.isfinite(model.novelty_distance_threshold):
        return
    keep = np.flatnonzero((windows.y != "") & windows.originals())
    keep = keep[np.lexsort((windows.spans[keep, 0], windows.slide[keep]))]  # each slide's windows together, in time order
    x, slide, group, surface = take_columns(windows.x[keep], windows.names, model.names), windows.slide[keep], windows.groups[keep], windows.y[keep]
    starts = np.flatnonzero(np.r_[True, slide[1:] != slide[:-1]])
    lengths = np.diff(np.r_[starts, len(slide)])
    sums = np.zeros((len(starts), x.shape[1]))
    surfaces = np.unique(model.novelty_y)
    own = model.novelty_surface_scale if model.novelty_surface_scale is not None else np.ones(len(surfaces))
    # per recording: the other recordings' slides, their surfaces and those surfaces' scales (the same for every window count)
    others = {g: (model.novelty_x[o], model.novelty_y[o], surface_scale_for(surfaces, own, model.novelty_y[o]))
              for g in np.unique(group[starts]) for o in [model.novelty_groups != g] if o.any()}
    factors: list[float] = []
    for w in range(1, most + 1):
        have = lengths >= w
        if have.sum() < fewest:
            break
        sums[have] += x[starts[have] + w - 1]
        z = model.novelty_standardise(model.novelty_features(sums[have] / w))
        groups, surfaces_of = group[starts[have]], surface[starts[have]]
        dist = np.zeros(len(z))
        counted = np.zeros(len(z), dtype=bool)  # as the whole-slide threshold (spectrum_threshold): only a slide whose surface
        for g in np.unique(groups):  # another recording holds (else its nearest surface is another, and it stands for an untaught one)
            if g in others:
                mine, (ref, labels, scale) = groups == g, others[g]
                dist[mine] = nearest_surface_distances(z[mine], ref, labels, model.novelty_k, scale=scale)[:, 0]
                counted[mine] = np.isin(surfaces_of[mine], labels)
        if counted.sum() < fewest:
            break
        factors.append(max(float(np.quantile(dist[counted], 1.0 - reject, method="higher")) / model.novelty_distance_threshold, 1.0))
    model.novelty_prefix = tuple(factors)


def _fit_member(sets: dict[tuple[Any, ...], tuple[AnalysisSettings, WindowSet]], c: Candidate, oof: FloatArray, y_idx: npt.NDArray[np.intp],
                classes: list[str], config: Config, fs: float, channels: int, seed: int, inner_folds: int, method: str) -> Model:
    """Candidate ``c`` fitted on every labelled slide, its temperature fitted on its out-of-fold slide scores ``oof`` (slides, K):
    a model without calibration, novelty or summary (an ensemble's partner as it is, the winner after :func:`_refit`)."""
    st, ws = sets[_key(c)]
    rows = np.flatnonzero(ws.y != "")
    cols, pipe, refit = fit_candidate(ws, rows, c, seed, inner_folds)
    settings = replace(st, names=tuple(ws.names[j] for j in cols), level=st.level if "dwt" in c.families else config.features.level,
                       fusion=c.fusion)
    params = {k: v for k, v in c.params.items() if k != "kbest"}
    if c.kind == "knn":
        params["n_neighbors"] = int(pipe[-1].n_neighbors)
    return Model(method, c.kind, params, [str(k) for k in pipe[-1].classes_], settings, fs, channels, pipe, fit_temperature(oof, y_idx), seed,
                 {}, "", refit)


def fit_model_novelty(model: Model, rows: FloatArray, labels: npt.NDArray[Any], groups: npt.NDArray[Any], score: str,
                      untaught: float = UNTAUGHT_SHARE) -> None:
    """Give ``model`` its novelty data: the novelty features (:meth:`~tactiled.learn.model.Model.novelty_features`) ``rows``
    (n, F'') of slides of surfaces ``labels`` and recordings ``groups`` (n,), standardised (a spectral shape, by its mean and
    standard deviation over these slides, floored at :data:`~tactiled.learn.model.SHAPE_SCALE_FLOOR`); the tests
    (:data:`NOVELTY_TESTS`; ``spectrum`` and ``far`` are stored as ``combined`` without its ratio threshold) and their
    thresholds (:func:`fit_novelty` at the share ``untaught`` of untaught slides, in ``summary``)."""
    if model.novelty_names is not None:
        model.novelty_center, model.novelty_scale = shape_standardisation(rows)
    z = model.novelty_standardise(rows)
    model.novelty_x, model.novelty_y, model.novelty_groups = z, labels, groups
    model.novelty_score = "combined" if score in ("far", "spectrum") else score
    model.novelty_threshold, info = fit_novelty(z, groups, labels, model.novelty_k, score=score, untaught=untaught)
    if score == "spectrum" and model.novelty_names is not None:  # the standardisation, too, without the surface left out
        info.update(unseen_flagged=left_out_flagged(rows, labels, groups, model.novelty_k), unseen_flagged_by="surface left out")
    scale = info.pop("surface_scale", None)
    model.novelty_surface_scale = np.asarray(scale, dtype=np.float64) if scale is not None else None
    far = info.get("distance_threshold")
    model.novelty_distance_threshold = float(far) if far is not None else math.inf
    model.summary = {**model.summary, "novelty": info}


def fit_calibration(oof: FloatArray, y_idx: npt.NDArray[np.intp]) -> tuple[float, FloatArray, dict[str, Any]]:
    """(temperature, knots (2, m), info): how a slide's confidence is computed from its scores.

    Temperature scaling on grouped out-of-fold slide scores ``oof`` (slides, K) against the true class ``y_idx``: the
    temperature T minimises the log loss of softmax(oof / T) (:func:`~tactiled.learn.model.fit_temperature`, no label
    smoothing), and the confidence is the top probability at T. The knots map it into [1/(n+2), 1 - 1/(n+2)], so that no
    slide is ever called certain. One parameter fitted on every class's probability, not two on the top one alone
    (Platt scaling, used before): on 21 training sets of the simulator's scenes its test-set ECE was lower on 16
    (docs/evaluation.md). Slides without a score are left out; with fewer than 10 left, or all of them right (or all
    wrong), the map is the constant (right + 1) / (n + 2), and T the label-smoothed one (it keeps the scores' spread for
    ``top`` and for the provisional labels' own calibration; unsmoothed, separable slides drive it to zero).
    """
    ok = (y_idx >= 0) & np.isfinite(oof).any(axis=1)
    right = (np.argmax(oof[ok], axis=1) == y_idx[ok]).astype(np.float64)
    n = len(right)
    lo, hi = 1.0 / (n + 2), 1.0 - 1.0 / (n + 2)
    grid = np.linspace(0.0, 1.0, 101)
    accuracy = float(right.mean()) if n else None
    if n < 10 or right.min() == right.max():
        value = np.full_like(grid, (right.sum() + 1.0) / (n + 2.0))
        return fit_temperature(oof, y_idx), np.vstack([grid, value]), {"method": "constant", "slides": n, "accuracy": accuracy}
    temperature = fit_temperature(oof, y_idx, smoothing=0.0)
    return temperature, np.vstack([grid, np.clip(grid, lo, hi)]), {"method": "temperature", "slides": n, "accuracy": accuracy,
                                                                    "temperature": temperature}


def calibrate(model: Model, oof: FloatArray, y_idx: npt.NDArray[np.intp]) -> None:
    """Give ``model`` its confidence: temperature and calibration map (:func:`fit_calibration`) fitted on its out-of-fold
    slide scores ``oof`` (slides, K) against ``y_idx``, recorded in ``summary["calibration"]``. An ensemble's members keep
    their own temperatures (label-smoothed: they weigh the members against each other)."""
    model.temperature, model.calibration, info = fit_calibration(oof, y_idx)
    model.summary = {**model.summary, "calibration": info}


def fit_early_calibration(ws: WindowSet, members: Sequence[tuple[Candidate, float]], outer: Sequence[tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]],
                          classes: list[str], temperature: float, seed: int, inner_folds: int = 3
                          ) -> tuple[tuple[float, float, float] | None, dict[str, Any]]:
    """(a, b, c) of :func:`~tactiled.learn.model.early_probability` for a model of ``members``, and what it was fitted on.

    ``members``: (candidate, its own temperature) of a single model, or of both members of an ensemble (their slide-prefix
    scores combined by :func:`~tactiled.learn.model.ensemble_scores`, as :class:`~tactiled.learn.model.Model` combines them);
    ``temperature`` softens the (combined) scores. In each outer fold (``outer``: train and test slide indices) every member is
    fitted on the train slides, and every test slide is classified from its first 1, 2, ... windows (``ws``: one row per
    window, every member's columns), as the pipeline does for provisional labels (the mean of those windows' scores, or of
    their features for a whole-slide member). A logistic fit of right or wrong on the logit of the top probability and the
    log of the window count gives the map. None when the folds give fewer than 20 prefixes or only right (or only wrong)
    ones; a fit in which a higher probability is not more often right keeps only the mean (a = b = 0).
    """
    from sklearn.linear_model import LogisticRegression

    index = {k: i for i, k in enumerate(classes)}
    tops: list[float] = []
    counts: list[int] = []
    right: list[bool] = []
    for train, test in outer:
        fitted = [_prefix_scorer(ws, c, train, index, seed, inner_folds) for c, _ in members]
        if any(f is None for f in fitted):
            continue
        for sl in test:
            label = ws.slides[sl].label
            w = _scored_rows(ws, np.array([sl]))
            if label not in index or not len(w):
                continue
            w = w[np.argsort(ws.spans[w, 0], kind="stable")]
            per = [f(ws.x[w]) for f in fitted if f is not None]
            scores = per[0] if len(per) == 1 else ensemble_scores(per[0], members[0][1], per[1], members[1][1])
            p = softmax(scores, temperature)
            tops += p.max(axis=1).tolist()
            counts += list(range(1, len(w) + 1))
            right += (np.argmax(p, axis=1) == index[label]).tolist()
    hit = np.array(right, dtype=np.float64)
    info: dict[str, Any] = {"prefixes": len(hit), "accuracy": float(hit.mean()) if len(hit) else None}
    if len(hit) < 20 or hit.min() == hit.max():
        return None, info
    x = np.column_stack([_logit(np.array(tops)), np.log(np.array(counts, dtype=np.float64))])
    fit = LogisticRegression(C=100.0).fit(x, hit)
    a, b = float(fit.coef_[0, 0]), float(fit.coef_[0, 1])
    coef = (a, b, float(fit.intercept_[0])) if a > 0 else (0.0, 0.0, float(_logit(np.array([hit.mean()]))[0]))
    return coef, {**info, "coef": list(coef)}


def _prefix_scorer(ws: WindowSet, c: Candidate, train: npt.NDArray[np.intp], index: dict[str, int], seed: int,
                   inner_folds: int) -> Callable[[FloatArray], FloatArray] | None:
    """Candidate ``c`` fitted on the slides ``train`` of ``ws`` (their mean features for a whole-slide candidate), as a function
    of one slide's windows' raw features (w, F) in time order to the scores (w, K) of its first 1, 2, ..., w windows (columns
    by ``index``; -inf for a class the fit never saw). None when the train slides hold fewer than two classes."""
    fit_on = ws.averaged() if c.fusion == "features" else ws
    rows = _window_rows(fit_on, train)
    if len(np.unique(fit_on.y[rows])) < 2:
        return None
    cols, pipe, _ = fit_candidate(fit_on, rows, c, seed, inner_folds)
    known = [index[str(k)] for k in pipe[-1].classes_]

    def prefixes(x: FloatArray) -> FloatArray:
        raw = prefix_fused(x[:, cols], lambda z: decision_scores(pipe[-1], pipe[:-1].transform(z)), c.fusion)
        scores = np.full((len(x), len(index)), -np.inf)
        scores[:, known] = raw
        return scores

    return prefixes


def _logit(q: FloatArray) -> FloatArray:
    """log(q / (1 - q)), q clipped to [1e-6, 1 - 1e-6] so that it stays finite."""
    q = np.clip(q, 1e-6, 1 - 1e-6)
    out: FloatArray = np.log(q / (1 - q))
    return out


def fit_novelty(z: FloatArray, files: npt.NDArray[Any], labels: npt.NDArray[Any], k: int, reject: float = 0.05,
                score: str = "ratio", untaught: float = UNTAUGHT_SHARE, count: bool = True) -> tuple[float, dict[str, Any]]:
    """The novelty threshold of training slides ``z`` (n, F') (standardised mean features), and what cross-validation says of it.

    Each slide's :func:`~tactiled.learn.model.novelty_parts` against the slides of *other recordings* stands for a
    new recording of a known surface; leaving each surface out in turn (its score against the slides of the other
    surfaces) stands for an untaught surface. The threshold (:func:`novelty_threshold`) calls at most ``reject`` of the
    known slides unknown and flags the untaught ones where that pays at the share ``untaught`` of untaught slides; ``info``
    says how many of each it does. A threshold of
    inf (never unknown) when no slide has another recording to compare with.

    ``spectrum``: only a threshold on the distance to the nearest surface (``info["distance_threshold"]``), the
    (1 - ``reject``) quantile of the known slides' distances (of the slides whose surface has another recording:
    :func:`spectrum_threshold`; none such, inf): at most ``reject`` of a new recording's slides of a known
    surface are called unknown (``count`` False: the threshold and scales without counting how many a new recording would
    have called unknown, ``info["known_rejected"]`` None). ``far``: ``combined`` without the ratio's threshold (inf), only
    the distance test below. ``combined``: the threshold is the ratio's, and ``info["distance_threshold"]`` a second one on the distance to the
    nearest surface (the ratio's numerator): the (1 - ``reject``) quantile of the left-out surfaces' distances, the
    distance from a taught slide to the nearest *other* surface (a step between taught surfaces), and never below the
    same quantile of the known slides' distances. A slide beyond it is farther from every taught surface than taught
    surfaces are from each other; a slide of another unit of the sensor or a new sheet of a known grade, whose shift is
    smaller than that step, is not. None (no distance gate) with fewer than two surfaces.
    """
    n = len(z)
    parts_of = "combined" if score in ("far", "spectrum") else score
    known = np.full((n, 2), np.nan)  # novelty_parts per slide: (score, distance to the nearest surface)
    unseen = np.full((n, 2), np.nan)
    surfaces = np.unique(labels)
    per_known = np.full((n, len(surfaces)), np.inf)  # spectrum: each slide's distance to every surface (other recordings)
    per_unseen = np.full((n, len(surfaces)), np.inf)  # ... and to every other surface
    for i in range(n):
        other_file, other_surface = files != files[i], labels != labels[i]
        for out, per, keep in ((known, per_known, other_file), (unseen, per_unseen, other_surface)):
            if not keep.any():
                continue
            if score == "spectrum":
                per[i, np.searchsorted(surfaces, np.unique(labels[keep]))] = surface_distances(z[i:i + 1], z[keep], labels[keep], k)[0]
                out[i] = (0.0, per[i].min())
            else:
                out[i] = novelty_parts(z[i:i + 1], z[keep], labels[keep], k, parts_of)[0]
    have, flagged = known[np.isfinite(known[:, 0])], unseen[np.isfinite(unseen[:, 0])]
    two = len(surfaces) < 3 and parts_of in ("ratio", "combined")  # a surface of two left out leaves one: no second-nearest, no ratio
    if two:
        flagged[:, 0] = 0.0  # the ratio tells nothing of an untaught surface here (its column held a plain distance)
    info: dict[str, Any] = {"k": k, "score": score, "untaught": untaught, "threshold": None, "known_rejected": None, "unseen_flagged": None}
    if parts_of == "combined":
        info["distance_threshold"] = None
    if not len(have):
        return math.inf, info
    threshold = math.inf if score in ("far", "spectrum") else max(novelty_threshold(have[:, 0], flagged[:, 0], reject, untaught), 1e-9)
    far = math.inf
    if score == "spectrum":
        far, scale = spectrum_threshold(per_known.min(axis=1), per_known, labels, reject)
        if not math.isfinite(far):  # no surface has two recordings: nothing to set a threshold by
            return math.inf, info
        info["distance_threshold"] = far
        info["surface_scale"] = scale.tolist()
        known[:, 1], unseen[:, 1] = (per_known / scale).min(axis=1), (per_unseen / scale).min(axis=1)  # each over its own scale
        have, flagged = known[np.isfinite(known[:, 0])], unseen[np.isfinite(unseen[:, 0])]
    elif parts_of == "combined" and len(flagged) and len(np.unique(labels)) >= 2:
        q = 1.0 - reject
        far = max(float(np.quantile(flagged[:, 1], q, method="higher")), float(np.quantile(have[:, 1], q, method="higher")), 1e-9)
        info["distance_threshold"] = far
    if score == "spectrum":  # its threshold and scales are fitted on the known slides: count each recording left out instead
        if count:
            info.update(known_rejected=held_out_rejected(z, files, labels, k, per_known, reject), known_rejected_by="recording left out")
    else:
        info.update(known_rejected=float(np.mean(over_thresholds(have, threshold, far) > 1.0)))
    measured = len(flagged) and not (two and not math.isfinite(far))  # with two surfaces, only a distance test is measured
    info.update(threshold=threshold if math.isfinite(threshold) else None,
                unseen_flagged=float(np.mean(over_thresholds(flagged, threshold, far) > 1.0)) if measured else None)
    return threshold, info


def shape_standardisation(rows: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(center, scale) (F'',) of spectral shapes ``rows`` (n, F''): their mean and standard deviation, the latter floored at
    :data:`~tactiled.learn.model.SHAPE_SCALE_FLOOR` (a constant feature divides by the floor, not by 0)."""
    return rows.mean(axis=0), np.maximum(rows.std(axis=0), SHAPE_SCALE_FLOOR)


def left_out_flagged(rows: FloatArray, labels: npt.NDArray[Any], files: npt.NDArray[Any], k: int, reject: float = 0.05) -> float | None:
    """The share of the slides of a surface left out of training that ``spectrum``'s test calls unknown, each surface left
    out in turn of everything the test is fitted on: the standardisation of the spectral shapes ``rows`` (n, F'') (mean and
    standard deviation over the other surfaces' slides, floored at :data:`~tactiled.learn.model.SHAPE_SCALE_FLOOR`), the
    distance threshold and each taught surface's own scale (:func:`fit_novelty` on the other surfaces' slides); its slides
    are then measured against the other surfaces' as a new slide is. None when no surface can be tested (fewer than two
    surfaces, or no other surface with two recordings to set a threshold)."""
    flagged = counted = 0
    for surface in np.unique(labels):
        out = labels == surface
        rest = ~out
        if not rest.any():
            continue
        center, spread = shape_standardisation(rows[rest])
        z = (rows - center) / spread
        per_known = other_recording_distances(z[rest], files[rest], labels[rest], k)
        far, scale = spectrum_threshold(per_known.min(axis=1), per_known, labels[rest], reject)
        if not math.isfinite(far):
            continue  # no taught surface has a second recording: nothing would be called unknown
        per = surface_distances(z[out], z[rest], labels[rest], k) / scale
        flagged += int(np.count_nonzero(per.min(axis=1) / far > 1.0))
        counted += int(out.sum())
    return flagged / counted if counted else None


def other_recording_distances(z: FloatArray, files: npt.NDArray[Any], labels: npt.NDArray[Any], k: int) -> FloatArray:
    """(n, S) each slide's mean distance to the ``k`` nearest slides of each surface (sorted) among the *other* recordings'
    (fewer where the surface has fewer; inf where it has none): :func:`fit_novelty`'s ``per_known`` for ``spectrum``, all
    slides at once (to rounding: one matrix product)."""
    surfaces, which = np.unique(labels, return_inverse=True)
    which = which.reshape(-1)
    d = pairwise_distances(z, z)
    d[files[:, None] == files[None, :]] = np.inf
    out = np.full((len(z), len(surfaces)), np.inf)
    for j in range(len(surfaces)):
        near = np.sort(d[:, which == j], axis=1)[:, :k]
        out[:, j] = _first_k_mean(near[:, None, :], np.isfinite(near)[:, None, :], k)[:, 0]
    return out


def spectrum_threshold(nearest: FloatArray, per_known: FloatArray, labels: npt.NDArray[Any], reject: float,
                       surfaces: npt.NDArray[Any] | None = None) -> tuple[float, FloatArray]:
    """(distance threshold, each surface's own scale (S,)) of ``spectrum``'s test from the known slides' distances: ``nearest``
    (n,) to the nearest surface (inf: none to compare with, left out) and ``per_known`` (n, S) to every surface (surfaces
    ``labels``; ``surfaces`` as :func:`own_scales`): the (1 - ``reject``) quantile of the nearest distances of the slides
    whose own surface has another recording (a finite distance to it in ``per_known``; at least 1e-9), and
    :func:`own_scales` over it. (inf, ones (S,)) when no slide's surface has another recording.

    A slide whose surface no other recording holds stands for an untaught surface, not a new recording of a taught one: its
    nearest surface is another, far one, and counting it would loosen the test for every surface (one 6-slide recording of
    a grating enrolled into a model of 8 hand-scene grades took the threshold from 5.68 to 11.59)."""
    if surfaces is None:
        surfaces = np.unique(labels)
    own = per_known[np.arange(len(labels)), np.searchsorted(surfaces, labels)]
    counted = nearest[np.isfinite(nearest) & np.isfinite(own)]
    if not len(counted):
        return math.inf, np.ones(len(surfaces))
    far = max(float(np.quantile(counted, 1.0 - reject, method="higher")), 1e-9)
    return far, own_scales(per_known, labels, far, reject, surfaces)


def held_out_rejected(z: FloatArray, files: npt.NDArray[Any], labels: npt.NDArray[Any], k: int, per_known: FloatArray,
                      reject: float = 0.05) -> float | None:
    """The share of slides of a new recording of a taught surface that ``spectrum``'s test calls unknown, by leaving each
    recording out in turn: its slides (``z`` (n, F') of recordings ``files`` and surfaces ``labels``) against the distance
    threshold and own scales (:func:`own_scales`) fitted, as :func:`fit_novelty` fits them, on the other recordings alone.
    ``per_known`` (n, S): each slide's distance to every surface's slides of the other recordings (:func:`fit_novelty`'s).
    A slide whose surface no other recording holds is not counted (it would be an untaught surface). None when no slide
    can be counted.

    Counting the slides the threshold was fitted on (each surface's own scale is the 95 % quantile of its own slides'
    distances: with fewer than 20 slides, their largest) called none of them unknown, whatever a new recording does."""
    surfaces, which = np.unique(labels, return_inverse=True)
    which = which.reshape(-1)
    d = pairwise_distances(z, z)
    d[files[:, None] == files[None, :]] = np.inf  # a slide is measured against other recordings only
    # per surface, each slide's nearest slides of it (enough that k stay once any one recording's are taken away), and their recordings
    top = k + max(Counter(zip(files.tolist(), labels.tolist(), strict=True)).values())
    dist = np.full((len(z), len(surfaces), top), np.inf)
    of = np.full((len(z), len(surfaces), top), -1, dtype=np.int64)
    code = np.unique(files, return_inverse=True)[1].reshape(-1)  # recordings numbered 0..R-1
    for j in range(len(surfaces)):
        cols = np.flatnonzero(which == j)
        order = np.argsort(d[:, cols], axis=1, kind="stable")[:, :top]
        dist[:, j, :order.shape[1]] = np.take_along_axis(d[:, cols], order, axis=1)
        of[:, j, :order.shape[1]] = code[cols][order]
    base = _first_k_mean(dist, np.isfinite(dist), k)  # (n, S): per_known's distances, from these lists
    # the (slide, surface) pairs whose k nearest hold a slide of recording r: only they change when r is left out
    row, col, pos = np.nonzero((of[:, :, :k] >= 0) & np.isfinite(dist[:, :, :k]))
    rec = of[row, col, pos]
    by = np.argsort(rec, kind="stable")
    cuts = np.flatnonzero(np.diff(rec[by])) + 1
    touched = {int(rec[g[0]]): np.unique(np.stack([row[g], col[g]], axis=1), axis=0) for g in np.split(by, cuts) if len(g)}
    rejected = counted = 0
    for r in range(int(code.max()) + 1):
        rest = code != r
        held = ~rest
        own = per_known[np.flatnonzero(held), which[held]]
        taught = np.isfinite(own)
        if not taught.any():
            continue
        per = base.copy()  # as per_known, of the other recordings' slides without r
        pairs = touched.get(r)
        if pairs is not None and len(pairs):
            a, b = pairs[:, 0], pairs[:, 1]
            per[a, b] = _first_k_mean(dist[a, b][:, None, :], ((of[a, b] != r) & np.isfinite(dist[a, b]))[:, None, :], k)[:, 0]
        per = per[rest]
        far, scale = spectrum_threshold(per.min(axis=1), per, labels[rest], reject, surfaces)
        if not math.isfinite(far):
            continue  # no surface of the other recordings has a second one to fit a threshold on: nothing would be called unknown
        beyond = (per_known[held] / scale).min(axis=1) / far > 1.0
        rejected += int(beyond[taught].sum())
        counted += int(taught.sum())
    return rejected / counted if counted else None


def _first_k_mean(dist: FloatArray, use: npt.NDArray[np.bool_], k: int) -> FloatArray:
    """(..., S) the mean of the first ``k`` of each sorted row of ``dist`` (..., S, m) that ``use`` allows; inf where none."""
    use = use & (np.cumsum(use, axis=-1) <= k)
    n = use.sum(axis=-1)
    out: FloatArray = np.where(n > 0, np.where(use, dist, 0.0).sum(axis=-1) / np.maximum(n, 1), np.inf)
    return out


def own_scales(per_known: FloatArray, labels: npt.NDArray[Any], threshold: float, reject: float = 0.05,
               surfaces: npt.NDArray[Any] | None = None) -> FloatArray:
    """(S,) each surface's own distance scale (surfaces sorted), at least 1: the (1 - ``reject``) quantile of the distances
    from each of its slides to its *own* other recordings' slides (``per_known`` (n, S): each slide's distance to every
    surface's slides of other recordings, inf where there are none), over ``threshold``.
    A surface whose recordings lie farther apart than the threshold (a grating whose lines move with the sliding speed, a
    surface taught from a few one-slide recordings) is measured on its own scale, so that a new recording of it is not
    called unknown for being as far from the others as they are from each other. 1 for a surface of one recording.
    ``surfaces``: the columns of ``per_known`` (sorted; default: those of ``labels``), a superset of ``labels``' surfaces."""
    if surfaces is None:
        surfaces, which = np.unique(labels, return_inverse=True)
        which = which.reshape(-1)
    else:
        which = np.searchsorted(surfaces, labels)
    own = per_known[np.arange(len(labels)), which]
    out = np.ones(len(surfaces))
    for j in range(len(surfaces)):
        mine = own[(which == j) & np.isfinite(own)]
        if len(mine):
            out[j] = max(float(np.quantile(mine, 1.0 - reject, method="higher")) / threshold, 1.0)
    return out


def novelty_threshold(known: FloatArray, unseen: FloatArray, reject: float = 0.05, untaught: float = UNTAUGHT_SHARE) -> float:
    """The threshold on novelty scores (a score above it: unknown) from known slides' scores (m,) and untaught ones' (u,).

    Of the thresholds that call at most ``reject`` of the known slides unknown, the one with the most to gain: untaught
    slides caught, weighed by ``untaught`` (the share of slides expected on untaught surfaces, :data:`UNTAUGHT_SHARE`), less
    known slides rejected, weighed by 1 - ``untaught`` (0.5: Youden's J, both alike); placed in the middle of the gap between the two scores around it:
    where the known and untaught scores are far apart (surfaces easy to tell apart) a slide may move half the gap
    (another unit of the sensor) before it is called unknown, rather than being rejected at the edge of the training
    spread. When no threshold gains anything (cross-validation says the score tells untaught surfaces from known ones no
    better than it costs known slides), inf: the score flags nothing. Without untaught scores, the (1 - ``reject``) quantile.
    """
    cap = float(np.quantile(known, 1.0 - reject, method="higher"))
    if not len(unseen):
        return cap
    points = np.unique(np.concatenate([known, unseen]))
    cuts = np.append((points[:-1] + points[1:]) / 2.0, points[-1])  # between consecutive scores, and at the highest (nothing seen flagged)
    cuts = cuts[cuts >= cap] if np.any(cuts >= cap) else cuts[-1:]
    gain = untaught * (unseen[None, :] > cuts[:, None]).mean(axis=1) - (1.0 - untaught) * (known[None, :] > cuts[:, None]).mean(axis=1)
    best = int(np.argmax(gain))
    return float(cuts[best]) if gain[best] > 0 else math.inf


def complexity(c: Candidate) -> tuple[int, int, int]:
    """How much a candidate can fit, for :func:`choose` (smaller: simpler).

    Classifier first (a linear model, an RBF SVM, kNN, an ELM, forward selection on top), then how many
    feature families and whether features are picked by score, then per-window fusion over a whole-slide mean
    (one row per slide averages the noise out before fitting).
    """
    return KIND_RANK[c.kind] + 2 * c.sfs, len(c.families) + (c.kbest > 0), int(c.fusion != "features")


def choose(candidates: Sequence[Candidate], folds: Sequence[Sequence[float]], stressed: Sequence[Sequence[float]] | None = None,
           slides: int = 0) -> int:
    """Index of the candidate to keep, from each candidate's accuracy per fold (the one-standard-error rule).

    The best mean accuracy sets the bar: its mean less one standard error (sd over folds / sqrt(folds)).
    Of the candidates at or above the bar, the simplest (:func:`complexity`) wins; among equally simple
    ones, the better mean, then the earlier in the list. With few recordings the top candidates are often
    within noise of each other, and the simpler one is the safer bet on new data (Hastie, Tibshirani and
    Friedman, The Elements of Statistical Learning, 2nd ed., section 7.10). ``stressed`` (``train --gain-tolerance``):
    each candidate's accuracy per fold under another film gain; of the candidates at or above the bar, those within one
    standard error of the best of them under it go on to the simplest. ``slides``: the slides the folds scored in all
    (:func:`within_one_se`'s floor on the standard error).
    """
    means = [float(np.mean(f)) if len(f) else 0.0 for f in folds]
    kept = within_one_se(folds, slides)
    if stressed is not None:
        kept = [kept[j] for j in within_one_se([stressed[i] for i in kept], slides)]
    return min(kept, key=lambda i: (complexity(candidates[i]), -means[i], i))


def within_one_se(folds: Sequence[Sequence[float]], slides: int = 0) -> list[int]:
    """Indices of the candidates whose mean accuracy is at or above the best mean less its standard error (in order).
    ``slides``: how many slides the folds scored in all; the standard error is then at least a proportion's over them,
    sqrt(p (1 - p) / slides): two or three folds that happen to agree (96.0 ± 0.0 %) do not make the best mean certain."""
    means = np.array([np.mean(f) if len(f) else 0.0 for f in folds])
    top = int(np.argmax(means))
    p = float(means[top])
    floor = math.sqrt(max(p * (1.0 - p), 0.0) / slides) if slides > 0 else 0.0
    bar = means[top] - max(standard_error(folds[top]), floor)
    return [i for i in range(len(folds)) if means[i] >= bar - 1e-12]


def standard_error(folds: Sequence[float]) -> float:
    """Standard error of the mean of per-fold accuracies: sd (ddof 1) / sqrt(folds); 0 for fewer than two folds."""
    n = len(folds)
    return float(np.std(folds, ddof=1)) / np.sqrt(n) if n > 1 else 0.0


def _counts(ws: WindowSet) -> dict[str, Any]:
    c = ws.counts
    return {"truth": c.truth, "detected": c.detected, "missed": sum(c.missed.values()), "missed_by_file": c.missed,
            "false": sum(c.false.values())}


def _inner_folds(ws: WindowSet, train: npt.NDArray[np.intp], n: int,
                 seed: int) -> tuple[str, list[tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]]]:
    """(how, folds): :func:`grouped_splits` of the slides ``train`` (indices into ws.slides), as indices into ws.slides,
    grouped by ``file``; by ``slide`` where a surface has a single file among them (an outer fold of surfaces recorded
    twice: folds grouped by file would test that file with nothing of its surface to train on, every candidate would score
    nothing, and the choice would fall to the simplest whatever it scores); ``none`` (no folds, no inner choice) where a
    surface has a single slide there (:func:`coarsest_testable`)."""
    labels = ws.slide_labels()[train]
    groupings = [np.array([ws.slides[i].file for i in train]), train]
    k = coarsest_testable(labels, groupings)
    if k is None:
        return "none", []
    return ("file", "slide")[k], [(train[a], train[b]) for a, b in grouped_splits(labels, groupings[k], n, seed)]


def coarsest_testable(y: npt.NDArray[Any], groupings: Sequence[npt.NDArray[Any]]) -> int | None:
    """Index of the first of ``groupings`` (each (n,), coarsest first) in which every labelled class of ``y`` (n,) has two
    groups or more, so that grouped folds can test each class on a group they did not train on; None if none does."""
    return next((k for k, g in enumerate(groupings) if fewest_groups(y, g) >= 2), None)


def _run_with_progress(tasks: list[tuple[Callable[..., Any], tuple[Any, ...]]], say: Progress, scheduler: str | None,
                       first: Sequence[bool] | None = None, units: Sequence[int] | None = None, unit: str = "fits") -> list[Any]:
    """Results of ``tasks`` in order; the ``first`` ones are started first (the slowest).

    Progress counts ``units`` (per task; default one each) as tasks finish, with the time elapsed and an
    estimate of the time left: the time per unit since the first task finished, times the units left (from the start,
    the workers' start-up counted as work: the first estimate ran 5 to 50 times too long).
    """
    from joblib import Parallel, delayed

    order = sorted(range(len(tasks)), key=lambda i: not (first[i] if first is not None else False))
    weight = list(units) if units is not None else [1] * len(tasks)
    total = max(1, sum(weight))
    out: list[Any] = [None] * len(tasks)
    step = max(1, len(tasks) // 20)
    t0 = time.perf_counter()
    with parallel_backend(scheduler):
        results = Parallel(return_as="generator")(delayed(tasks[i][0])(*tasks[i][1]) for i in order)
        done_units = 0
        first_at, first_units = 0.0, 0  # when the first task finished, and its units: the rate is measured from there
        for done, (i, result) in enumerate(zip(order, results, strict=True), 1):
            out[i] = result
            done_units += weight[i]
            now = time.perf_counter()
            if done == 1:
                first_at, first_units = now, done_units
            if done % step == 0 or done == len(tasks):
                since = done_units - first_units
                left = f", about {_clock((now - first_at) / since * (total - done_units))} left" if since and done_units < total else ""
                say(f"[{'#' * round(20 * done_units / total):<20s}] {done_units}/{total} {unit}, {_clock(now - t0)} elapsed{left}")
    return out


def _clock(seconds: float) -> str:
    """``m:ss`` of a duration in seconds."""
    m, s = divmod(round(seconds), 60)
    return f"{m}:{s:02d}"


# ---- the papers' method ----------------------------------------------------------------------------------------------------


def sfs_columns(ws: WindowSet, rows: npt.NDArray[np.intp], seed: int, inner_folds: int = 3, n_features: int | str = "auto",
                pool: int = 0, tol: float = 0.005) -> list[int]:
    """Forward selection (ELM criterion, grouped CV) on the windows ``rows``: the rule of scikit-learn's
    SequentialFeatureSelector (each step adds the column whose CV accuracy, mean over the folds, is highest, the first of
    equals; "auto" stops when that gains less than ``tol``), written as a loop of plain fits and predictions because its
    ``cross_val_score`` per candidate spent about three quarters of the time validating inputs and scoring (a test checks that both
    choose the same columns).

    ``n_features`` "auto": add features while the CV accuracy rises by at least ``tol``. Folds grouped by file; by slide
    where a surface has a single file among ``rows`` (as :func:`_inner_folds`), by window where it has a single slide.
    Constant columns are never candidates. ``pool`` > 0: only the ``pool`` columns with the largest
    ANOVA F on ``rows`` are candidates (a cheaper search; every step costs one CV per candidate).
    Returns column indices into ``ws.names``.
    """
    import sklearn
    from sklearn.pipeline import Pipeline
    from sklearn.preprocessing import StandardScaler

    from tactiled.learn.elm import ELMClassifier
    from tactiled.learn.model import LogFeatures, anova_f

    x, y = ws.x[rows], ws.y[rows]
    # by file; where a surface has one file here (an outer fold's training part) by slide, as _inner_folds; where it has one
    # slide, by window (optimistic, but the features are still ranked on held-out rows)
    groupings = [ws.groups[rows], ws.slide[rows], np.arange(len(rows))]
    k = coarsest_testable(y, groupings)
    cv = grouped_splits(y, groupings[-1 if k is None else k], inner_folds, seed)
    z = Pipeline([("log", LogFeatures(tuple(ws.names))), ("scale", StandardScaler())]).fit_transform(x)
    varying = np.flatnonzero(np.ptp(z, axis=0) > 1e-12)
    if 0 < pool < len(varying) and len(np.unique(y)) > 1:
        f_stat = np.nan_to_num(anova_f(z[:, varying], y)[0], nan=0.0, posinf=np.finfo(np.float64).max)
        varying = np.sort(varying[np.argsort(-f_stat, kind="stable")[:pool]])
    if len(varying) == 0:
        raise ValueError("forward selection: every feature is constant on these windows")
    zv = z[:, varying]
    elm = ELMClassifier(n_hidden=50, calibrate=False, random_state=seed)

    def accuracy(cols: list[int]) -> float:
        """Mean over the folds of the accuracy of an ELM on the columns ``cols`` (in ascending order, as the selector's mask)."""
        return float(np.mean([np.mean(elm.fit(zv[tr][:, cols], y[tr]).predict(zv[te][:, cols]) == y[te]) for tr, te in cv]))

    steps = len(varying) - 1 if n_features == "auto" else min(int(n_features), len(varying) - 1)
    chosen: list[int] = []
    last = -np.inf
    with sklearn.config_context(assume_finite=True):  # z is finite: a scaled log of finite features
        for _ in range(steps):
            scores = {j: accuracy(sorted([*chosen, j])) for j in range(len(varying)) if j not in chosen}
            best = max(scores, key=scores.__getitem__)
            if n_features == "auto" and scores[best] - last < tol:
                break
            last = scores[best]
            chosen.append(best)
    return [int(varying[j]) for j in sorted(chosen)]


def window_oof(ws: WindowSet, cols: npt.NDArray[np.intp], kind: str, params: dict[str, Any],
               folds: list[tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]], classes: list[str], seed: int) -> FloatArray:
    """Out-of-fold scores (w, K) of every window, each from the fold model that did not see its slide (-inf: class unseen)."""
    out = np.full((len(ws.y), len(classes)), -np.inf)
    index = {c: i for i, c in enumerate(classes)}
    for train, test in folds:
        tr, te = _window_rows(ws, train), _scored_rows(ws, test)
        if len(np.unique(ws.y[tr])) < 2 or not len(te):
            continue
        pipe, _ = fit_pipeline(ws.x[tr][:, cols], ws.y[tr], [ws.names[j] for j in cols], kind, params, seed)
        raw = decision_scores(pipe[-1], pipe[:-1].transform(ws.x[te][:, cols]))
        for j, c in enumerate(pipe[-1].classes_):
            out[te, index[str(c)]] = raw[:, j]
    return out


def paper(recs: Sequence[tuple[str, Recording]], config: Config, *, folds: int = 5, inner_folds: int = 3, seed: int = 0,
          progress: Progress | None = None, scheduler: str | None = None,
          found: tuple[list[list[LabelledSlide]], SlideCounts] | None = None, novelty: str = NOVELTY_DEFAULT,
          untaught: float = UNTAUGHT_SHARE, check_usable: Callable[[UsableTable], Collection[str]] | None = None,
          group_by: str = "file", gain: float = GAIN_DEFAULT) -> SearchResult:
    """The papers' DWT + SFS + ELM (:data:`PAPER`), cross-validated the same way as :func:`search`, then fitted on everything
    (``gain``: its accuracy under another film gain, reported; one candidate, nothing to choose)."""
    return search(recs, config, folds=folds, inner_folds=inner_folds, seed=seed, candidates=[PAPER], progress=progress, scheduler=scheduler,
                  found=found, method="paper", novelty=novelty, untaught=untaught, speed=0.0, check_usable=check_usable, group_by=group_by,
                  gain=gain)
