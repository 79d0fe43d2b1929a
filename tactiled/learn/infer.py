"""Lean inference: a saved model's pipeline evaluated with numpy from its file's arrays, without importing scikit-learn.

    raw features (n, F) ─▶ log10 of the scale features ─▶ (x − scaler_mean) / scaler_scale ─▶ classifier scores (n, K')

The scores are those of :func:`tactiled.learn.model.decision_scores` on the scikit-learn pipeline the
same file loads into (equal to rounding; tests/test_infer.py checks 1e-9), columns in the
classifier's class order :attr:`LeanPipeline.classes_` (the file's classes for elm and linear,
the sorted training labels for knn and svm, as scikit-learn orders them):

- elm: H = σ(z·W + b), s = H·β; K ≥ 3 classes: the first K columns of s; 2 classes: ±(s₁ − s₀)/4
  (scikit-learn's binary decision value d = (s₁ − s₀)/2, as ±d/2); 1 class: 0.
- linear: d = z·coefᵀ + intercept; 2 classes (one row): ±d/2.
- knn: the fraction p of each class among the ``n_neighbors`` nearest training rows (Euclidean,
  uniform weights), as log(max(p, 1e-3)).
- svm: the fitted support vectors (rows ``svm_support`` of ``train_x``), ``svm_dual_coef``
  (K − 1, n_SV), ``svm_intercept`` (K(K − 1)/2,), ``svm_n_support`` (K,) and ``svm_gamma``
  (libsvm's one-vs-one decision values, with scikit-learn's public signs); 2 classes: ±d/2;
  more: scikit-learn's one-vs-rest votes plus confidences/(3(|confidences| + 1)).

:func:`lean_pipeline` returns None when the file lacks what numpy needs (an svm model saved
before its fitted arrays were stored, a ``kbest`` selector): the model then loads through
scikit-learn.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from tactiled.core.features import classifier_inputs, rowwise_matmul

FloatArray = npt.NDArray[np.float64]
SVM_ARRAYS = ("svm_support", "svm_dual_coef", "svm_intercept", "svm_n_support", "svm_gamma")


def pm_half(d: FloatArray) -> FloatArray:
    """A binary decision value (n,) as the two columns (−d/2, d/2)."""
    return np.stack([-d / 2, d / 2], axis=1)


def log_proba(p: FloatArray) -> FloatArray:
    """Scores from probabilities: their log, floored at 1e-3 (so one window can never veto a class)."""
    return np.asarray(np.log(np.clip(p, 1e-3, None)), dtype=np.float64)


def sigmoid(z: FloatArray) -> FloatArray:
    """The logistic sigmoid, overflow-free (through tanh): an ELM's hidden layer."""
    out: FloatArray = 0.5 * (1.0 + np.tanh(0.5 * z))
    return out


class LeanPipeline:
    """The log → scale → classifier chain of one model file, as numpy arrays (see the module docstring)."""

    def __init__(self, kind: str, names: tuple[str, ...] | list[str], classes_: npt.NDArray[np.str_], mean: FloatArray, scale: FloatArray,
                 arrays: dict[str, Any], params: dict[str, Any]) -> None:
        self.kind = kind
        self.names = list(names)
        self.classes_ = classes_
        self.mean = mean
        self.scale = scale
        self.arrays = arrays  # the file's arrays, so a lean model saves as it loaded
        self.params = params
        if kind == "svm":
            support = np.asarray(arrays["svm_support"])
            self._sv = np.ascontiguousarray(arrays["train_x"][support])
            self._sv_sq = np.einsum("ij,ij->i", self._sv, self._sv)
            k = len(classes_)
            n_support = np.asarray(arrays["svm_n_support"], dtype=np.int64)
            starts = np.concatenate([[0], np.cumsum(n_support)])
            pairs = [(i, j) for i in range(k) for j in range(i + 1, k)]
            # one (n_SV, pairs) matrix: column p holds class i's coefficients against j and class j's against i
            coef = np.zeros((self._sv.shape[0], len(pairs)))
            dual = np.asarray(arrays["svm_dual_coef"], dtype=np.float64)
            for p, (i, j) in enumerate(pairs):
                coef[starts[i]:starts[i + 1], p] = dual[j - 1, starts[i]:starts[i + 1]]
                coef[starts[j]:starts[j + 1], p] = dual[i, starts[j]:starts[j + 1]]
            self._pair_coef = coef
            self._first, self._second = pair_matrices(k)
        elif kind == "knn":  # what depends on the training rows only, once per model rather than per query
            train_x = arrays["train_x"]
            self._train_sq = (train_x * train_x).sum(axis=1)
            self._train_label = np.searchsorted(classes_, arrays["train_y"])  # class index of every training row

    def transform(self, x: npt.ArrayLike) -> FloatArray:
        """Standardised classifier inputs (n, F) of raw features ``x`` (n, F)."""
        z: FloatArray = (classifier_inputs(np.asarray(x, dtype=np.float64), self.names) - self.mean) / self.scale
        return z

    def scores(self, x: npt.ArrayLike, alone: bool = False) -> FloatArray:
        """Scores (n, K') of raw features ``x`` (n, F), columns in :attr:`classes_` order, higher is likelier.

        ``alone``: each row's scores bit for bit those of the row alone (``scores(x[i:i + 1])``; :func:`rowwise_matmul`),
        whatever the other rows; else one matrix product for all rows (the same to rounding)."""
        z = self.transform(x)
        a = self.arrays
        k = len(self.classes_)
        mm = rowwise_matmul if alone else np.matmul
        if self.kind == "elm":
            s = mm(sigmoid(mm(z, a["weights"]) + a["biases"]), a["beta"])
            if k == 1:
                return np.zeros((z.shape[0], 1))
            return pm_half((s[:, 1] - s[:, 0]) / 2) if k == 2 else np.asarray(s[:, :k], dtype=np.float64)
        if self.kind == "linear":
            d = mm(z, np.asarray(a["coef"], dtype=np.float64).T) + a["intercept"]
            return pm_half(d[:, 0]) if k == 2 else np.asarray(d, dtype=np.float64)
        if self.kind == "knn":
            return self._knn(z, mm)
        return self._svm(z, mm)

    def _knn(self, z: FloatArray, mm: Callable[[FloatArray, FloatArray], FloatArray]) -> FloatArray:
        train_x = self.arrays["train_x"]
        n = int(self.params.get("n_neighbors", 9))
        d = (z * z).sum(axis=1)[:, None] - mm(2.0 * z, train_x.T) + self._train_sq[None, :]
        nearest = np.argpartition(d, n - 1, axis=1)[:, :n] if n < train_x.shape[0] else np.broadcast_to(np.arange(train_x.shape[0]), d.shape)
        label = self._train_label[nearest]  # (q, n) class indices
        p = np.stack([(label == c).sum(axis=1) for c in range(len(self.classes_))], axis=1) / n
        return log_proba(p)

    def _svm(self, z: FloatArray, mm: Callable[[FloatArray, FloatArray], FloatArray]) -> FloatArray:
        gamma = float(self.arrays["svm_gamma"])
        if self.params.get("kernel", "rbf") == "linear":
            kern = mm(z, self._sv.T)
        else:
            sq = (z * z).sum(axis=1)[:, None] - mm(2.0 * z, self._sv.T) + self._sv_sq[None, :]
            kern = np.exp(-gamma * np.maximum(sq, 0.0))
        dec = mm(kern, self._pair_coef) + self.arrays["svm_intercept"]
        if len(self.classes_) == 2:
            return pm_half(dec[:, 0])
        return pairwise_scores(dec, self._first, self._second, mm)


def pair_matrices(k: int) -> tuple[FloatArray, FloatArray]:
    """(first, second), each (k(k-1)/2, k): pair p of a one-vs-one classifier (pairs (0, 1), (0, 2), ..., (k-2, k-1), as
    libsvm orders them) -> a one in the column of its first class, and of its second class."""
    pairs = [(i, j) for i in range(k) for j in range(i + 1, k)]
    first, second = np.zeros((len(pairs), k)), np.zeros((len(pairs), k))
    for p, (i, j) in enumerate(pairs):
        first[p, i] = second[p, j] = 1.0
    return first, second


def pairwise_scores(dec: FloatArray, first: FloatArray, second: FloatArray,
                    mm: Callable[[FloatArray, FloatArray], FloatArray] = np.matmul) -> FloatArray:
    """Class scores (n, k) of one-vs-one decision values ``dec`` (n, pairs) (> 0: the pair's first class): each class's
    mean log-sigmoid of its margins against the others, log σ(2 d), a soft count of the duels it wins.

    Vote counts carry no confidence (the top class of 15 nearly always has 14 votes); a plain sum of margins lets
    the duels against far-away classes outweigh the close one that decides. The log-sigmoid saturates for a duel
    won by far and penalises one lost, and it grades how clearly the slide won. Its argmax is not always the vote's
    (``SVC.predict``): a narrow win costs nearly as much as a narrow loss (log σ(0.2) = -0.60, log σ(-0.2) = -0.80),
    so a class that wins every duel narrowly can score below one that loses to it narrowly and wins the rest by far.
    On the simulator's scenes (15 surfaces, bench/labels.py's data sets) the top class differs from the vote on about
    11 % of test slides and is right 1.6 ± 0.5 points less often than the vote on other units of the sensor (0.7 to
    1.6 points on the same unit).
    ``mm``: the matrix product (:func:`rowwise_matmul`: each row as alone).
    """
    k = first.shape[1]
    win, lose = -np.logaddexp(0.0, -2.0 * dec), -np.logaddexp(0.0, 2.0 * dec)  # log σ(2d), log σ(-2d)
    out: FloatArray = (mm(win, first) + mm(lose, second)) / max(k - 1, 1)
    return out


def svm_arrays(clf: Any) -> dict[str, Any]:
    """The arrays of a fitted scikit-learn SVC that :class:`LeanPipeline` evaluates (stored in svm model files)."""
    return {"svm_support": np.asarray(clf.support_, dtype=np.int64), "svm_dual_coef": np.asarray(clf.dual_coef_, dtype=np.float64),
            "svm_intercept": np.asarray(clf.intercept_, dtype=np.float64), "svm_n_support": np.asarray(clf.n_support_, dtype=np.int64),
            "svm_gamma": np.float64(clf._gamma)}


def lean_pipeline(kind: str, names: tuple[str, ...] | list[str], classes: list[str], params: dict[str, Any],
                  arrays: dict[str, Any]) -> LeanPipeline | None:
    """The lean pipeline of a model file's (already checked) arrays, or None if numpy alone cannot evaluate it.

    Raises ValueError if the svm arrays are inconsistent with the training set.
    """
    if 0 < int(params.get("kbest", 0)) < len(names):
        return None  # the selector's columns are not stored
    mean = np.asarray(arrays["scaler_mean"], dtype=np.float64)
    scale = np.asarray(arrays["scaler_scale"], dtype=np.float64)
    if kind in ("elm", "linear"):
        return LeanPipeline(kind, names, np.array(classes), mean, scale, arrays, params)
    classes_ = np.unique(arrays["train_y"]).astype(np.str_)
    if kind == "knn":
        return LeanPipeline(kind, names, classes_, mean, scale, arrays, params)
    if not all(key in arrays for key in SVM_ARRAYS):
        return None
    n_train, k = arrays["train_x"].shape[0], len(classes_)
    support, n_support = np.asarray(arrays["svm_support"]), np.asarray(arrays["svm_n_support"])
    dual, intercept = np.asarray(arrays["svm_dual_coef"]), np.asarray(arrays["svm_intercept"])
    gamma = np.asarray(arrays["svm_gamma"])
    ok = (support.ndim == 1 and support.dtype.kind == "i" and support.size >= 1 and int(support.min()) >= 0 and int(support.max()) < n_train
          and n_support.shape == (k,) and n_support.dtype.kind == "i" and int(n_support.min()) >= 0 and int(n_support.sum()) == support.size
          and dual.shape == (max(k - 1, 1), support.size) and intercept.shape == (max(k * (k - 1) // 2, 1),) and gamma.shape == ()
          and dual.dtype.kind == intercept.dtype.kind == gamma.dtype.kind == "f"
          and bool(np.all(np.isfinite(dual))) and bool(np.all(np.isfinite(intercept))) and bool(np.isfinite(gamma)) and float(gamma) > 0)
    if not ok:
        raise ValueError("svm_support, svm_n_support, svm_dual_coef, svm_intercept, svm_gamma: shapes or values do not match the training set")
    return LeanPipeline(kind, names, classes_, mean, scale, arrays, params)
