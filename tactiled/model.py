"""Model files: ``.npz`` of plain arrays plus a JSON header; never pickle.

Arrays: ``header`` (0-d unicode, JSON), ``classes`` (K,) unicode, ``scaler_mean`` and
``scaler_scale`` (F,) (of the classifier inputs: log10 of sd/energy/rms features), and per classifier: ELM ``weights`` (F, L), ``biases`` (L,),
``beta`` (L, K), ``temperature`` (); kNN and SVM ``train_x`` (n, F) and ``train_y`` (n,)
(libsvm and kNN are deterministic, so they are refit from their training set at load).
The header carries the format and its version, the classifier and its parameters, the
analysis settings (window, spikes, wavelet, feature names), fs, channels, a training
summary, and ``fingerprint``: the SHA-256 (first 16 hex digits) of the header without it
and of every array's bytes. Loading checks all of it and refuses a mismatch with one line.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from tactiled.analysis import AnalysisSettings
from tactiled.elm import ELMClassifier, _softmax
from tactiled.errors import ModelError
from tactiled.features import classifier_inputs
from tactiled.npzio import NpzError, read_npz
from tactiled.recording import atomic_savez

FORMAT = "tactiled-model"
FORMAT_VERSION = 1
CLASSIFIERS = ("elm", "knn", "svm")
FloatArray = npt.NDArray[np.float64]


def default_model_path() -> Path:
    """The model shipped in the package."""
    return Path(str(resources.files("tactiled") / "data" / "default_model.npz"))


def make_classifier(kind: str, params: dict[str, Any], seed: int = 0) -> Any:
    """A fresh scikit-learn estimator of ``kind`` (elm, knn, svm) with ``params``."""
    if kind == "elm":
        return ELMClassifier(n_hidden=int(params.get("n_hidden", 200)), alpha=float(params.get("alpha", 1e-6)), random_state=seed,
                             init=str(params.get("init", "hpelm")))
    if kind == "knn":
        from sklearn.neighbors import KNeighborsClassifier  # imported on demand: the daemon with an ELM never needs it

        return KNeighborsClassifier(n_neighbors=int(params.get("n_neighbors", 9)))
    if kind == "svm":
        from sklearn.svm import SVC

        return SVC(kernel=str(params.get("kernel", "rbf")), C=float(params.get("C", 10.0)), gamma=params.get("gamma", "scale"), random_state=seed)
    raise ModelError(f"unknown classifier {kind!r}; choose one of {', '.join(CLASSIFIERS)}")


@dataclass
class Model:
    """A trained classifier with everything needed to use it on a stream."""

    kind: str
    params: dict[str, Any]
    classes: list[str]
    settings: AnalysisSettings
    fs: float
    channels: int
    scaler_mean: FloatArray
    scaler_scale: FloatArray
    estimator: Any
    seed: int = 0
    summary: dict[str, Any] = field(default_factory=dict)
    fingerprint: str = ""
    train_x: FloatArray | None = None
    train_y: npt.NDArray[np.str_] | None = None

    @property
    def names(self) -> tuple[str, ...]:
        return self.settings.names

    def predict_proba(self, x: npt.ArrayLike) -> FloatArray:
        """(n, K) class probabilities, columns in :attr:`classes` order, for raw features x (n, F)."""
        z = (classifier_inputs(np.asarray(x, dtype=np.float64).reshape(-1, len(self.names)), self.names) - self.scaler_mean) / self.scaler_scale
        if self.kind == "svm":
            scores = self.estimator.decision_function(z)
            if scores.ndim == 1:
                scores = np.stack([-scores, scores], axis=1)
            out: FloatArray = _softmax(np.asarray(scores, dtype=np.float64))
        else:
            out = np.asarray(self.estimator.predict_proba(z), dtype=np.float64)
        full = np.zeros((out.shape[0], len(self.classes)))
        index = {c: i for i, c in enumerate(self.classes)}
        for j, c in enumerate(self.estimator.classes_):
            full[:, index[str(c)]] = out[:, j]
        return full

    def predict(self, x: npt.ArrayLike) -> npt.NDArray[np.str_]:
        return np.asarray(self.classes)[np.argmax(self.predict_proba(x), axis=1)]

    def check_stream(self, fs: float, channels: int, where: str = "stream") -> None:
        """Refuse a stream of another rate or channel count (one line)."""
        if abs(fs - self.fs) > 1e-6 * self.fs:
            raise ModelError(f"model trained at fs {self.fs:g} Hz, {where} is {fs:g} Hz")
        if channels < self.channels:
            raise ModelError(f"model needs {self.channels} channels, {where} has {channels}")

    # ---- persistence -------------------------------------------------------------------------

    def _arrays(self) -> dict[str, Any]:
        arrays: dict[str, Any] = {"classes": np.array(self.classes, dtype=np.str_), "scaler_mean": self.scaler_mean,
                                  "scaler_scale": self.scaler_scale}
        if self.kind == "elm":
            e = self.estimator
            arrays.update(weights=e.weights_, biases=e.biases_, beta=e.beta_, temperature=np.float64(e.temperature_))
        else:
            assert self.train_x is not None and self.train_y is not None
            arrays.update(train_x=self.train_x, train_y=np.asarray(self.train_y, dtype=np.str_))
        return arrays

    def _header(self) -> dict[str, Any]:
        return {"format": FORMAT, "version": FORMAT_VERSION, "classifier": self.kind, "params": self.params, "seed": self.seed,
                "classes": self.classes, "settings": self.settings.to_dict(), "fs": self.fs, "channels": self.channels,
                "summary": self.summary}

    def save(self, path: str | Path) -> str:
        """Write atomically; returns the fingerprint."""
        arrays = self._arrays()
        header = self._header()
        self.fingerprint = _fingerprint(header, arrays)
        header["fingerprint"] = self.fingerprint
        atomic_savez(path, {"header": np.str_(json.dumps(header, sort_keys=True)), **arrays})
        return self.fingerprint


def _fingerprint(header: dict[str, Any], arrays: dict[str, Any]) -> str:
    h = hashlib.sha256(json.dumps(header, sort_keys=True).encode())
    for key in sorted(arrays):
        a = np.ascontiguousarray(arrays[key])
        h.update(key.encode() + str(a.dtype).encode() + str(a.shape).encode() + a.tobytes())
    return h.hexdigest()[:16]


def _need(cond: bool, path: object, what: str) -> None:
    if not cond:
        raise ModelError(f"{path}: {what}")


def load_model(path: str | Path | None = None) -> Model:
    """Load and check a model file (``None``: the shipped model); :class:`ModelError` names file and problem."""
    path = Path(path) if path else default_model_path()
    try:
        arrays = read_npz(path)
    except NpzError as exc:
        what = "no such model file" if str(exc) == "no such file" else str(exc)
        raise ModelError(f"{path}: array {exc.key}: {what}" if exc.key else f"{path}: {what}") from None
    _need("header" in arrays and arrays["header"].shape == () and arrays["header"].dtype.kind == "U", path, "header: missing or not a string")
    try:
        header = json.loads(arrays.pop("header").item())
    except json.JSONDecodeError as exc:
        raise ModelError(f"{path}: header: not JSON: {exc}") from None
    _need(isinstance(header, dict) and header.get("format") == FORMAT, path, f"header.format: not a {FORMAT} file")
    _need(header.get("version") == FORMAT_VERSION, path, f"header.version: {header.get('version')!r} is not the supported {FORMAT_VERSION}")
    try:
        return _build(path, header, arrays)
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, ModelError):
            raise
        raise ModelError(f"{path}: header or arrays inconsistent: {exc}") from None


def _build(path: Path, header: dict[str, Any], arrays: dict[str, Any]) -> Model:
    fingerprint = header.pop("fingerprint", None)
    _need(fingerprint == _fingerprint(header, arrays), path, "fingerprint does not match the contents (tampered or corrupt)")
    kind = header["classifier"]
    _need(kind in CLASSIFIERS, path, f"header.classifier: unknown {kind!r}")
    settings = AnalysisSettings.from_dict(header["settings"])
    f = len(settings.names)
    classes = [str(c) for c in header["classes"]]
    _need(f > 0 and len(classes) >= 1, path, "header: no features or no classes")
    _need(list(arrays["classes"]) == classes, path, "classes: differ from the header's")
    for key in ("scaler_mean", "scaler_scale"):
        a = arrays[key]
        _need(a.shape == (f,) and a.dtype == np.float64 and bool(np.all(np.isfinite(a))), path, f"{key}: must be ({f},) finite float64")
    _need(bool(np.all(arrays["scaler_scale"] > 0)), path, "scaler_scale: must be > 0")
    fs, channels = float(header["fs"]), int(header["channels"])
    _need(fs > 0 and 1 <= channels <= 8, path, "header: fs must be > 0 and channels in 1..8")
    params, seed = dict(header["params"]), int(header["seed"])
    estimator = make_classifier(kind, params, seed)
    train_x = train_y = None
    if kind == "elm":
        w, b, beta = arrays["weights"], arrays["biases"], arrays["beta"]
        hidden = int(params.get("n_hidden", 200))
        _need(w.shape == (f, hidden) and b.shape == (hidden,) and beta.shape == (hidden, len(classes)), path,
              "weights, biases, beta: shapes do not match the header")
        _need(all(bool(np.all(np.isfinite(a))) for a in (w, b, beta)), path, "weights: not finite")
        estimator.weights_, estimator.biases_, estimator.beta_ = w, b, beta
        estimator.temperature_ = float(arrays["temperature"])
        estimator.classes_ = np.array(classes)
        estimator.n_features_in_ = f
    else:
        train_x, train_y = arrays["train_x"], arrays["train_y"]
        _need(train_x.ndim == 2 and train_x.shape[1] == f and train_y.shape == (train_x.shape[0],) and train_x.dtype == np.float64,
              path, "train_x, train_y: shapes do not match the header")
        _need(bool(np.all(np.isfinite(train_x))), path, "train_x: not finite")
        estimator.fit(train_x, train_y)
    return Model(kind, params, classes, settings, fs, channels, arrays["scaler_mean"], arrays["scaler_scale"], estimator, seed,
                 dict(header.get("summary", {})), fingerprint or "", train_x, train_y)
