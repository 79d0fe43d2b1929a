"""Lean inference (tactiled/learn/infer.py) against the scikit-learn pipeline the same file loads into."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tactiled.core.analysis import AnalysisSettings
from tactiled.core.features import is_log_feature
from tactiled.learn.infer import LeanPipeline
from tactiled.learn.model import Model, fit_pipeline, load_model

NAMES = ("film1.time.D1.sd", "film1.time.D2.energy", "film1.time.A1.mean", "film2.freq.D3.kurt", "film2.psd.100-126Hz.power")


def _raw(z: np.ndarray, model: Model) -> np.ndarray:
    """Raw features (n, F) of the model's analysis whose standardised classifier inputs are ``z`` (the inverse of log → scale
    on the classifier's columns; 1 in the columns only the novelty reads)."""
    arrays = model._arrays()
    own = z * arrays["scaler_scale"] + arrays["scaler_mean"]
    logs = np.array([is_log_feature(n) for n in model.inputs])
    own[:, logs] = 10.0 ** own[:, logs]
    x = np.ones((len(z), len(model.names)))
    x[:, [model.names.index(n) for n in model.inputs]] = own
    return x


@pytest.mark.parametrize("kind", ["elm", "linear", "knn", "svm"])
@pytest.mark.parametrize("classes", [2, 5])
def test_lean_equals_sklearn(kind: str, classes: int, tmp_path: Path) -> None:
    rng = np.random.default_rng(classes)
    y = np.repeat([f"s{i}" for i in range(classes)], 30)
    centre = np.repeat(np.arange(classes), 30)[:, None] * 0.4
    x = np.exp(rng.standard_normal((len(y), len(NAMES))) * 0.5 + centre - 4)
    x[:, 2] = rng.standard_normal(len(y)) + centre[:, 0]  # a mean: not a log feature
    params = {"n_neighbors": 7} if kind == "knn" else {"n_hidden": 40} if kind == "elm" else {}
    pipe, refit = fit_pipeline(x, y, NAMES, kind, params, seed=3)
    model = Model("test", kind, params, [str(c) for c in pipe[-1].classes_], AnalysisSettings(duration_s=0.5, names=NAMES), 20000.0, 2,
                  pipe, 0.8, 3, {}, "", refit)
    path = tmp_path / "m.npz"
    model.save(path)
    lean, ref = load_model(path), load_model(path, lean=False)
    assert isinstance(lean.pipeline, LeanPipeline) and not isinstance(ref.pipeline, LeanPipeline)
    query = np.vstack([np.exp(rng.standard_normal((60, len(NAMES))) * 0.7 + rng.uniform(-4.5, -2.5)), x[:20] * 1.01])
    query[:, 2] = rng.standard_normal(len(query)) * 2
    np.testing.assert_allclose(lean.scores(query), ref.scores(query), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(lean.predict_proba(query), ref.predict_proba(query), rtol=0, atol=1e-9)
    np.testing.assert_allclose(lean.slide_proba(query[:5]), ref.slide_proba(query[:5]), rtol=0, atol=1e-9)
    # a lean model saves to the same file it loaded from
    assert lean.save(tmp_path / "again.npz") == model.fingerprint


def test_shipped_model_lean_on_its_training_set() -> None:
    """The shipped model, evaluated by numpy, gives the scikit-learn pipeline's probabilities on the windows it was trained on."""
    lean, ref = load_model(), load_model(lean=False)
    assert isinstance(lean.pipeline, LeanPipeline)
    x = _raw(lean._arrays()["train_x"], lean)
    p, q = lean.predict_proba(x), ref.predict_proba(x)
    np.testing.assert_allclose(p, q, rtol=0, atol=1e-9)
    assert (lean.predict(x) == ref.predict(x)).all()


def test_loading_the_shipped_model_imports_neither_sklearn_nor_scipy() -> None:
    code = ("import sys; from tactiled.learn.model import load_model; from tactiled.core.pipeline import Pipeline; m = load_model(); "
            "print(sorted({k.split('.')[0] for k in sys.modules} & {'sklearn', 'scipy'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_svm_file_without_fitted_arrays_loads_through_sklearn(tmp_path: Path) -> None:
    """An svm file saved before the fitted arrays were stored still loads (refitted by scikit-learn)."""
    from tactiled.files.recording import atomic_savez

    model = load_model(lean=False)
    arrays = {k: v for k, v in {**model._arrays(), **model._trust_arrays()}.items() if not k.startswith("svm_")}
    header = model._header()
    from tactiled.learn.model import _fingerprint

    header["fingerprint"] = _fingerprint(header, arrays)
    import json

    path = tmp_path / "old.npz"
    atomic_savez(path, {"header": np.str_(json.dumps(header, sort_keys=True)), **arrays})
    old = load_model(path)
    assert not isinstance(old.pipeline, LeanPipeline)
    x = _raw(arrays["train_x"][:50], model)
    np.testing.assert_allclose(old.predict_proba(x), load_model().predict_proba(x), rtol=0, atol=1e-9)


def test_svm_soft_count_is_not_always_the_vote() -> None:
    """pairwise_scores' argmax can differ from the one-vs-one vote (SVC.predict), as its docstring says: a class that wins
    every duel narrowly ranks below one that loses to it narrowly and wins its other duel by far; a clear winner stays on top."""
    from tactiled.learn.infer import pair_matrices, pairwise_scores

    first, second = pair_matrices(3)  # pairs (0, 1), (0, 2), (1, 2)
    dec = np.array([[0.1, 0.1, 5.0], [2.0, 2.0, 5.0]])
    votes = (dec > 0) @ first + (dec <= 0) @ second
    scores = pairwise_scores(dec, first, second)
    assert votes.argmax(axis=1).tolist() == [0, 0]  # class 0 wins both its duels in both rows
    assert scores.argmax(axis=1).tolist() == [1, 0]  # narrowly: class 1 scores higher; clearly: class 0 stays on top
    np.testing.assert_allclose(scores[0], [np.log(1 / (1 + np.exp(-0.2))), (np.log(1 / (1 + np.exp(0.2))) + np.log(1 / (1 + np.exp(-10.0)))) / 2,
                                           (np.log(1 / (1 + np.exp(0.2))) + np.log(1 / (1 + np.exp(10.0)))) / 2])
