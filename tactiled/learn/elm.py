"""Extreme learning machine classifier, a scikit-learn estimator.

H = σ(X·W + b) with W ~ N(0, 1)·3/√d and b ~ N(0, 1) (hpelm's initialisation: steep
enough to resolve 15 classes along one z-scored feature, yet not saturated in d
dimensions), seeded; targets one-hot mapped to ±1; output weights β solve
the ridge problem min ‖Hβ − T‖² + λ‖β‖² with λ = alpha·trace(HᵀH)/L by Cholesky of
HᵀH + λI, falling back to SVD least squares of the augmented system if Cholesky fails;
never an explicit inverse. Inputs are expected standardised (the model pipeline does it).

``predict_proba`` is a softmax of the decision values with a temperature fitted by
minimising the log loss of out-of-fold decision values (internal stratified CV during
``fit``), i.e. temperature scaling, so probabilities are calibrated on unseen data.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy import linalg, optimize
from sklearn.base import BaseEstimator, ClassifierMixin
from sklearn.model_selection import StratifiedKFold
from sklearn.utils.multiclass import check_classification_targets
from sklearn.utils.validation import check_is_fitted, validate_data

from tactiled.learn.infer import sigmoid

FloatArray = npt.NDArray[np.float64]


def _softmax(z: FloatArray) -> FloatArray:
    z = z - z.max(axis=1, keepdims=True)
    e = np.exp(z)
    out: FloatArray = e / e.sum(axis=1, keepdims=True)
    return out


def ridge_solve(h: FloatArray, t: FloatArray, alpha: float) -> FloatArray:
    """β (L, K) minimising ‖hβ − t‖² + λ‖β‖², λ = alpha·trace(hᵀh)/L: Cholesky, SVD fallback.

    ``alpha = 0`` gives the minimum-norm least-squares solution (the pseudo-inverse of the
    papers' plain ELM) by SVD, never a normal-equations inverse.
    """
    if alpha == 0:
        plain: FloatArray = linalg.lstsq(h, t, lapack_driver="gelsd")[0]
        return plain
    hth = h.T @ h
    lam = alpha * max(float(np.trace(hth)) / hth.shape[0], 1e-12)
    try:
        c = linalg.cho_factor(hth + lam * np.eye(hth.shape[0]), check_finite=True)
        beta: FloatArray = linalg.cho_solve(c, h.T @ t)
        if np.all(np.isfinite(beta)):
            return beta
    except (linalg.LinAlgError, ValueError):
        pass
    aug = np.vstack([h, np.sqrt(lam) * np.eye(h.shape[1])])
    rhs = np.vstack([t, np.zeros((h.shape[1], t.shape[1]))])
    beta = linalg.lstsq(aug, rhs, lapack_driver="gelsd")[0]
    return beta


class ELMClassifier(ClassifierMixin, BaseEstimator):  # type: ignore[misc]
    """Extreme learning machine: ``n_hidden`` sigmoid units, ridge ``alpha``, seeded ``random_state``.

    Follows the scikit-learn estimator contract (``check_estimator`` passes): parameters
    stored in ``__init__``, learned attributes ending in ``_``, ``fit`` returns self. For two
    classes ``decision_function`` returns (n,) (positive means ``classes_[1]``), else (n, K).
    """

    def __init__(self, n_hidden: int = 200, alpha: float = 1e-6, random_state: int = 0, calibrate: bool = True, init: str = "hpelm") -> None:
        self.n_hidden = n_hidden
        self.alpha = alpha
        self.init = init
        self.random_state = random_state
        self.calibrate = calibrate

    def _hidden(self, x: FloatArray) -> FloatArray:
        return sigmoid(np.asarray(x, dtype=np.float64) @ self.weights_ + self.biases_)

    def _fit_core(self, x: FloatArray, y_idx: npt.NDArray[np.intp], n_classes: int) -> None:
        rng = np.random.default_rng(self.random_state)
        d = x.shape[1]
        if self.init == "huang":  # Huang's reference code: W ~ U(-1, 1), b ~ U(0, 1)
            self.weights_ = rng.uniform(-1.0, 1.0, (d, self.n_hidden))
            self.biases_ = rng.uniform(0.0, 1.0, self.n_hidden)
        else:
            self.weights_ = rng.standard_normal((d, self.n_hidden)) * (3.0 / np.sqrt(max(d, 1)))
            self.biases_ = rng.standard_normal(self.n_hidden)
        t = -np.ones((x.shape[0], n_classes))
        t[np.arange(x.shape[0]), y_idx] = 1.0
        self.beta_ = ridge_solve(self._hidden(x), t, self.alpha)

    def fit(self, X: npt.ArrayLike, y: npt.ArrayLike) -> ELMClassifier:
        """Fit on X (n, F) and labels y (n,); with ``calibrate``, the softmax temperature from out-of-fold decision values. Returns self."""
        if not (isinstance(self.n_hidden, (int, np.integer)) and 1 <= self.n_hidden <= 100_000):
            raise ValueError(f"n_hidden must be an integer in 1..100000, got {self.n_hidden!r}")
        if not (np.isfinite(self.alpha) and self.alpha >= 0):
            raise ValueError(f"alpha must be finite and >= 0, got {self.alpha!r}")
        if self.init not in ("hpelm", "huang"):
            raise ValueError(f"init must be 'hpelm' or 'huang', got {self.init!r}")
        x: FloatArray
        x, y = validate_data(self, X, y, dtype=np.float64, y_numeric=False)
        with warnings.catch_warnings():  # few slides per class in a small fold is expected here, not a regression problem
            warnings.filterwarnings("ignore", message="The number of unique classes is greater than 50%", category=UserWarning)
            check_classification_targets(y)
        self.classes_, y_idx = np.unique(y, return_inverse=True)
        k = max(len(self.classes_), 2)  # one class: two outputs, so the solver and the softmax stay well defined
        self.temperature_ = 1.0
        if self.calibrate and len(self.classes_) > 1:
            counts = np.bincount(y_idx)
            folds = min(5, int(counts.min()))
            if folds >= 2:
                scores = np.zeros((x.shape[0], k))
                for tr, te in StratifiedKFold(folds, shuffle=True, random_state=self.random_state).split(x, y_idx):
                    self._fit_core(x[tr], y_idx[tr], k)
                    scores[te] = self._hidden(x[te]) @ self.beta_

                def nll(log_t: float) -> float:
                    p = _softmax(scores / np.exp(log_t))
                    return float(-np.mean(np.log(np.clip(p[np.arange(len(y_idx)), y_idx], 1e-12, None))))

                res = optimize.minimize_scalar(nll, bounds=(-6.0, 4.0), method="bounded")
                self.temperature_ = float(np.exp(res.x))
        self._fit_core(x, y_idx, k)
        return self

    def _scores(self, x: npt.ArrayLike) -> FloatArray:
        """Decision values (n, K) for every class (K >= 2)."""
        check_is_fitted(self, "beta_")
        z: FloatArray = validate_data(self, x, dtype=np.float64, reset=False)
        out: FloatArray = self._hidden(z) @ self.beta_
        return out

    def decision_function(self, x: npt.ArrayLike) -> FloatArray:
        """Decision values of x (n, F): (n,) for two classes (positive means ``classes_[1]``), else (n, K)."""
        scores = self._scores(x)
        if len(self.classes_) == 2:
            binary: FloatArray = (scores[:, 1] - scores[:, 0]) / 2
            return binary
        return scores[:, : len(self.classes_)]

    def predict_proba(self, x: npt.ArrayLike) -> FloatArray:
        """Probabilities (n, K) of x (n, F): softmax of the decision values at the fitted temperature ((n, 1) of ones for one class)."""
        scores = self._scores(x)
        if len(self.classes_) == 1:
            return np.ones((scores.shape[0], 1))
        return _softmax(scores / self.temperature_)

    def predict(self, x: npt.ArrayLike) -> npt.NDArray[Any]:
        """Labels (n,) of x (n, F): the class with the largest decision value."""
        scores = self._scores(x)
        out: npt.NDArray[Any] = self.classes_[np.argmax(scores[:, : len(self.classes_)], axis=1)]
        return out
