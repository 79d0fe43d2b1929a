"""Accuracy, per-class recall and confusion matrix of predictions."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt


def score_report(y_true: npt.NDArray[Any], y_pred: npt.NDArray[Any], classes: Sequence[str]) -> dict[str, Any]:
    """``{"accuracy", "n", "recall": {class: r}, "classes", "confusion": rows true, columns predicted}``."""
    labels = sorted(set(classes) | set(map(str, y_true)))
    index = {c: i for i, c in enumerate(labels)}
    cm = np.zeros((len(labels), len(labels)), dtype=int)
    for t, p in zip(y_true, y_pred, strict=True):
        cm[index[str(t)], index[str(p)]] += 1
    recall = {c: float(cm[i, i] / cm[i].sum()) for i, c in enumerate(labels) if cm[i].sum()}
    return {"accuracy": float(np.mean(np.asarray(y_true) == np.asarray(y_pred))), "n": len(y_true), "recall": recall,
            "classes": labels, "confusion": cm.tolist()}
