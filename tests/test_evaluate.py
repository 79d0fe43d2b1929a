"""`tactiled evaluate` end to end on a small simulated set, and the clustering pieces."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from tactiled.learn.cluster import hungarian_accuracy, kmeans, som_clusters
from tactiled.sim.simulate import write_dataset
from tests.conftest import run_cli


def test_hungarian_and_kmeans_metrics() -> None:
    rng = np.random.default_rng(0)
    centres = np.array([[5.0, 0.0], [0.0, 5.0], [-5.0, -5.0]])
    y = np.repeat(np.arange(3), 30)
    x = centres[y] + rng.standard_normal((90, 2)) * 0.5
    for metric in ("sqeuclidean", "cityblock", "cosine"):
        assert hungarian_accuracy(kmeans(x, 3, metric, n_init=3), y.astype(str)) > 0.95
    assert hungarian_accuracy(som_clusters(x, 3, iterations=2000), y) > 0.9
    assert hungarian_accuracy(np.array([1, 1, 0, 0]), np.array(["a", "a", "b", "b"])) == 1.0


def test_evaluate_writes_all_six_experiments(tmp_path: Path) -> None:
    data = tmp_path / "d"
    write_dataset(data, scene="robot", surfaces="3", files_per_surface=3, slides_per_file=3)
    report = tmp_path / "r"
    res = run_cli("evaluate", *sorted(str(p) for p in data.glob("*.npz")), "--report", f"{report}/", "--quick", "--folds", "3", timeout=300)
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith(f"{report}/report.md: 9 recordings")  # a clean path, whatever the folder's spelling
    out = json.loads((report / "report.json").read_text())
    assert set(out) >= {"classifiers", "window_grid", "sampling_rate", "feature_count", "unsupervised", "default_method"}
    acc = out["classifiers"]["results"]
    assert {"ELM", "kNN k=9", "SVM RBF", "SVM linear", "ELM (plain: U(-1,1), pinv)"} <= set(acc)
    assert all(0.0 <= r["mean"] <= 1.0 and r["sd"] >= 0 for r in acc.values())
    assert acc["ELM"]["mean"] > 0.6  # three well separated surfaces
    assert [r["fs"] for r in out["sampling_rate"]] == [20000.0, 5000.0]
    md = (report / "report.md").read_text()
    for heading in ("(a) Classifiers", "(b) Start point", "(c) Sampling rate", "(d) Number", "(e) Without labels", "(f) Error against run time",
                    "(g) The default method", "Quick run: forward selection among the 16 features"):
        assert heading in md
    assert (report / "error_vs_runtime.png").stat().st_size > 10_000 and (report / "error_vs_decision_time.png").stat().st_size > 10_000
    cal = out["default_method"]["calibration"]
    assert 0.0 <= cal["ece"] <= 1.0 and 0.0 <= cal["brier"] <= 1.0 and sum(n for _, n, _, _ in cal["reliability"]) == 27
    assert "expected calibration error" in md and (report / "reliability.png").stat().st_size > 10_000


def test_evaluate_needs_ground_truth(tmp_path: Path) -> None:
    res = run_cli("evaluate", str(tmp_path / "nope.npz"), "--report", str(tmp_path / "r"))
    assert res.returncode == 2 and "at least two readable recordings" in res.stderr


def _files(root: Path, *, surfaces: str = "2", fs: float | None = None) -> list[str]:
    """A tiny robot-scene set: two recordings of one slide per surface, at ``fs`` (default 20 kHz)."""
    return [str(p) for p in write_dataset(root, scene="robot", surfaces=surfaces, files_per_surface=2, slides_per_file=1, fs=fs)]


def test_features_refuse_recordings_of_two_rates_in_either_order(tmp_path: Path) -> None:
    fast = _files(tmp_path / "fast", surfaces="1")[0]
    slow = _files(tmp_path / "slow", surfaces="1", fs=2200.0)[0]
    for files in ([fast, slow], [slow, fast]):  # the first order raised from deep inside; the second wrote 2.2 kHz bands for both
        out = tmp_path / "f.npz"
        res = run_cli("features", *files, "-o", str(out))
        lines = res.stderr.splitlines()  # train's check (tactiled.learn.train.check_recordings), one line
        assert res.returncode == 2 and len(lines) == 1 and lines[0].startswith("tactiled: error: recordings differ in fs [2200.0, 20000.0]"), res.stderr
        assert not out.exists()

