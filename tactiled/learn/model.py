"""Models: a scikit-learn pipeline over window features, and its files (``.npz`` + JSON; never pickle).

A model classifies windows of a slide and combines them (:meth:`Model.fuse`):

    raw features (n, F) ─▶ log10 of scale features ─▶ StandardScaler ─▶ classifier ─▶ scores (n, K)
    slide: mean of its windows' scores (or the scores of the mean of their features) ─▶ softmax(· / temperature) ─▶ probabilities (K,)

An *ensemble* (format 7; ``tactiled train --ensemble``) has a second member, :attr:`Model.partner`, the plain spectral
classifier (whole-slide mean of log band energies, log centroid and kurtosis; RBF SVM), beside the candidate the search
chose. One analysis computes both members' features (``settings.names`` is their union); each member takes its own
columns (``Model.member_names``, ``partner.names``) and fuses them its own way, and the slide's probabilities are

    softmax((log softmax(first's slide scores / T1) + log softmax(partner's slide scores / T2)) / T)

(:func:`ensemble_scores`): the normalised product of the members' probabilities, each softened by its own temperature
(``Model.member_temperature``, ``partner.temperature``), over the ensemble's temperature ``temperature``. T, the
confidence calibration and the provisional labels' calibration are fitted on the ensemble's out-of-fold scores; the
novelty data are the first member's (its standardised slide-mean features).

``pipeline`` is a real :class:`sklearn.pipeline.Pipeline` (steps ``log``, ``scale``,
``clf``), so scikit-learn's tools work on it. The classifier is one of ``elm`` (the
papers' extreme learning machine), ``knn``, ``svm`` (RBF) or ``linear`` (L2-regularised
multinomial logistic regression). Scores are the classifier's decision values (log
probabilities for kNN); ``temperature`` is fitted on out-of-fold slides in training so
that a slide's confidence is calibrated.

A slide's label comes with two numbers (:meth:`Model.assess`): ``confidence``, the probability that the label is
right, a monotone map (``calibration``) of the top softmax probability. Training fits ``temperature`` on grouped
out-of-fold slides by temperature scaling and makes the map the top probability itself, kept within [1/(n+2),
1 - 1/(n+2)] (``summary["calibration"]["method"]`` is ``temperature``); older models hold a Platt or isotonic map over a
label-smoothed temperature, and still load. A provisional label's confidence, from the first windows of a slide, is
:func:`early_probability` of the top probability and the number of windows (``early_calibration``, fitted on out-of-fold
prefixes of slides, format 5), kept within the final map's range (:meth:`Model.early_bounds`). The second number is ``novelty``, a score of the slide
(the mean of its windows' features, standardised as the classifier sees them) against the training slides
(:func:`novelty_parts`), divided by the threshold that grouped cross-validation set so that at most 5 % of slides
of known surfaces exceed it: above 1, the slide is unlike every surface the model was taught. From format 5 on the
score is the nearest-neighbour distance *ratio* (the distance to the nearest surface over the distance to the next
one), which a shift of the whole feature space (another unit of the sensor, a new sheet of the same grade) moves far
less than it moves plain distances; format 3 and 4 files keep the plain distance they were fitted with. From format 6
on, the score may be ``combined``: the ratio over its threshold or the distance to the nearest surface over a
distance threshold (``novelty.distance_threshold``, the distance beyond which a slide is farther from every taught
surface than taught surfaces are from one another), whichever is larger, so that a surface far from every taught
one is flagged even where one taught surface is much nearer than the next (a small ratio).

File arrays: ``header`` (0-d unicode, JSON), ``classes`` (K,) unicode, ``scaler_mean`` and
``scaler_scale`` (F,); per classifier: elm ``weights`` (F, L), ``biases`` (L,), ``beta``
(L, K'), ``elm_temperature`` (); linear ``coef`` (K'', F), ``intercept`` (K'',); knn and
svm ``train_x`` (n, F) standardised and ``train_y`` (n,) (both deterministic, refit at
load; at most :data:`MAX_REFIT_ROWS` rows so a load never hangs); svm also the fitted
``svm_support``, ``svm_dual_coef``, ``svm_intercept``, ``svm_n_support``, ``svm_gamma``; from format 3 on, every
model also has ``calibration`` (2, m) knots (top probability, P(right)), both nondecreasing in [0, 1], and
``novelty_x`` (n, F') the standardised mean features of its n training slides; from format 4 on, every model
also keeps ``train_x`` (n, F) and ``train_y`` (n,) (the standardised rows its classifier was fitted on) and
``novelty_y`` and ``novelty_groups`` (n,) (each novelty row's surface and recording), which ``tactiled enrol`` refits on
(optional: :mod:`tactiled.learn.infer` evaluates the model with numpy alone, no refit, no
scikit-learn import; ``load_model(lean=False)`` takes the scikit-learn path; an svm that
must be refit at load has at most :data:`MAX_SVM_REFIT_ROWS` rows). Only the arrays of the
file's classifier are read, at most :data:`MAX_MODEL_BYTES` inflated. The header carries the
format and its version, the method, the classifier and its parameters, the analysis
settings (windows, spikes, feature names), fs, channels, temperature, ``novelty`` (``k`` and
``threshold``; format 3; ``score``, format 5; ``distance_threshold``, format 6), a training summary
(including the cross-validated accuracy), and ``fingerprint``: the SHA-256 (first 16 hex
digits) of the header without it and of every array's bytes. Loading checks all of it (types,
ranges, shapes, and that the stream's channels hold the features), runs a probe (one window of
synthetic noise through the whole analysis and the classifier, which must give a finite
probability), and refuses anything wrong with one line naming file and part: a model that
loads cannot crash the daemon at the first slide.

Format 8 (``train``'s default unknown-surface test, ``spectrum``): the novelty reads the shape of the slide's spectrum,
not the classifier's features. ``header.novelty.inputs`` names psd columns of ``settings.names`` (computed by the one
analysis whatever the classifier reads); a slide's novelty features are
:func:`~tactiled.core.features.spectral_shape` of their slide means (per channel, log10 band powers less their mean),
standardised by the arrays ``novelty_center`` and ``novelty_scale`` (B,); ``novelty_x`` (n, B) holds the training
slides' so; ``novelty_surface_scale`` (S,) >= 1 divides each surface's distances (its surfaces in sorted order): a
surface whose own recordings lie farther apart than the threshold is measured on its own scale.
``header.novelty.prefix`` lists the distance thresholds of slides of 1, 2, ... windows (a whole slide of that many, or a
provisional label from a slide's first ones), as multiples (>= 1) of the whole training slides' one (the last one holds
beyond them; empty: that one).
``header.inputs`` names the classifier's own columns (an ensemble's first member's are
``header.ensemble.member.names``, as in format 7); ``settings.names`` is the union of every part's columns.

Format 7 (an ensemble; a model of one classifier is still written as format 6, byte for byte as before): the header's
``settings.names`` are both members' features and ``ensemble`` holds ``member`` (``names``: the first classifier's
columns, whose F' sizes ``scaler_*``, ``train_x`` and ``novelty_x``; ``temperature``: T1) and ``partner`` (``method``,
``classifier``, ``params``, ``names``, ``fusion``, ``temperature``: T2); the partner's arrays are those of a model of its
classifier (``classes``, ``scaler_mean``, ``scaler_scale``, the classifier's, ``train_x``, ``train_y``) under the prefix
``partner_`` (:data:`PARTNER`), checked as the first member's are and named with the prefix in errors. Formats 2 to 6
load as they did.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from tactiled.core.analysis import Analyser, AnalysisSettings
from tactiled.core.detect import FRONT_END_KEYS
from tactiled.core.features import FeaturePlan, classifier_inputs, name_family, raw_features, row_dots, rowwise_matmul, spectral_shape
from tactiled.errors import ModelError
from tactiled.files.npzio import NpzError, NpzReader, load_json_bounded
from tactiled.files.recording import atomic_savez, surface_name_problem
from tactiled.learn.infer import SVM_ARRAYS, LeanPipeline, lean_pipeline, log_proba, pair_matrices, pairwise_scores, pm_half, svm_arrays
from tactiled.readable import MISSING

FORMAT = "tactiled-model"
FORMAT_VERSION = 8  # written for a model whose novelty reads the slide's spectral shape (:attr:`Model.novelty_names`), with or without a partner
ENSEMBLE_VERSION = 7  # an ensemble (a second member, :attr:`Model.partner`) whose novelty reads its first member's features
SINGLE_VERSION = 6  # a single classifier whose novelty reads its own features
READ_VERSIONS = (2, 3, 4, 5, 6, 7, 8)  # format 2 (before calibration and novelty) still loads: confidence uncalibrated, novelty None; 3: no enrolment
TRUST_ARRAYS = ("calibration", "novelty_x")
SHAPE_ARRAYS = ("novelty_center", "novelty_scale", "novelty_surface_scale")  # format 8: the spectral shapes' standardisation, each surface's own distance scale
SHAPE_SCALE_FLOOR = 0.01  # log10 units (0.1 dB): a band level no slide moved is not a ruler that calls every new slide far
ENROL_ARRAYS = ("train_x", "train_y", "novelty_y", "novelty_groups")  # format 4: what tactiled enrol refits on
CLASSIFIERS = ("elm", "knn", "svm", "linear")
MAX_REFIT_ROWS = 20_000
MAX_SVM_REFIT_ROWS = 4000  # an RBF SVM refit at load (a file without its fitted SVM, or lean=False): 4000 rows of noise take ~2 s, 20 000 minutes
MAX_FEATURES = 4096
MAX_MODEL_BYTES = 256 << 20  # all arrays of a model file, inflated
MAX_WINDOW_SAMPLES = 1 << 20  # an analysis window: 52 s at 20 kHz
ARRAYS = {"elm": ("weights", "biases", "beta", "elm_temperature"), "linear": ("coef", "intercept"), "knn": ("train_x", "train_y"),
          "svm": ("train_x", "train_y")}
PARTNER = "partner_"  # format 7: the prefix of the second member's arrays (its classes, scaler, classifier and training rows)
FloatArray = npt.NDArray[np.float64]
SurfaceGroups = tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]  # surface_groups: (columns (S, m), counts (S,))


def default_model_path() -> Path:
    """The model shipped in the package."""
    return Path(str(resources.files("tactiled") / "data" / "default_model.npz"))


def make_classifier(kind: str, params: dict[str, Any], seed: int = 0) -> Any:
    """A fresh scikit-learn estimator of ``kind`` (elm, knn, svm, linear) with ``params``."""
    if kind == "elm":
        from tactiled.learn.elm import ELMClassifier

        return ELMClassifier(n_hidden=int(params.get("n_hidden", 200)), alpha=float(params.get("alpha", 1e-6)), random_state=seed,
                             init=str(params.get("init", "hpelm")), calibrate=bool(params.get("calibrate", False)))
    if kind == "knn":
        from sklearn.neighbors import KNeighborsClassifier

        return KNeighborsClassifier(n_neighbors=int(params.get("n_neighbors", 9)))
    if kind == "svm":
        from sklearn.svm import SVC

        return SVC(kernel=str(params.get("kernel", "rbf")), C=float(params.get("C", 10.0)), gamma=params.get("gamma", "scale"), random_state=seed,
                   class_weight=params.get("class_weight"))
    if kind == "linear":
        from sklearn.linear_model import LogisticRegression

        return LogisticRegression(C=float(params.get("C", 1.0)), max_iter=int(params.get("max_iter", 1000)), class_weight=params.get("class_weight"))
    raise ModelError(f"unknown classifier {kind!r}; choose one of {', '.join(CLASSIFIERS)}")


class LogFeatures:
    """The pipeline's first step: :func:`tactiled.core.features.classifier_inputs` for ``names`` (stateless)."""

    def __init__(self, names: tuple[str, ...] | list[str] = ()) -> None:
        self.names = names

    def fit(self, x: Any, y: Any = None) -> LogFeatures:
        """Nothing to learn; returns self."""
        return self

    def transform(self, x: Any) -> FloatArray:
        """Classifier inputs (n, F) of raw features x (n, F): log10 of the scale features (:func:`classifier_inputs`)."""
        return classifier_inputs(np.asarray(x, dtype=np.float64), list(self.names))

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """``{"names": names}``, the step's only parameter (scikit-learn's contract)."""
        return {"names": self.names}

    def set_params(self, **params: Any) -> LogFeatures:
        """Set ``names`` if given; returns self (scikit-learn's contract)."""
        self.names = params.get("names", self.names)
        return self


def anova_f(x: Any, y: Any) -> tuple[FloatArray, FloatArray]:
    """scikit-learn's ``f_classif`` (ANOVA F and p-values of each column of x (n, F) against labels y (n,)) without its
    warnings in ``train``'s output: a fold with one row per class (no within-class degrees of freedom) or a constant
    column (a band empty in a fold) gives NaN, which the callers rank last."""
    import warnings

    from sklearn.feature_selection import f_classif

    with np.errstate(divide="ignore", invalid="ignore"), warnings.catch_warnings():
        warnings.filterwarnings("ignore", r"(?s)Features .* are constant", UserWarning)  # (?s): the index list may wrap onto new lines
        f_stat, p = f_classif(x, y)
    return np.asarray(f_stat, dtype=np.float64), np.asarray(p, dtype=np.float64)


def make_pipeline(names: tuple[str, ...] | list[str], kind: str, params: dict[str, Any], seed: int = 0) -> Any:
    """An unfitted sklearn Pipeline: log of scale features → standardise → [the ``kbest`` best by ANOVA F] → classifier."""
    from sklearn.pipeline import Pipeline
    from sklearn.preprocessing import StandardScaler

    steps: list[tuple[str, Any]] = [("log", LogFeatures(tuple(names))), ("scale", StandardScaler())]
    k = int(params.get("kbest", 0))
    if 0 < k < len(names):
        from sklearn.feature_selection import SelectKBest

        steps.append(("select", SelectKBest(anova_f, k=k)))
    return Pipeline([*steps, ("clf", make_classifier(kind, params, seed))])


def decision_scores(clf: Any, z: FloatArray) -> FloatArray:
    """Scores (n, K) of a fitted classifier, columns in ``clf.classes_`` order, higher is likelier.

    Decision values where the classifier has them (a binary (n,) becomes ±d/2; an SVM of more than two classes gives
    the soft count of its one-vs-one duels, :func:`tactiled.learn.infer.pairwise_scores`), else the log
    of its probabilities (floored at 1e-3, so one window can never veto a class).
    """
    k = len(clf.classes_)
    if getattr(clf, "decision_function_shape", None) is not None and k > 2:  # an SVC: its one-vs-one duels, softly counted
        shape = clf.decision_function_shape
        clf.decision_function_shape = "ovo"
        try:
            return pairwise_scores(np.asarray(clf.decision_function(z), dtype=np.float64), *pair_matrices(k))
        finally:
            clf.decision_function_shape = shape
    if hasattr(clf, "decision_function") and k > 1:
        d = np.asarray(clf.decision_function(z), dtype=np.float64)
        return pm_half(d) if d.ndim == 1 else d
    return log_proba(np.asarray(clf.predict_proba(z), dtype=np.float64))


def softmax(z: FloatArray, temperature: float = 1.0) -> FloatArray:
    """Row-wise softmax of ``z / temperature``: always finite, in [0, 1], rows summing to 1.

    A NaN score counts as the least likely class, ±inf as ±1e300; a temperature that is not
    finite and > 0 is taken as 1 (models are refused at load for it; this is the last guard).
    """
    if not (math.isfinite(temperature) and temperature > 0):
        temperature = 1.0
    with np.errstate(over="ignore", invalid="ignore"):
        z = np.asarray(z, dtype=np.float64) / temperature
    z = np.clip(np.nan_to_num(z, nan=-1e300, posinf=1e300, neginf=-1e300), -1e300, 1e300)
    z = z - z.max(axis=-1, keepdims=True)
    e = np.exp(z)
    out: FloatArray = e / e.sum(axis=-1, keepdims=True)
    return out


def log_softmax(z: FloatArray, temperature: float = 1.0) -> FloatArray:
    """Row-wise log of :func:`softmax` of ``z / temperature`` (..., K), computed in log space so that it stays finite.

    A score of -inf (a class the fold's model never saw, a slide with no window) stays -inf, and a row of -inf
    stays -inf throughout (no class is more likely than another); NaN counts as -inf, +inf as 1e300, and a
    temperature that is not finite and > 0 is taken as 1, as in :func:`softmax`.
    """
    if not (math.isfinite(temperature) and temperature > 0):
        temperature = 1.0
    z = np.asarray(z, dtype=np.float64)
    finite = ~(np.isnan(z) | (z == -np.inf))  # +inf counts as 1e300; a finite score that overflows below stays finite
    with np.errstate(over="ignore", invalid="ignore"):
        z = np.where(finite, np.clip(np.nan_to_num(z, posinf=1e300) / temperature, -1e300, 1e300), -np.inf)
    top = np.where(finite, z, -1e300).max(axis=-1, keepdims=True)
    shifted = np.where(finite, z - top, -np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        norm = np.log(np.exp(shifted).sum(axis=-1, keepdims=True))  # >= 0 where the row has a finite score; -inf where it has none
        out: FloatArray = np.where(np.isfinite(norm), shifted - norm, -np.inf)
    return out


def ensemble_scores(first: FloatArray, first_temperature: float, second: FloatArray, second_temperature: float) -> FloatArray:
    """Slide scores (..., K) of a two-member ensemble: the sum of each member's log softmax probabilities.

    ``first`` and ``second`` are the members' fused slide scores (..., K) (columns in the same class order),
    each softened by its own temperature. ``softmax`` of the sum is the normalised product of the members'
    probabilities; :class:`Model` divides it by the ensemble's own temperature (fitted on out-of-fold sums, since two
    members that see one slide are not independent and their product is over-confident). -inf where either member
    has -inf (a class it never saw).
    """
    out: FloatArray = log_softmax(first, first_temperature) + log_softmax(second, second_temperature)
    return out


def fit_temperature(scores: FloatArray, y_idx: npt.NDArray[np.intp], smoothing: float = 0.02) -> float:
    """Temperature T minimising the log loss of softmax(scores / T) against ``y_idx`` (rows = slides).

    The targets are label-smoothed (``smoothing`` of the mass spread over the other classes),
    so perfectly separated training slides do not drive T to zero and every confidence to 1.
    Slides with no window, or whose true class the fold's model never saw, are ignored;
    other classes it never saw count as far less likely than any seen one.
    """
    from scipy import optimize

    ok = y_idx >= 0
    ok[ok] = np.isfinite(scores[ok, y_idx[ok]])
    if ok.sum() < 2 or scores.shape[1] < 2:
        return 1.0
    s, y = scores[ok], y_idx[ok]
    low = np.where(np.isfinite(s), s, np.inf).min(axis=1, keepdims=True) - 20.0
    s = np.where(np.isfinite(s), s, low)
    k = s.shape[1]
    target = np.full(s.shape, smoothing / (k - 1))
    target[np.arange(len(y)), y] = 1.0 - smoothing

    def nll(log_t: float) -> float:
        p = softmax(s, math.exp(log_t))
        return float(-np.mean(np.sum(target * np.log(np.clip(p, 1e-300, None)), axis=1)))

    res = optimize.minimize_scalar(nll, bounds=(-8.0, 6.0), method="bounded")
    return float(math.exp(res.x))


@dataclass
class Model:
    """A trained window classifier with everything needed to use it on a stream.

    An *ensemble* (format 7) has a second member, :attr:`partner` (a :class:`Model` of its own: classifier, its
    feature names, fusion and temperature; no calibration or novelty). Both read columns of one analysis:
    ``settings.names`` is the union of the members' features, :attr:`member_names` this model's own classifier's
    columns and ``partner.names`` the partner's. A slide's probabilities are then ``softmax`` of
    :func:`ensemble_scores` (each member's fused slide scores softened by its own temperature, :attr:`member_temperature`
    and ``partner.temperature``) over :attr:`temperature`; the calibration maps and the novelty data (this member's
    standardised slide-mean features) are the ensemble model's. Without a partner, ``temperature`` softens this
    classifier's fused scores, as before.
    """

    method: str
    kind: str
    params: dict[str, Any]
    classes: list[str]
    settings: AnalysisSettings
    fs: float
    channels: int
    pipeline: Any
    temperature: float = 1.0
    seed: int = 0
    summary: dict[str, Any] = field(default_factory=dict)
    fingerprint: str = ""
    refit: tuple[FloatArray, npt.NDArray[np.str_]] | None = None  # standardised training rows and labels (kNN/SVM refit on them; enrol)
    calibration: FloatArray | None = None  # (2, m): top softmax probability -> P(label right); None: uncalibrated (format 2)
    early_calibration: tuple[float, float, float] | None = None  # (a, b, c) of early_probability, for provisional labels (format 5)
    novelty_x: FloatArray | None = None  # (n, F'): standardised mean features of the training slides; None: no novelty (format 2)
    novelty_k: int = 3
    novelty_threshold: float = math.inf
    novelty_y: npt.NDArray[np.str_] | None = None  # (n,): the surface of each novelty_x row (format 4; enrol refits the threshold)
    novelty_groups: npt.NDArray[np.int64] | None = None  # (n,): the recording of each novelty_x row, numbered from 0
    novelty_score: str = "ratio"  # how novelty_parts measures a slide against novelty_x (NOVELTY_SCORES); files before format 5: distance
    novelty_distance_threshold: float = math.inf  # score "combined" (format 6): the nearest surface's distance above which a slide is unknown
    novelty_names: tuple[str, ...] | None = None  # format 8: the psd columns whose spectral shape novelty_x holds; None: this classifier's inputs
    novelty_center: FloatArray | None = None  # format 8: (B,) the mean of the training slides' spectral shapes ...
    novelty_scale: FloatArray | None = None  # ... and (B,) their standard deviation (floored at SHAPE_SCALE_FLOOR): novelty_x's standardisation
    novelty_prefix: tuple[float, ...] = ()  # format 8: the distance threshold of a slide of 1, 2, ... windows, times the whole training slides' one
    novelty_surface_scale: FloatArray | None = None  # format 8: (S,) >= 1, each surface's distances divided by it (surfaces sorted)
    start_level: float | None = None  # the detector's envelope above which a stream begins in a slide (learnt from the training
    # recordings' rests and slides: tactiled.learn.levels); None: not learnt (a stream's start is then told by its changes)
    start_front: dict[str, float] | None = None  # the detector's front-end settings the level was measured under (detect.FRONT_END_KEYS)
    partner: Model | None = None  # an ensemble's second member (format 7); None: a single classifier
    member_names: tuple[str, ...] | None = None  # an ensemble: this classifier's columns (a subset of settings.names); None: all of them
    member_temperature: float = 1.0  # an ensemble: the temperature of this classifier's own probabilities (``temperature`` is the ensemble's)
    _groups: tuple[npt.NDArray[np.str_], SurfaceGroups] | None = field(default=None, init=False, repr=False, compare=False)  # novelty_y's

    @property
    def names(self) -> tuple[str, ...]:
        """The F raw feature names the model takes, in column order (its settings'; an ensemble's: both members')."""
        return self.settings.names

    @property
    def inputs(self) -> tuple[str, ...]:
        """The F' raw feature names this model's own classifier reads (:attr:`member_names`, else all of :attr:`names`)."""
        return self.member_names if self.member_names is not None else self.settings.names

    def own(self, x: npt.ArrayLike) -> FloatArray:
        """This classifier's columns (n, F') of raw features x (n, F) (the columns of :attr:`inputs`; all of them without a partner)."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, len(self.names))
        return x if self.member_names is None else take_columns(x, self.names, self.member_names)

    def scores(self, x: npt.ArrayLike, alone: bool = False) -> FloatArray:
        """Window scores (n, K) of this model's own classifier, columns in :attr:`classes` order, for raw features x (n, F).

        ``alone``: each row's scores bit for bit those of the row alone (``scores(x[i:i + 1])``), whatever the other rows."""
        x = self.own(x)
        if isinstance(self.pipeline, LeanPipeline):
            raw, order = self.pipeline.scores(x, alone), self.pipeline.classes_
        elif alone and x.shape[0] > 1:  # scikit-learn's estimators: one row at a time
            raw = np.concatenate([decision_scores(self.pipeline[-1], self.pipeline[:-1].transform(row[None])) for row in x])
            order = self.pipeline[-1].classes_
        else:
            raw, order = decision_scores(self.pipeline[-1], self.pipeline[:-1].transform(x)), self.pipeline[-1].classes_
        if len(order) == len(self.classes) and all(str(c) == k for c, k in zip(order, self.classes, strict=True)):
            return raw
        full = np.full((raw.shape[0], len(self.classes)), raw.min() - 10.0 if raw.size else -10.0)
        index = {c: i for i, c in enumerate(self.classes)}
        for j, c in enumerate(order):
            full[:, index[str(c)]] = raw[:, j]
        return full

    def fuse(self, scores: FloatArray) -> FloatArray:
        """Probabilities (K,) of a slide from the scores (w, K) of its windows (w >= 1) (a single classifier's)."""
        return softmax(np.asarray(scores, dtype=np.float64).mean(axis=0), self.temperature)

    def fused_scores(self, features: FloatArray) -> FloatArray:
        """This classifier's slide scores (K,) from the raw features (w, F) of a slide's windows (w >= 1), by the settings'
        ``fusion``: the mean of the windows' scores, or the scores of the windows' mean features."""
        x = np.asarray(features, dtype=np.float64).reshape(-1, len(self.names))
        return self.fused_many(x, [(0, x.shape[0])])[0]

    def fused_many(self, x: FloatArray, rows: Sequence[tuple[int, int]]) -> FloatArray:
        """This classifier's slide scores (q, K) of q slides, slide i the windows ``x[lo:hi]`` ((lo, hi) = ``rows[i]``, hi > lo)
        of raw features x (n, F), row i bit for bit :meth:`fused_scores` of ``x[lo:hi]`` (each slide's mean features scored
        as a row alone, or each slide's windows scored together and averaged)."""
        if self.settings.fusion == "features":
            return self.scores(slice_means(x, rows), alone=True)
        return np.stack([self.scores(x[lo:hi]).mean(axis=0) for lo, hi in rows])

    def _combined(self, x: FloatArray, score: Callable[[Model, FloatArray], FloatArray]) -> FloatArray:
        """``score`` (a Model method: window, slide or prefix scores) of this classifier on raw features x (n, F), or, for an
        ensemble, :func:`ensemble_scores` of both members' (each on its own columns, softened by its own temperature)."""
        own = score(self, x)
        if self.partner is None:
            return own
        return ensemble_scores(own, self.member_temperature, score(self.partner, take_columns(x, self.names, self.partner.names)),
                               self.partner.temperature)

    def slide_proba(self, features: FloatArray) -> FloatArray:
        """Probabilities (K,) of a slide from the raw features (w, F) of its windows (w >= 1): this classifier's fused
        scores softened by ``temperature``; an ensemble's, :func:`ensemble_scores` of both members over ``temperature``."""
        x = np.asarray(features, dtype=np.float64).reshape(-1, len(self.names))
        return softmax(self._combined(x, Model.fused_scores), self.temperature)

    def confidence(self, p_top: float) -> float:
        """The probability that the label is right, from the top softmax probability of a slide (the calibration map)."""
        if self.calibration is None:
            return float(p_top)
        return float(np.clip(np.interp(p_top, self.calibration[0], self.calibration[1]), 0.0, 1.0))

    def novelty(self, features: FloatArray) -> float | None:
        """How unlike the training slides a slide is, from its windows' raw features (w, F): > 1 is an unknown surface.

        :func:`novelty_parts` of the slide's standardised mean features (this classifier's, :attr:`inputs`; an ensemble's
        first member's) against the training slides, over the thresholds
        set in training (:func:`over_thresholds`; the distance threshold is infinite unless the score is ``combined``).
        None for a model without novelty data.
        """
        x = np.asarray(features, dtype=np.float64).reshape(-1, len(self.names))
        return self.novelty_many(x, [(0, x.shape[0])])[0]

    def novelty_many(self, x: FloatArray, rows: Sequence[tuple[int, int]], final: bool = True) -> list[float | None]:
        """:meth:`novelty` of q slides, slide i the windows ``x[lo:hi]`` ((lo, hi) = ``rows[i]``) of raw features x (n, F),
        each bit for bit (each slide's mean a row alone), in one pass over the training slides. A slide of w windows, whole
        or the first windows of one that goes on (not ``final``), is held to the distance threshold of w windows
        (:attr:`novelty_prefix`), where the model has them: fewer windows estimate the spectrum less well, and a new
        recording's short slides of a taught surface were called unknown 4 to 8 times as often as its long ones under the
        whole slides' threshold. Beyond the table, a provisional label keeps its last entry and a whole slide the whole
        training slides' threshold (it is as long as the longest of them)."""
        if self.novelty_x is None or not len(self.novelty_x):
            return [None] * len(rows)
        limit: float | FloatArray = self.novelty_distance_threshold
        if self.novelty_prefix:  # beyond the table a whole slide is as long as the longest training slides: their threshold
            last = len(self.novelty_prefix)
            limit = limit * np.array([self.novelty_prefix[min(hi - lo, last) - 1] if not final or hi - lo <= last else 1.0
                                      for lo, hi in rows])
        z = self.novelty_standardise(self.novelty_features(slice_means(x, rows)))
        if self.novelty_y is not None and (self._groups is None or self._groups[0] is not self.novelty_y):
            self._groups = (self.novelty_y, surface_groups(self.novelty_y))
        parts = novelty_parts(z, self.novelty_x, self.novelty_y, self.novelty_k, self.novelty_score, alone=True,
                              groups=None if self._groups is None else self._groups[1], scale=self.novelty_surface_scale)
        return [float(v) for v in over_thresholds(parts, self.novelty_threshold, limit)]

    def novelty_features(self, means: FloatArray) -> FloatArray:
        """The novelty features (q, F'') of q slides whose mean raw features are ``means`` (q, F), before standardisation: the
        :func:`~tactiled.core.features.spectral_shape` of the :attr:`novelty_names` columns (format 8), else this classifier's
        own raw columns (:meth:`own`)."""
        if self.novelty_names is None:
            return self.own(means)
        return spectral_shape(take_columns(means, self.names, self.novelty_names), self.novelty_names)

    def novelty_standardise(self, rows: FloatArray) -> FloatArray:
        """The rows (q, F'') :attr:`novelty_x` holds for :meth:`novelty_features` ``rows``: standardised by ``novelty_center``
        and ``novelty_scale`` (format 8), else as the classifier sees them (:meth:`standardise`)."""
        if self.novelty_names is None or self.novelty_center is None or self.novelty_scale is None:
            return self.standardise(rows)
        out: FloatArray = (rows - self.novelty_center) / self.novelty_scale
        return out

    def novelty_unstandardise(self, z: FloatArray) -> FloatArray:
        """The inverse of :meth:`novelty_standardise`: novelty features (q, F'') of rows ``z`` (q, F'') of :attr:`novelty_x`."""
        if self.novelty_names is None or self.novelty_center is None or self.novelty_scale is None:
            return self.unstandardise(z)
        out: FloatArray = z * self.novelty_scale + self.novelty_center
        return out

    def early_confidence(self, p_top: float, windows: int) -> float:
        """The probability that a label from the first ``windows`` windows of a slide is right (a provisional label), from its top
        softmax probability: :func:`early_probability` with ``early_calibration``; the whole-slide map when the model has none."""
        if self.early_calibration is None:
            return self.confidence(p_top)
        return early_probability(self.early_calibration, p_top, windows, self.early_bounds())

    def early_bounds(self) -> tuple[float, float]:
        """[low, high] of a provisional label's confidence: the range of the final calibration map (temperature scaling's
        [1/(n+2), 1 - 1/(n+2)] of n training slides; a constant map's one value as its top) and its mirror, within
        :data:`EARLY_BOUNDS`, so that a label from a few windows is never surer than the whole slide's could be."""
        if self.calibration is None or not self.calibration.shape[-1]:
            return EARLY_BOUNDS
        values = self.calibration[1]
        hi = min(EARLY_BOUNDS[1], float(np.max(values)))
        lo = max(EARLY_BOUNDS[0], min(float(np.min(values)), 1.0 - hi))
        return min(lo, hi), hi

    def assess(self, features: FloatArray, final: bool = True) -> tuple[FloatArray, float, float | None]:
        """(softmax probabilities (K,), confidence that the top class is right, novelty) of a slide's windows' raw features (w, F).

        ``final``: the whole slide (the calibration map); else the first w windows of a slide that goes on (:meth:`early_confidence`).
        """
        x = np.asarray(features, dtype=np.float64).reshape(-1, len(self.names))
        proba, confidence, novelty = self.assess_many(x, [(0, x.shape[0])], final)
        return proba[0], confidence[0], novelty[0]

    def assess_many(self, features: FloatArray, rows: Sequence[tuple[int, int]],
                    final: bool = True) -> tuple[FloatArray, list[float], list[float | None]]:
        """:meth:`assess` of q slides (or slides so far) at once, slide i the windows ``features[lo:hi]`` ((lo, hi) = ``rows[i]``,
        hi > lo) of raw features (n, F): (probabilities (q, K), confidences (q,), novelties (q,)), row i bit for bit
        ``assess(features[lo:hi], final)`` (offline: every assessment of a recording in one call)."""
        x = np.asarray(features, dtype=np.float64).reshape(-1, len(self.names))
        proba = softmax(self._combined(x, lambda m, cols: m.fused_many(cols, rows)), self.temperature)
        tops = cast(list[float], proba.max(axis=1).tolist())
        confidence = [self.confidence(p) if final else self.early_confidence(p, hi - lo) for p, (lo, hi) in zip(tops, rows, strict=True)]
        return proba, confidence, self.novelty_many(x, rows, final)

    def standardise(self, x: FloatArray) -> FloatArray:
        """Classifier inputs (n, F') of raw features (n, F') of :attr:`inputs` (:meth:`own` of the full columns): log of
        scale features, standardised (the steps before this model's own classifier)."""
        if isinstance(self.pipeline, LeanPipeline):
            return self.pipeline.transform(x)
        return np.asarray(self.pipeline[:-1].transform(x), dtype=np.float64)

    def unstandardise(self, z: FloatArray) -> FloatArray:
        """Raw features (n, F') of :attr:`inputs` whose classifier inputs are ``z`` (n, F'): the inverse of :meth:`standardise`."""
        if isinstance(self.pipeline, LeanPipeline):
            mean, scale = self.pipeline.mean, self.pipeline.scale
        else:
            mean, scale = self.pipeline.named_steps["scale"].mean_, self.pipeline.named_steps["scale"].scale_
        return raw_features(np.asarray(z, dtype=np.float64) * scale + mean, self.inputs)

    def predict_proba(self, x: npt.ArrayLike) -> FloatArray:
        """(n, K) probabilities of single windows (raw features x (n, F)), each as a slide of one window."""
        return softmax(self._combined(np.asarray(x, dtype=np.float64).reshape(-1, len(self.names)), Model.scores), self.temperature)

    def predict(self, x: npt.ArrayLike) -> npt.NDArray[np.str_]:
        """Labels (n,) of single windows from raw features x (n, F): the class with the largest probability."""
        return np.asarray(self.classes)[np.argmax(self.predict_proba(x), axis=1)]

    def check_stream(self, fs: float, channels: int, where: str = "stream", model: str | Path | None = None) -> None:
        """Refuse a stream (``where``) of another rate ``fs`` (Hz) or another number of ``channels``: one line naming the
        stream and, when given, the model file ``model`` (``model.npz: model trained at fs 2200 Hz, sensor ft is 20000 Hz``).
        A stream of more channels was accepted until 2026-11-27: the shipped two-film model labelled a three-film sensor's
        slides without a word (an outside audit), where README says any other channel count is refused."""
        named = f"{model}: " if model is not None else ""
        if abs(fs - self.fs) > 1e-6 * self.fs:
            raise ModelError(f"{named}model trained at fs {self.fs:g} Hz, {where} is {fs:g} Hz")
        if channels != self.channels:
            raise ModelError(f"{named}model of {self.channels} channel{'s' if self.channels > 1 else ''}, {where} has {channels}")

    def describe(self) -> str:
        """One line: method, classifier(s), features, windows, cross-validated accuracy."""
        cv = self.summary.get("cv_accuracy")
        acc = f", nested CV accuracy {100 * cv['mean']:.1f} ± {100 * cv['sd']:.1f} %" if isinstance(cv, dict) else ""
        band = cv.get("interval95") if isinstance(cv, dict) else None
        if acc and isinstance(band, list) and len(band) == 2 and all(_is_number(v) for v in band):
            over = "slides" if isinstance(cv, dict) and cv.get("grouped_by") == "slide" else "recordings"
            acc += f" (95 % interval over {over} {100 * band[0]:.0f}–{100 * band[1]:.0f} %)"
        if acc and self.partner is not None and isinstance(cv, dict) and cv.get("model") != "ensemble":  # trained before its file stated the ensemble's own
            acc = acc.replace("nested CV accuracy", "nested CV accuracy of its first member alone", 1)
        why = optimistic_reason(cv) if isinstance(cv, dict) else None
        if why is not None:
            acc += f", optimistic ({why})"
        if acc and self.summary.get("enrolled"):  # enrol keeps the summary of the model it started from
            acc = (acc.replace(", nested CV accuracy", ", the base model's nested CV accuracy", 1)
                   + " (from before enrolment: not measured with the slides enrolled)")
        s = self.settings
        what = f"{self.kind} on {len(self.inputs)} features"
        if self.partner is not None:
            ens = self.summary.get("ensemble")
            cv_ens = f" (CV accuracy {100 * ens['mean']:.1f} %)" if isinstance(ens, dict) and _is_number(ens.get("mean")) else ""
            what = (f"ensemble{cv_ens} of {self.kind} on {len(self.inputs)} features ({self.settings.fusion} fusion) and {self.partner.kind} "
                    f"on {len(self.partner.names)} ({self.partner.settings.fusion} fusion)")
        if self.novelty_names is not None:
            what += f", unknown surfaces from the shape of {len(self.novelty_names)} band levels"
        return (f"{self.method}: {what}, windows {s.duration_s:g} s every {s.hop():g} s from "
                f"{s.start_s:g} s{' (at most ' + str(s.max_windows) + ')' if s.max_windows else ''}, {len(self.classes)} classes{acc}")

    # ---- persistence -------------------------------------------------------------------------

    def _arrays(self) -> dict[str, Any]:
        """This classifier's arrays, and an ensemble's partner's under :data:`PARTNER` (format 7)."""
        arrays = self._member_arrays()
        if self.partner is not None:
            arrays.update({PARTNER + k: v for k, v in self.partner._member_arrays().items()})
        return arrays

    def _member_arrays(self) -> dict[str, Any]:
        if isinstance(self.pipeline, LeanPipeline):  # the file's arrays it loaded from, less the novelty's own (_trust_arrays)
            return {k: v for k, v in self.pipeline.arrays.items() if k not in SHAPE_ARRAYS}
        scaler, clf = self.pipeline.named_steps["scale"], self.pipeline.named_steps["clf"]
        arrays: dict[str, Any] = {"classes": np.array(self.classes, dtype=np.str_), "scaler_mean": np.asarray(scaler.mean_, dtype=np.float64),
                                  "scaler_scale": np.asarray(scaler.scale_, dtype=np.float64)}
        if self.kind == "elm":
            arrays.update(weights=clf.weights_, biases=clf.biases_, beta=clf.beta_, elm_temperature=np.float64(clf.temperature_))
        elif self.kind == "linear":
            arrays.update(coef=np.asarray(clf.coef_, dtype=np.float64), intercept=np.asarray(clf.intercept_, dtype=np.float64))
        elif self.kind == "svm":  # the fitted SVM, so that loading needs no refit (tactiled/learn/infer.py)
            arrays.update(svm_arrays(clf))
        if self.refit is None:
            raise ModelError("a model keeps its standardised training rows (kNN and SVM refit on them, enrol adds to them)")
        arrays.update(train_x=np.asarray(self.refit[0], dtype=np.float64), train_y=np.asarray(self.refit[1], dtype=np.str_))
        return arrays

    def _trust_arrays(self) -> dict[str, Any]:
        calibration = self.calibration if self.calibration is not None else np.array([[0.0, 1.0], [0.0, 1.0]])
        novelty_x = self.novelty_x if self.novelty_x is not None else np.zeros((0, len(self.novelty_names or self.inputs)))
        n = novelty_x.shape[0]
        novelty_y = self.novelty_y if self.novelty_y is not None and len(self.novelty_y) == n else np.full(n, "", dtype=np.str_)
        groups = self.novelty_groups if self.novelty_groups is not None and len(self.novelty_groups) == n else np.arange(n)
        arrays = {"calibration": np.asarray(calibration, dtype=np.float64), "novelty_x": np.asarray(novelty_x, dtype=np.float64),
                  "novelty_y": np.asarray(novelty_y, dtype=np.str_), "novelty_groups": np.asarray(groups, dtype=np.int64)}
        if self.novelty_names is not None:
            surfaces = len(np.unique(novelty_y)) if n else 0
            arrays.update(novelty_center=np.asarray(self.novelty_center, dtype=np.float64),
                          novelty_scale=np.asarray(self.novelty_scale, dtype=np.float64),
                          novelty_surface_scale=np.asarray(self.novelty_surface_scale if self.novelty_surface_scale is not None
                                                           else np.ones(surfaces), dtype=np.float64))
        return arrays

    def _header(self) -> dict[str, Any]:
        header = self._single_header()
        if self.start_level is not None:  # written only when learnt: a model without it has the header it had
            header["detector"] = {"start_level": self.start_level, "front_end": self.start_front}
        if self.novelty_names is not None:  # format 8: the classifier's own columns, and the novelty's
            header.update(version=FORMAT_VERSION, inputs=list(self.inputs))
            header["novelty"].update(inputs=list(self.novelty_names), prefix=list(self.novelty_prefix))
        if self.partner is not None:
            p = self.partner
            header.update(version=FORMAT_VERSION if self.novelty_names is not None else ENSEMBLE_VERSION, ensemble={
                "member": {"names": list(self.inputs), "temperature": self.member_temperature},
                "partner": {"method": p.method, "classifier": p.kind, "params": p.params, "names": list(p.names), "fusion": p.settings.fusion,
                            "temperature": p.temperature}})
        return header

    def _single_header(self) -> dict[str, Any]:
        return {"format": FORMAT, "version": SINGLE_VERSION, "method": self.method, "classifier": self.kind, "params": self.params,
                "seed": self.seed, "classes": self.classes, "settings": self.settings.to_dict(), "fs": self.fs, "channels": self.channels,
                "temperature": self.temperature, "summary": self.summary,
                "novelty": {"k": self.novelty_k, "threshold": self.novelty_threshold if math.isfinite(self.novelty_threshold) else None,
                            "score": self.novelty_score,
                            "distance_threshold": self.novelty_distance_threshold if math.isfinite(self.novelty_distance_threshold) else None},
                "early_calibration": list(self.early_calibration) if self.early_calibration is not None else None}

    def save(self, path: str | Path) -> str:
        """Write atomically; returns the fingerprint."""
        arrays = {**self._arrays(), **self._trust_arrays()}
        header = self._header()
        self.fingerprint = _fingerprint(header, arrays)
        header["fingerprint"] = self.fingerprint
        atomic_savez(path, {"header": np.str_(json.dumps(header, sort_keys=True)), **arrays})
        return self.fingerprint


def fit_pipeline(x: FloatArray, y: npt.NDArray[Any], names: list[str] | tuple[str, ...], kind: str, params: dict[str, Any],
                 seed: int = 0) -> tuple[Any, tuple[FloatArray, npt.NDArray[np.str_]]]:
    """Fit :func:`make_pipeline` on raw features ``x`` (n, F).

    Returns the pipeline and its standardised training rows with their labels (kNN and SVM are refit on them at
    load; ``tactiled enrol`` adds to them). kNN and SVM are fitted on at most :data:`MAX_REFIT_ROWS` rows (an SVM on
    at most :data:`MAX_SVM_REFIT_ROWS`: its fit time grows with the square of the rows); beyond that, a seeded
    subsample; the rows kept for the ELM and the linear model are capped the same way (they are fitted on all).
    """
    if kind == "knn":  # never more neighbours than the rarest class has rows: more would outvote it wherever it is
        fewest = int(np.unique(y, return_counts=True)[1].min()) if len(y) else 1
        params = {**params, "n_neighbors": max(1, min(int(params.get("n_neighbors", 9)), x.shape[0], fewest))}
    pipe = make_pipeline(names, kind, params, seed)
    cap = MAX_SVM_REFIT_ROWS if kind == "svm" else MAX_REFIT_ROWS  # an RBF SVM's fit grows with the square of its rows
    if kind in ("svm", "knn") and x.shape[0] > cap:
        keep = capped_rows(y, cap, seed)
        x, y = x[keep], y[keep]
    pipe.fit(x, y)
    if x.shape[0] > MAX_REFIT_ROWS:
        keep = capped_rows(y, MAX_REFIT_ROWS, seed)
        x, y = x[keep], y[keep]
    return pipe, (pipe[:-1].transform(x), np.asarray(y, dtype=np.str_))


MIN_CLASS_ROWS = 10  # a capped subsample keeps at least this many rows of every class (all it has, where it has fewer)


def capped_rows(y: npt.NDArray[Any], cap: int, seed: int) -> npt.NDArray[np.intp]:
    """The rows (sorted) of labels ``y`` (n,) that a fit on at most ``cap`` of them keeps (``cap`` < n): a seeded draw, then
    each class the draw left with fewer than :data:`MIN_CLASS_ROWS` rows made up to that (or to all it has) from its other
    rows, as many taken back from the class with the most. A plain draw of 4 000 rows from 16 000 lost a surface of two
    (its class gone from the model while its name stayed in the summary); where no class falls short, the draw as it was."""
    rng = np.random.default_rng(seed)
    chosen = np.zeros(len(y), dtype=bool)
    chosen[rng.choice(len(y), cap, replace=False)] = True
    names, inverse = np.unique(y, return_inverse=True)
    for c in range(len(names)):
        rows = np.flatnonzero(inverse == c)
        short = min(len(rows), MIN_CLASS_ROWS) - int(chosen[rows].sum())
        if short > 0:
            chosen[rng.choice(rows[~chosen[rows]], short, replace=False)] = True
    while (extra := int(chosen.sum()) - cap) > 0:
        counts = np.bincount(inverse[chosen], minlength=len(names))
        big = int(np.argmax(counts))
        rows = np.flatnonzero(chosen & (inverse == big))
        chosen[rng.choice(rows, min(extra, max(len(rows) - MIN_CLASS_ROWS, 1)), replace=False)] = False
    return np.flatnonzero(chosen)


def slice_means(x: FloatArray, rows: Sequence[tuple[int, int]]) -> FloatArray:
    """(q, F) the mean of the rows ``x[lo:hi]`` of x (n, F) for each (lo, hi) of ``rows`` (hi > lo), each bit for bit
    ``x[lo:hi].mean(axis=0)`` (the same sum and division, without its per-call overhead)."""
    if len(rows) == 1:
        lo, hi = rows[0]
        out: FloatArray = np.add.reduce(x[lo:hi], axis=0, keepdims=True) / (hi - lo)
        return out
    return np.stack([np.add.reduce(x[lo:hi], axis=0) / (hi - lo) for lo, hi in rows])


def prefix_fused(x: FloatArray, score: Callable[[FloatArray], FloatArray], fusion: str) -> FloatArray:
    """Fused slide scores (w, K) of the first 1, 2, ..., w windows x (w, F) (time order) from a window scorer ``score``
    ((n, F) -> (n, K)): the scores of the prefixes' mean features (``fusion`` "features") or the prefixes' mean scores."""
    counts = np.arange(1, x.shape[0] + 1, dtype=np.float64)[:, None]
    if fusion == "features":
        return score(np.cumsum(x, axis=0) / counts)
    out: FloatArray = np.cumsum(score(x), axis=0) / counts
    return out


def take_columns(x: FloatArray, names: Sequence[str], wanted: Sequence[str]) -> FloatArray:
    """The columns (n, len(wanted)) of raw features ``x`` (n, len(names)) named ``wanted`` (each one of ``names``), in that order."""
    index = {n: i for i, n in enumerate(names)}
    # C order: numpy gives a column selection in Fortran order, and the row-by-row products round by layout
    out: FloatArray = np.ascontiguousarray(np.asarray(x, dtype=np.float64)[:, [index[n] for n in wanted]])
    return out


def _fingerprint(header: dict[str, Any], arrays: dict[str, Any]) -> str:
    h = hashlib.sha256(json.dumps(header, sort_keys=True).encode())
    for key in sorted(arrays):
        a = np.ascontiguousarray(arrays[key])
        h.update(key.encode() + str(a.dtype).encode() + str(a.shape).encode() + a.tobytes())
    return h.hexdigest()[:16]


def _need(cond: bool, path: object, what: str) -> None:
    if not cond:
        raise ModelError(f"{path}: {what}")


def load_model(path: str | Path | None = None, lean: bool = True) -> Model:
    """Load and check a model file (``None``: the shipped model); :class:`ModelError` names file and problem.

    ``lean``: evaluate with numpy alone when the file allows it (:mod:`tactiled.learn.infer`; no scikit-learn import);
    False: through the scikit-learn pipeline, refitting kNN and SVM.
    """
    path = Path(path) if path else default_model_path()
    try:
        with NpzReader(path, MAX_MODEL_BYTES) as reader:
            _need("header" in reader or "samples" not in reader, path,
                  "a recording (it holds samples), not a model file: make a model with tactiled train")
            _need("header" in reader, path, "header: missing or not a string")
            text = reader.read("header")
            _need(text.shape == () and text.dtype.kind == "U", path, "header: missing or not a string")
            try:
                header = load_json_bounded(text.item(), "header")
            except ValueError as exc:
                raise ModelError(f"{path}: {exc}") from None
            _need(isinstance(header, dict) and header.get("format") == FORMAT, path, f"header.format: not a {FORMAT} file")
            _need(header.get("version") in READ_VERSIONS, path,
                  f"header.version: {header.get('version')!r} is not one of the supported {READ_VERSIONS} (retrain with this tactiled)")
            kind = header.get("classifier")
            _need(kind in CLASSIFIERS, path, f"header.classifier: unknown {kind!r}")
            version = header.get("version")
            nov = header.get("novelty")
            shape = SHAPE_ARRAYS if version == FORMAT_VERSION and isinstance(nov, dict) and nov.get("inputs") is not None else ()
            trust: tuple[str, ...] = (*TRUST_ARRAYS, *ENROL_ARRAYS, *shape) if version in (4, 5, 6, 7, 8) else TRUST_ARRAYS if version == 3 else ()
            keys = _member_keys(kind, set(reader.keys()), "", trust)
            partner = _partner_kind(path, header)
            if partner is not None:  # formats 7 and 8: the second member's arrays, each under the prefix, and its training rows
                keys += _member_keys(partner, set(reader.keys()), PARTNER, ENROL_ARRAYS[:2])
            missing, extra = [k for k in keys if k not in reader], sorted(set(reader.keys()) - {"header", *keys})
            _need(not missing, path, f"{', '.join(missing)}: missing")
            what = f"{kind} model" + (f" with a {partner} partner" if partner else "")
            _need(not extra, path, f"{', '.join(extra)}: not an array of a {what} (the fingerprint covers every array)")
            arrays = {k: reader.read(k) for k in keys}
    except NpzError as exc:
        what = "no such model file" if str(exc) == MISSING else str(exc)
        raise ModelError(f"{path}: array {exc.key}: {what}" if exc.key else f"{path}: {what}") from None
    try:
        return _build(path, header, arrays, lean)
    except ModelError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
        raise ModelError(f"{path}: header or arrays inconsistent: {exc}") from None


def _member_keys(kind: str, present: set[str], prefix: str, extra: Sequence[str]) -> tuple[str, ...]:
    """The array names of one member of classifier ``kind`` (``prefix``: :data:`PARTNER` for an ensemble's second), with the
    fitted SVM's arrays where the file has them (``present``) and the ``extra`` ones (calibration, novelty, training rows)."""
    optional = [k for k in SVM_ARRAYS if prefix + k in present] if kind == "svm" else []
    return tuple(prefix + k for k in dict.fromkeys(("classes", "scaler_mean", "scaler_scale", *ARRAYS[kind], *optional, *extra)))


def _partner_kind(path: Path, header: dict[str, Any]) -> str | None:
    """The classifier of a format-7 or -8 file's second member (``header.ensemble.partner.classifier``), None without one."""
    ens = header.get("ensemble") if header.get("version") in (ENSEMBLE_VERSION, FORMAT_VERSION) else None
    if ens is None:
        return None
    _need(isinstance(ens, dict) and isinstance(ens.get("member"), dict) and isinstance(ens.get("partner"), dict), path,
          "header.ensemble: must be null or an object with member and partner objects")
    kind = ens["partner"].get("classifier")
    _need(kind in CLASSIFIERS, path, f"header.ensemble.partner.classifier: unknown {kind!r}")
    return str(kind)


def _finite(a: Any) -> bool:
    return bool(np.issubdtype(np.asarray(a).dtype, np.floating) and np.all(np.isfinite(a)))


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _check_settings(path: Path, s: AnalysisSettings, fs: float, channels: int) -> None:
    _need(all(_is_number(v) for v in (s.start_s, s.duration_s, s.hop_s, s.nsigma)), path, "settings: times and nsigma must be finite numbers")
    _need(all(isinstance(v, int) and not isinstance(v, bool) for v in (s.max_windows, s.half_width, s.level)), path,
          "settings: max_windows, half_width, level must be integers")
    _need(all(isinstance(v, str) for v in (s.spikes, s.wavelet, s.mode, s.fusion, *s.names)), path,
          "settings: spikes, wavelet, mode, fusion, names must be strings")
    _need(isinstance(s.centred, bool), path, "settings.centred: must be true or false")
    _need(0 <= s.start_s <= 60 and 0 < s.duration_s <= 60 and 0 <= s.hop_s <= 60, path, "settings: start_s, duration_s, hop_s out of range")
    _need(0 <= s.max_windows <= 10_000, path, "settings.max_windows: out of range 0..10000")
    _need(s.fusion in ("scores", "features"), path, "settings.fusion: must be scores or features")
    _need(s.spikes in ("mad", "hampel", "none") and 1 <= s.half_width <= 1000 and 0 < s.nsigma <= 1000, path, "settings: spike removal out of range")
    _need(1 <= s.level <= 8, path, "settings.level: must be in 1..8")
    _need(0 < len(s.names) <= MAX_FEATURES, path, f"settings.names: 1..{MAX_FEATURES} features")
    _need(1 <= round(s.duration_s * fs) <= MAX_WINDOW_SAMPLES, path, f"settings.duration_s: 1..{MAX_WINDOW_SAMPLES} samples at fs")
    import pywt

    _need(s.wavelet in pywt.wavelist(kind="discrete") and s.mode in pywt.Modes.modes, path, "settings: wavelet or mode unknown to PyWavelets")
    try:
        plan = FeaturePlan(s.names, s.wavelet, s.mode, fs=fs)
    except ValueError as exc:
        raise ModelError(f"{path}: settings: {exc}") from None
    _need(plan.channels_needed <= channels, path, f"settings.names: features of {plan.channels_needed} channels, the model has {channels}")
    _need(plan.min_samples() <= round(s.duration_s * fs), path,
          f"settings.duration_s: {s.duration_s:g} s is shorter than the {plan.min_samples()} samples the features need")


def _check_params(path: Path, kind: str, params: dict[str, Any], where: str = "params") -> None:
    def num(key: str, lo: float, hi: float, integer: bool = False) -> None:
        if key in params:
            v = params[key]
            _need(_is_number(v) and lo <= v <= hi and (not integer or isinstance(v, int)), path,
                  f"{where}.{key}: must be {'an integer' if integer else 'a number'} in [{lo:g}, {hi:g}]")

    num("n_hidden", 1, 100_000, integer=True)
    num("alpha", 0, 1e6)
    num("n_neighbors", 1, 1000, integer=True)
    num("C", 1e-6, 1e4 if kind == "svm" else 1e9)  # a huge C makes the SVM's refit at load crawl
    num("max_iter", 1, 100_000, integer=True)
    num("kbest", 0, MAX_FEATURES, integer=True)
    if kind == "svm":
        gamma = params.get("gamma", "scale")
        _need(params.get("kernel", "rbf") in ("rbf", "linear") and (gamma in ("scale", "auto") or (_is_number(gamma) and 0 < gamma <= 1e6)),
              path, f"{where}: svm kernel must be rbf or linear, gamma scale, auto or a number in (0, 1e6]")
    _need(params.get("class_weight") in (None, "balanced") and (kind in ("svm", "linear") or "class_weight" not in params), path,
          f"{where}.class_weight: must be balanced (svm and linear only) or absent")
    if kind == "elm":
        _need(str(params.get("init", "hpelm")) in ("hpelm", "huang") and isinstance(params.get("calibrate", False), bool), path,
              f"{where}: elm init must be hpelm or huang, calibrate true or false")


def _build(path: Path, header: dict[str, Any], arrays: dict[str, Any], lean: bool = True) -> Model:
    fingerprint = header.pop("fingerprint", None)
    _need(fingerprint == _fingerprint(header, arrays), path, "fingerprint does not match the contents (tampered or corrupt)")
    kind = header["classifier"]
    fs, channels = header["fs"], header["channels"]
    _need(_is_number(fs) and 100 <= fs <= 1e6 and isinstance(channels, int) and 1 <= channels <= 8, path,
          "header: fs must be in 100 Hz..1 MHz and channels in 1..8")
    fs = float(fs)
    try:
        settings = AnalysisSettings.from_dict(header["settings"])  # a key every file has had, missing: not a default's windows
    except ValueError as exc:
        raise ModelError(f"{path}: {exc}") from None
    _check_settings(path, settings, fs, channels)
    _need(isinstance(header["classes"], list), path, "header.classes: must be a list")
    classes = [str(c) for c in header["classes"]]
    _need(1 <= len(classes) <= MAX_CLASSES and len(set(classes)) == len(classes), path, f"header.classes: 1..{MAX_CLASSES} distinct classes")
    bad = next(((i, problem) for i, c in enumerate(classes) if (problem := surface_name_problem(c))), None)
    if bad is not None:  # a class is a surface name: printed one per line, published as the label ("" would read as no label)
        raise ModelError(f"{path}: header.classes[{bad[0]}]: {bad[1]}")
    _need(isinstance(header["params"], dict), path, "header.params: must be an object")
    params, seed = dict(header["params"]), header["seed"]
    _check_params(path, kind, params)
    temperature = _temperature(path, header.get("temperature", 1.0), "header.temperature")
    _need(isinstance(seed, int) and 0 <= seed < 2**32, path, "header.seed: must be an integer in [0, 2**32)")
    summary = header.get("summary", {})
    cv = summary.get("cv_accuracy") if isinstance(summary, dict) else None
    _need(isinstance(summary, dict) and (cv is None or (isinstance(cv, dict) and _is_number(cv.get("mean")) and _is_number(cv.get("sd")))),
          path, "header.summary: must be an object, its cv_accuracy mean and sd numbers")
    ensemble = header["ensemble"] if _partner_kind(path, header) is not None else None
    if ensemble:
        names = _subset(path, ensemble["member"].get("names"), settings.names, "header.ensemble.member.names")
    elif header.get("version") == FORMAT_VERSION:  # format 8: the classifier's columns, beside the novelty's
        names = _subset(path, header.get("inputs"), settings.names, "header.inputs")
    else:
        names = settings.names
    own = {k: v for k, v in arrays.items() if not k.startswith(PARTNER)}
    pipe, refit = _member(path, "", kind, params, seed, names, classes, own, lean)
    model = Model(str(header.get("method", kind)), kind, params, classes, settings, fs, channels, pipe, temperature, seed,
                  dict(summary), fingerprint or "", refit)
    if ensemble is not None or names != settings.names:
        model.member_names = names
    detector = header.get("detector")
    if detector is not None:
        level: Any = detector.get("start_level") if isinstance(detector, dict) else None
        _need(_is_number(level) and 0 < level < 1e30, path, "header.detector.start_level: must be a positive finite number")
        front: Any = detector.get("front_end")
        _need(isinstance(front, dict) and set(front) == set(FRONT_END_KEYS) and all(_is_number(v) for v in front.values()), path,
              f"header.detector.front_end: must hold the numbers {', '.join(FRONT_END_KEYS)} (the level is used only under them)")
        model.start_level, model.start_front = float(level), {k: float(v) for k, v in front.items()}
    if ensemble is not None:
        _attach_partner(path, model, ensemble, {k[len(PARTNER):]: v for k, v in arrays.items() if k.startswith(PARTNER)}, lean)
    if "calibration" in arrays:
        _check_trust(path, model, header, arrays)
    read = {*model.inputs, *(model.partner.names if model.partner is not None else ()), *(model.novelty_names or ())}
    _need(read == set(model.names), path, "settings.names: must be the union of the classifiers' and the novelty's names")
    _probe(path, model)
    return model


def _temperature(path: Path, value: Any, where: str) -> float:
    """A temperature from a header: a finite number in [1e-6, 1e6]."""
    _need(_is_number(value) and 1e-6 <= value <= 1e6, path, f"{where}: must be a finite number in [1e-6, 1e6]")
    return float(value)


def _subset(path: Path, names: Any, union: tuple[str, ...], where: str) -> tuple[str, ...]:
    """The feature names a part of the model reads (a member's classifier, the novelty): a non-empty list of distinct names,
    each one of the analysis's ``union``."""
    _need(isinstance(names, list) and 0 < len(names) <= len(union) and all(isinstance(n, str) for n in names) and len(set(names)) == len(names)
          and set(names) <= set(union), path, f"{where}: must be distinct feature names of settings.names")
    return tuple(names)


def _attach_partner(path: Path, model: Model, ensemble: dict[str, Any], arrays: dict[str, Any], lean: bool) -> None:
    """Check a format-7 file's second member (``header.ensemble``; its arrays without the :data:`PARTNER` prefix) and attach it."""
    head, where = ensemble["partner"], "header.ensemble.partner"
    names = _subset(path, head.get("names"), model.names, f"{where}.names")
    _need(head.get("fusion") in ("scores", "features"), path, f"{where}.fusion: must be scores or features")
    _need(isinstance(head.get("params"), dict) and isinstance(head.get("method", ""), str), path, f"{where}: params must be an object, method a string")
    kind, params = str(head["classifier"]), dict(head["params"])
    _check_params(path, kind, params, f"{where}.params")
    temperature = _temperature(path, head.get("temperature"), f"{where}.temperature")
    model.member_temperature = _temperature(path, ensemble["member"].get("temperature"), "header.ensemble.member.temperature")
    pipe, refit = _member(path, PARTNER, kind, params, model.seed, names, model.classes, arrays, lean)
    model.partner = Model(str(head.get("method", kind)), kind, params, model.classes, replace(model.settings, names=names, fusion=head["fusion"]),
                          model.fs, model.channels, pipe, temperature, model.seed, {}, "", refit)


def _member(path: Path, prefix: str, kind: str, params: dict[str, Any], seed: int, names: tuple[str, ...], classes: list[str],
            arrays: dict[str, Any], lean: bool) -> tuple[Any, tuple[FloatArray, npt.NDArray[np.str_]] | None]:
    """The pipeline and training rows of one member (its ``arrays``, named without ``prefix``; errors name them with it), checked
    against its feature ``names`` (F) and the header's ``classes``: lean (numpy) when ``lean`` and the arrays allow it."""
    f = len(names)
    _need(list(arrays["classes"]) == classes, path, f"{prefix}classes: differ from the header's")
    mean, scale = arrays["scaler_mean"], arrays["scaler_scale"]
    for key, a in (("scaler_mean", mean), ("scaler_scale", scale)):
        _need(a.shape == (f,) and _finite(a), path, f"{prefix}{key}: must be ({f},) finite floats")
    _need(bool(np.all(scale > 0)), path, f"{prefix}scaler_scale: must be > 0")
    if kind == "elm":
        w, b, beta = arrays["weights"], arrays["biases"], arrays["beta"]
        hidden = int(params.get("n_hidden", 200))
        _need(w.shape == (f, hidden) and b.shape == (hidden,) and beta.shape == (hidden, max(len(classes), 2)), path,
              f"{prefix}weights, {prefix}biases, {prefix}beta: shapes do not match the header")
        _need(all(_finite(a) for a in (w, b, beta)), path, f"{prefix}weights, {prefix}biases, {prefix}beta: must be finite floats")
        elm_t = arrays["elm_temperature"]
        t = float(elm_t) if elm_t.size == 1 and elm_t.dtype.kind in "fiu" else math.nan
        _need(elm_t.shape == () and _finite(elm_t) and 1e-6 <= t <= 1e6, path, f"{prefix}elm_temperature: must be a finite float in [1e-6, 1e6]")
    elif kind == "linear":
        coef, intercept = arrays["coef"], arrays["intercept"]
        rows = 1 if len(classes) == 2 else len(classes)
        _need(coef.shape == (rows, f) and intercept.shape == (rows,) and _finite(coef) and _finite(intercept), path,
              f"{prefix}coef, {prefix}intercept: shapes do not match the header or not finite")
    refit = None
    if "train_x" in arrays:
        train_x, train_y = arrays["train_x"], arrays["train_y"]
        _need(train_x.ndim == 2 and train_x.shape[1] == f and 1 <= train_x.shape[0] <= MAX_REFIT_ROWS and train_y.shape == (train_x.shape[0],),
              path, f"{prefix}train_x, {prefix}train_y: shapes do not match the header (at most {MAX_REFIT_ROWS} rows)")
        _need(train_y.dtype.kind == "U", path, f"{prefix}train_y: must be unicode")
        _need(_finite(train_x), path, f"{prefix}train_x: must be finite floats")
        _need(set(map(str, train_y)) == set(classes), path, f"{prefix}train_y: classes differ from the header's")
        if kind == "knn":
            _need(int(params.get("n_neighbors", 9)) <= train_x.shape[0], path, f"{prefix}params.n_neighbors: more than the training rows")
        refit = (train_x, train_y)
    try:
        pipe = lean_pipeline(kind, names, classes, params, arrays) if lean else None
    except ValueError as exc:
        raise ModelError(f"{path}: {prefix}{exc}") from None
    if pipe is None:
        if kind == "svm":
            _need(arrays["train_x"].shape[0] <= MAX_SVM_REFIT_ROWS, path, f"{prefix}train_x: {arrays['train_x'].shape[0]} rows, more than the "
                  f"{MAX_SVM_REFIT_ROWS} an svm is refit on at load (save it with this tactiled to store the fitted SVM)")
        pipe = _sklearn_pipeline(names, kind, params, seed, classes, arrays)
    return pipe, refit


def _check_trust(path: Path, model: Model, header: dict[str, Any], arrays: dict[str, Any]) -> None:
    """Check and attach a format-3 model's calibration and novelty data."""
    cal, nx = arrays["calibration"], arrays["novelty_x"]
    _need(cal.ndim == 2 and cal.shape[0] == 2 and 2 <= cal.shape[1] <= 10_000 and _finite(cal), path,
          "calibration: must be (2, m) finite floats, 2 <= m <= 10000")
    _need(bool(np.all((cal >= 0) & (cal <= 1)) and np.all(np.diff(cal, axis=1) >= 0)), path, "calibration: knots must be nondecreasing in [0, 1]")
    nov: Any = header.get("novelty")
    _need(isinstance(nov, dict), path, "header.novelty: must be an object")
    if nov.get("inputs") is not None and header.get("version") == FORMAT_VERSION:  # format 8: the spectral shape of psd columns
        shape = _subset(path, nov["inputs"], model.names, "header.novelty.inputs")
        _need(all(name_family(n) == "psd" for n in shape), path, "header.novelty.inputs: must be psd features")
        center, scale = arrays["novelty_center"], arrays["novelty_scale"]
        _need(center.shape == (len(shape),) and scale.shape == (len(shape),) and _finite(center) and _finite(scale) and bool(np.all(scale > 0)),
              path, f"novelty_center, novelty_scale: must be ({len(shape)},) finite floats, the scale > 0")
        prefix = nov.get("prefix", [])
        _need(isinstance(prefix, list) and len(prefix) <= 1000 and all(_is_number(v) and 1.0 <= v <= 1e6 for v in prefix), path,
              "header.novelty.prefix: must be a list of at most 1000 numbers in [1, 1e6]")
        model.novelty_names, model.novelty_center, model.novelty_scale, model.novelty_prefix = shape, center, scale, tuple(map(float, prefix))
        own = arrays["novelty_surface_scale"]
        surfaces = len(np.unique(arrays["novelty_y"])) if arrays["novelty_y"].size else 0
        _need(own.shape == (surfaces,) and _finite(own) and bool(np.all(own >= 1.0)), path,
              f"novelty_surface_scale: must be ({surfaces},) finite floats >= 1, one per surface of novelty_y")
        model.novelty_surface_scale = own
    width = len(model.novelty_names) if model.novelty_names is not None else model.standardise(np.zeros((1, len(model.inputs)))).shape[1]
    _need(nx.ndim == 2 and nx.shape[1] == width and nx.shape[0] <= MAX_REFIT_ROWS and (nx.size == 0 or _finite(nx)), path,
          f"novelty_x: must be (n, {width}) finite floats, at most {MAX_REFIT_ROWS} rows")
    _need(isinstance(nov.get("k"), int) and not isinstance(nov.get("k"), bool) and 1 <= nov["k"] <= 100, path,
          "header.novelty.k: must be an integer in 1..100")
    threshold = nov.get("threshold")
    _need(threshold is None or (_is_number(threshold) and threshold > 0), path, "header.novelty.threshold: must be a number > 0 or null")
    if "novelty_y" in arrays:
        ny, groups = arrays["novelty_y"], arrays["novelty_groups"]
        _need(ny.shape == (nx.shape[0],) and ny.dtype.kind == "U" and groups.shape == (nx.shape[0],) and groups.dtype.kind == "i", path,
              "novelty_y, novelty_groups: must be one unicode label and one integer per novelty_x row")
        model.novelty_y, model.novelty_groups = ny, groups
    version = header.get("version", 0)
    score = nov.get("score", "distance") if version >= 5 else "distance"
    scores = NOVELTY_SCORES if version >= 6 else ("ratio", "distance")  # combined: format 6
    _need(score in scores, path, f"header.novelty.score: must be one of {', '.join(scores)}")
    far = nov.get("distance_threshold") if version >= 6 else None
    _need(far is None or (_is_number(far) and far > 0), path, "header.novelty.distance_threshold: must be a number > 0 or null")
    _need(score != "combined" or model.novelty_y is not None, path, "novelty_y: a combined novelty score needs each slide's surface")
    model.calibration, model.novelty_x, model.novelty_k, model.novelty_score = cal, nx, int(nov["k"]), score
    model.novelty_distance_threshold = float(far) if far is not None else math.inf
    early = header.get("early_calibration")
    _need(early is None or (isinstance(early, list) and len(early) == 3 and all(_is_number(v) for v in early)), path,
          "header.early_calibration: must be three finite numbers or null")
    model.early_calibration = (float(early[0]), float(early[1]), float(early[2])) if early is not None else None
    model.novelty_threshold = float(threshold) if threshold is not None else math.inf


MAX_CLASSES = 10_000  # classes a model file may hold
EARLY_BOUNDS = (0.01, 0.99)  # a provisional label's confidence never leaves these, whatever the model's final map allows


def optimistic_reason(nested: dict[str, Any]) -> str | None:
    """Why a nested CV accuracy (a model's ``cv_accuracy``, search's ``nested``) is optimistic, in the words
    :meth:`Model.describe` and ``evaluate``'s report say it, or None."""
    if nested.get("grouped_by") == "slide":
        return "train --group-by slide: the folds split recordings"
    if nested.get("inner_grouped_by") == "none":
        return "one slide of a surface in a fold: no choice inside it"
    return None


def early_probability(coef: Sequence[float], p_top: float, windows: int, bounds: tuple[float, float] = EARLY_BOUNDS) -> float:
    """P(label right) of a label from the first ``windows`` windows of a slide with top softmax probability ``p_top``:
    sigmoid(a logit(p_top) + b log(windows) + c), ``coef`` = (a, b, c) (Platt scaling with the window count as a second
    input, fitted in training on out-of-fold prefixes of slides), kept within ``bounds`` (:meth:`Model.early_bounds`: those
    of the final map, within :data:`EARLY_BOUNDS`): a few windows never make a label certain, nor surer than the whole slide
    could be."""
    a, b, c = coef
    q = min(max(p_top, 1e-6), 1 - 1e-6) if math.isfinite(p_top) else 0.5
    z = a * math.log(q / (1 - q)) + b * math.log(max(windows, 1)) + c
    return min(max(1.0 / (1.0 + math.exp(-min(max(z, -700.0), 700.0))), bounds[0]), bounds[1])


def pairwise_distances(z: FloatArray, train: FloatArray, alone: bool = False) -> FloatArray:
    """(q, n) Euclidean distances between the rows of ``z`` (q, F) and of ``train`` (n, F); ``alone``: each row bit for bit
    that of the row alone (:func:`row_dots`, :func:`rowwise_matmul`; else one matrix product)."""
    zz = row_dots(z, z) if alone else (z * z).sum(axis=1)  # numpy sums the rows of a block in another order than one row
    d2 = zz[:, None] - (rowwise_matmul if alone else np.matmul)(2.0 * z, train.T) + (train * train).sum(axis=1)[None, :]
    return np.sqrt(np.maximum(d2, 0.0))


def _nearest_mean(d: FloatArray, k: int) -> FloatArray:
    """(q,) mean of the ``k`` smallest of each row of ``d`` (q, n) (k capped at n)."""
    k = max(1, min(k, d.shape[1]))
    out: FloatArray = np.partition(d, k - 1, axis=1)[:, :k].mean(axis=1)
    return out


def knn_distance(z: FloatArray, train: FloatArray, k: int, alone: bool = False) -> FloatArray:
    """(q,) mean Euclidean distance of each row of ``z`` (q, F) to its ``k`` nearest rows of ``train`` (n, F) (k capped at n);
    ``alone``: each row bit for bit that of the row alone."""
    return _nearest_mean(pairwise_distances(z, train, alone), k)


NOVELTY_SCORES = ("ratio", "distance", "combined")


def novelty_parts(z: FloatArray, train: FloatArray, labels: npt.NDArray[Any] | None, k: int, score: str = "ratio",
                  alone: bool = False, groups: SurfaceGroups | None = None, scale: FloatArray | None = None) -> FloatArray:
    """(q, 2) how unlike the training rows ``train`` (n, F) (surfaces ``labels`` (n,)) each row of ``z`` (q, F) is: the
    score, and the distance to the nearest taught surface (mean over its ``k`` nearest rows).

    ``distance``: the score is the mean distance to the ``k`` nearest training rows (both columns). ``ratio`` and
    ``combined``: the nearest-neighbour distance ratio (Mendes Junior et al., "Nearest neighbors distance ratio open-set
    classifier", Machine Learning 2017): the distance to the nearest surface over the same for the next nearest surface,
    in [0, 1]. Near 0: clearly one taught surface; near 1: between two of them, or far from all (both distances large).
    Unlike a distance, the ratio takes its scale from how far apart the surfaces are, not from how close recordings of
    one surface were in training, so a sensor that is shifted as a whole (another unit, a new sheet of a grade) keeps
    the slides it can still tell apart. With fewer than two surfaces in ``labels`` (or none given), the distance.
    ``alone``: each row bit for bit that of the row alone (:func:`rowwise_matmul`; else one matrix product, the same to rounding);
    ``groups``: :func:`surface_groups` of ``labels``, when the caller keeps it; ``scale``: each surface's distances over its
    own (:func:`nearest_surface_distances`).
    """
    if labels is None or score == "distance":
        d = knn_distance(np.asarray(z, dtype=np.float64), np.asarray(train, dtype=np.float64), k, alone)
        return np.column_stack([d, d])
    per = nearest_surface_distances(z, train, labels, k, alone, groups, scale)
    ratio = np.where(np.isfinite(per[:, 1]), per[:, 0] / np.maximum(per[:, 1], 1e-300), per[:, 0])
    return np.column_stack([ratio, per[:, 0]])


def novelty_scores(z: FloatArray, train: FloatArray, labels: npt.NDArray[Any] | None, k: int, score: str = "ratio") -> FloatArray:
    """(q,) the score column of :func:`novelty_parts`."""
    out: FloatArray = novelty_parts(z, train, labels, k, score)[:, 0]
    return out


def over_thresholds(parts: FloatArray, threshold: float, distance_threshold: float | FloatArray = math.inf) -> FloatArray:
    """(q,) the novelty of :func:`novelty_parts` rows (q, 2), above 1: unknown. The larger of the score over ``threshold``
    and the distance to the nearest surface over ``distance_threshold`` (``combined``): a slide is unknown when it lies
    between taught surfaces (ratio near 1) or farther from every taught surface than they lie from one another (the ratio
    alone misses that when one surface is much nearer than the next). ``distance_threshold``: one, or one per row (q,). An
    infinite threshold contributes 0."""
    out: FloatArray = np.maximum(parts[:, 0] / threshold, parts[:, 1] / distance_threshold)
    return out


def surface_scale_for(surfaces: npt.NDArray[Any], scale: FloatArray, labels: npt.NDArray[Any]) -> FloatArray:
    """(S',) the ``scale`` of ``surfaces`` (S,) (sorted) for the surfaces of ``labels`` in sorted order (a subset of them)."""
    out: FloatArray = scale[np.searchsorted(surfaces, np.unique(labels))]
    return out


def surface_groups(labels: npt.NDArray[Any]) -> SurfaceGroups:
    """The training rows of each of the S surfaces of ``labels`` (n,), in sorted surface order: (columns (S, m): each surface's
    row numbers in order, padded with n, m its largest count; counts (S,))."""
    _, codes = np.unique(labels, return_inverse=True)
    codes = codes.reshape(-1)
    counts = np.bincount(codes)
    order = np.argsort(codes, kind="stable")
    columns = np.full((len(counts), max(int(counts.max(initial=0)), 1)), len(codes), dtype=np.intp)
    columns[codes[order], np.arange(len(codes)) - (np.cumsum(counts) - counts)[codes[order]]] = order
    return columns, counts


def nearest_surface_distances(z: FloatArray, train: FloatArray, labels: npt.NDArray[Any], k: int, alone: bool = False,
                              groups: SurfaceGroups | None = None, scale: FloatArray | None = None) -> FloatArray:
    """(q, 2) for each row of ``z`` (q, F): the mean distance to the ``k`` nearest training rows (``train`` (n, F)) of the
    nearest surface (``labels`` (n,)), and the same for the next nearest surface (inf with a single surface); ``alone``:
    each row bit for bit that of the row alone; ``groups``: :func:`surface_groups` of ``labels``, when the caller keeps it;
    ``scale`` (S,): each surface's distances divided by its own (the surfaces in sorted order, :func:`surface_scale_for`)."""
    per = surface_distances(z, train, labels, k, alone, groups)
    per = np.sort(per / scale[None, :] if scale is not None else per, axis=1)
    out: FloatArray = np.column_stack([per[:, 0], per[:, 1] if per.shape[1] > 1 else np.full(len(per), np.inf)])
    return out


def surface_distances(z: FloatArray, train: FloatArray, labels: npt.NDArray[Any], k: int, alone: bool = False,
                      groups: SurfaceGroups | None = None) -> FloatArray:
    """(q, S) for each row of ``z`` (q, F), the mean distance to the ``k`` nearest training rows (``train`` (n, F)) of each
    of the S surfaces of ``labels`` (n,), in sorted order; ``alone`` and ``groups`` as :func:`nearest_surface_distances`."""
    d = pairwise_distances(np.asarray(z, dtype=np.float64), np.asarray(train, dtype=np.float64), alone)
    columns, counts = groups if groups is not None else surface_groups(labels)
    return _nearest_per_surface(d, columns, counts, k)


def _nearest_per_surface(d: FloatArray, columns: npt.NDArray[np.intp], counts: npt.NDArray[np.intp], k: int) -> FloatArray:
    """(q, S) the mean of the ``k`` smallest distances of each surface in each row of ``d`` (q, n) (:func:`surface_groups`'
    ``columns`` and ``counts``; k capped at the surface's rows), all rows at once: each surface's distances in a row of its
    own (padded with inf), sorted, the k smallest summed in ascending order from 0."""
    nearest = np.sort(np.concatenate([d, np.full((d.shape[0], 1), np.inf)], axis=1)[:, columns], axis=2)
    take = np.minimum(k, counts)
    total = np.zeros(nearest.shape[:2])
    for j in range(int(take.max(initial=0))):
        total = total + (nearest[:, :, j] if j < take.min() else np.where(j < take, nearest[:, :, j], 0.0))
    out: FloatArray = total / np.maximum(take, 1)
    return out


def _probe(path: Path, model: Model) -> None:
    """One window of seeded noise through the model's whole analysis and classifier, as the daemon runs them: it must give a probability."""
    s = model.settings
    noise = np.random.default_rng(0).standard_normal((round(s.duration_s * model.fs), model.channels)) * 0.01
    try:
        window = Analyser(s, model.fs, 1.0, integer=False).analyse(noise)
        _need(window.features is not None, path, f"probe window: no features ({window.reason})")
        assert window.features is not None
        two = np.stack([window.features, window.features * 1.5])
        scores = model.scores(two)
        partner = model.partner.scores(take_columns(two, model.names, model.partner.names)) if model.partner is not None else scores
        p, confidence, novelty = model.assess(two)
    except (ValueError, FloatingPointError, ArithmeticError, IndexError, TypeError) as exc:
        raise ModelError(f"{path}: probe prediction failed: {exc}") from None
    _need(scores.shape == partner.shape == (2, len(model.classes)) and bool(np.all(np.isfinite(scores)) and np.all(np.isfinite(partner))), path,
          "probe prediction: scores are not finite" + (" (the partner's or the first member's)" if model.partner is not None else ""))
    _need(bool(np.all(np.isfinite(p))) and abs(float(p.sum()) - 1.0) < 1e-6, path, "probe prediction is not a finite probability")
    _need(0.0 <= confidence <= 1.0 and (novelty is None or math.isfinite(novelty)), path, "probe prediction: confidence or novelty not finite")


def _sklearn_pipeline(names: tuple[str, ...], kind: str, params: dict[str, Any], seed: int, classes: list[str], arrays: dict[str, Any]) -> Any:
    """The scikit-learn pipeline of one member's (already checked) arrays over its features ``names``; kNN and SVM are refitted on
    the stored training set."""
    f = len(names)
    pipe = make_pipeline(names, kind, params, seed)
    scaler, clf = pipe.named_steps["scale"], pipe.named_steps["clf"]
    mean, scale = arrays["scaler_mean"], arrays["scaler_scale"]
    scaler.mean_, scaler.scale_, scaler.var_ = mean, scale, scale**2
    scaler.n_features_in_, scaler.n_samples_seen_ = f, 1
    if kind == "elm":
        clf.weights_, clf.biases_, clf.beta_ = arrays["weights"], arrays["biases"], arrays["beta"]
        clf.temperature_, clf.classes_, clf.n_features_in_ = float(arrays["elm_temperature"]), np.array(classes), f
    elif kind == "linear":
        clf.coef_, clf.intercept_, clf.classes_, clf.n_features_in_ = arrays["coef"], arrays["intercept"], np.array(classes), f
    else:
        clf.fit(arrays["train_x"], arrays["train_y"])
    return pipe
