"""Clustering without labels (paper 2): K-means with squared Euclidean, cityblock (k-medians)
and cosine (spherical) distances, a self-organising map, and Hungarian scoring.

scikit-learn's KMeans is squared-Euclidean only (its maintainers declined other metrics,
scikit-learn#13956), so cityblock and cosine use a small Lloyd loop with the right centroid
for each: the component-wise median, and the renormalised mean of unit vectors (as MATLAB's
kmeans does). The SOM is MiniSom with one neuron per cluster.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]


def hungarian_accuracy(clusters: IntArray, labels: npt.NDArray[Any]) -> float:
    """Accuracy after matching clusters to labels one to one (maximum agreement)."""
    classes, y = np.unique(labels, return_inverse=True)
    k = int(clusters.max()) + 1
    table = np.zeros((k, len(classes)))
    np.add.at(table, (clusters, y), 1)
    rows, cols = linear_sum_assignment(table, maximize=True)
    return float(table[rows, cols].sum() / len(labels))


def kmeans(x: FloatArray, k: int, metric: str = "sqeuclidean", n_init: int = 10, max_iter: int = 100, seed: int = 0) -> IntArray:
    """Cluster rows of x (n, d) into k clusters; returns labels (n,). metric: sqeuclidean, cityblock, cosine."""
    if metric == "sqeuclidean":
        from sklearn.cluster import KMeans

        return np.asarray(KMeans(k, n_init=n_init, random_state=seed).fit_predict(x), dtype=np.intp)
    if metric == "cosine":
        norms = np.linalg.norm(x, axis=1, keepdims=True)
        if np.any(norms == 0):
            raise ValueError("cosine k-means: a row has no direction (all-zero feature vector)")
        x = x / norms
    elif metric != "cityblock":
        raise ValueError(f"unknown metric {metric!r}")
    rng = np.random.default_rng(seed)
    best: tuple[float, IntArray] | None = None
    for _ in range(n_init):
        centres = x[rng.choice(len(x), 1)]
        for _ in range(1, k):  # k-means++ seeding with the metric's distance
            d = cdist(x, centres, metric).min(axis=1) ** 2
            centres = np.vstack([centres, x[rng.choice(len(x), p=d / d.sum() if d.sum() > 0 else None)]])
        labels = np.zeros(len(x), dtype=np.intp)
        for it in range(max_iter):
            new = cdist(x, centres, metric).argmin(axis=1)
            if it and np.array_equal(new, labels):
                break
            labels = new
            for j in range(k):
                members = x[labels == j]
                if len(members) == 0:  # re-seed an empty cluster at the farthest point
                    members = x[[int(cdist(x, centres, metric).min(axis=1).argmax())]]
                c = np.median(members, axis=0) if metric == "cityblock" else members.mean(axis=0)
                if metric == "cosine":
                    c = c / max(float(np.linalg.norm(c)), 1e-300)
                centres[j] = c
        cost = float(cdist(x, centres, metric)[np.arange(len(x)), labels].sum())
        if best is None or cost < best[0]:
            best = (cost, labels.copy())
    assert best is not None
    return best[1]


def som_clusters(x: FloatArray, k: int, seed: int = 0, iterations: int = 5000) -> IntArray:
    """Winning neuron of each row on a 1 × k self-organising map (MiniSom)."""
    from minisom import MiniSom

    som = MiniSom(1, k, x.shape[1], sigma=max(k / 4, 0.5), learning_rate=0.5, random_seed=seed)
    som.random_weights_init(x)
    som.train_random(x, iterations)
    return np.array([som.winner(row)[1] for row in x], dtype=np.intp)
