"""`tactiled evaluate` end to end on a small simulated set, and the clustering pieces.

The commands run by main() in the test's process (cli_here): the same handlers, lines and files, without a new interpreter
and worker pool for each."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tactiled.learn.cluster import hungarian_accuracy, kmeans, som_clusters
from tactiled.sim.simulate import write_dataset
from tests.conftest import cli_here


def test_hungarian_and_kmeans_metrics() -> None:
    rng = np.random.default_rng(0)
    centres = np.array([[5.0, 0.0], [0.0, 5.0], [-5.0, -5.0]])
    y = np.repeat(np.arange(3), 30)
    x = centres[y] + rng.standard_normal((90, 2)) * 0.5
    for metric in ("sqeuclidean", "cityblock", "cosine"):
        assert hungarian_accuracy(kmeans(x, 3, metric, n_init=3), y.astype(str)) > 0.95
    assert hungarian_accuracy(som_clusters(x, 3, iterations=2000), y) > 0.9
    assert hungarian_accuracy(np.array([1, 1, 0, 0]), np.array(["a", "a", "b", "b"])) == 1.0


def test_evaluate_writes_all_six_experiments(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "d"
    write_dataset(data, scene="robot", surfaces="3", files_per_surface=3, slides_per_file=3)
    report = tmp_path / "r"
    res = cli_here(capfd, "evaluate", *sorted(str(p) for p in data.glob("*.npz")), "--report", f"{report}/", "--quick", "--folds", "3")
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


@pytest.mark.parametrize("n_features", ["auto", 3])
def test_forward_selection_chooses_the_columns_scikit_learns_selector_chooses(n_features: str | int) -> None:
    """sfs_columns runs the rule of scikit-learn's SequentialFeatureSelector as its own loop (for speed): the same columns,
    with the same folds and ELM, on three classes where two columns carry the class and one is constant."""
    from types import SimpleNamespace

    from sklearn.feature_selection import SequentialFeatureSelector
    from sklearn.preprocessing import StandardScaler

    from tactiled.learn.elm import ELMClassifier
    from tactiled.learn.search import grouped_splits, sfs_columns

    rng = np.random.default_rng(5)
    y = np.repeat(np.array(["a", "b", "c"]), 20)
    x = np.abs(rng.standard_normal((60, 8))) + 1.0
    x[:, 2] += (y == "b") * 1.5
    x[:, 5] += (y == "c") * 1.2
    x[:, 7] = 1.0  # constant: never a candidate
    groups = np.repeat(np.arange(12), 5)  # four files per surface
    ws = SimpleNamespace(x=x, y=y, groups=groups, slide=np.arange(60), names=[f"f{i}" for i in range(8)])
    got = sfs_columns(ws, np.arange(60), seed=3, inner_folds=3, n_features=n_features)  # type: ignore[arg-type]
    sfs = SequentialFeatureSelector(ELMClassifier(n_hidden=50, calibrate=False, random_state=3), direction="forward", scoring="accuracy",
                                    n_features_to_select=n_features, tol=0.005 if n_features == "auto" else None,
                                    cv=grouped_splits(y, groups, 3, 3))
    sfs.fit(StandardScaler().fit_transform(x)[:, :7], y)
    assert got == [int(j) for j in np.flatnonzero(sfs.get_support())] and {2, 5} <= set(got)
    if n_features == 3:
        assert len(got) == 3


def test_evaluate_needs_ground_truth(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    res = cli_here(capfd, "evaluate", str(tmp_path / "nope.npz"), "--report", str(tmp_path / "r"))
    assert res.returncode == 2 and "at least two readable recordings" in res.stderr


def _files(root: Path, *, surfaces: str = "2", fs: float | None = None) -> list[str]:
    """A tiny robot-scene set: two recordings of one slide per surface, at ``fs`` (default 20 kHz)."""
    return [str(p) for p in write_dataset(root, scene="robot", surfaces=surfaces, files_per_surface=2, slides_per_file=1, fs=fs)]


def _label_only(path: str, label: str | None) -> None:
    """Rewrite the recording at ``path`` without its per-slide ground truth, with only the file-level ``label`` (or none)."""
    from dataclasses import replace

    from tactiled.files.recording import load_recording, save_recording

    rec = load_recording(path)
    save_recording(path, replace(rec, slide_start=None, slide_stop=None, surface=None, ra_um=None, label=label))


def test_features_refuse_recordings_of_two_rates_in_either_order(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    fast = _files(tmp_path / "fast", surfaces="1")[0]
    slow = _files(tmp_path / "slow", surfaces="1", fs=2200.0)[0]
    for files in ([fast, slow], [slow, fast]):  # the first order raised from deep inside; the second wrote 2.2 kHz bands for both
        out = tmp_path / "f.npz"
        res = cli_here(capfd, "features", *files, "-o", str(out))
        lines = res.stderr.splitlines()  # train's check (tactiled.learn.train.check_recordings), one line
        assert res.returncode == 2 and len(lines) == 1 and lines[0].startswith("tactiled: error: recordings differ in fs or channels ("), res.stderr
        assert f"{files[0]}: {'20000' if files[0] == fast else '2200'} Hz" in lines[0] and f"{files[1]}: " in lines[0], lines  # which files
        assert not out.exists()


def test_evaluate_refuses_a_single_surface(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    report = tmp_path / "r"
    res = cli_here(capfd, "evaluate", *_files(tmp_path / "d", surfaces="1"), "--report", str(report), "--quick", "--experiments", "a")
    assert res.returncode == 2 and res.stderr.splitlines()[-1].startswith("tactiled: error: evaluation needs at least two surfaces, got ['Ra"), res.stderr
    assert not (report / "report.md").exists()


def test_evaluate_uses_label_only_recordings_and_names_one_without_ground_truth(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    files = _files(tmp_path / "d")
    for path in files[2:]:  # every recording of the second surface keeps only its file label
        _label_only(path, Path(path).name.split("_")[1])
    bare = str(tmp_path / "bare.npz")
    write_dataset(tmp_path / "b", scene="robot", surfaces="1", files_per_surface=1, slides_per_file=1, seed=5)
    (tmp_path / "b" / next(p.name for p in (tmp_path / "b").glob("*.npz"))).rename(bare)
    _label_only(bare, None)
    report = tmp_path / "r"
    res = cli_here(capfd, "evaluate", *files, bare, "--report", str(report), "--quick", "--experiments", "a", "--folds", "2")
    assert res.returncode == 2, res.stderr  # the bare file was named and skipped
    assert f"tactiled: skipped: {bare}: no ground truth (neither per-slide surfaces nor a file label)" in res.stderr.splitlines()
    assert res.stdout.startswith(f"{report / 'report.md'}: 4 recordings")
    out = json.loads((report / "report.json").read_text())
    assert (out["files"], out["classifiers"]["surfaces"], out["classifiers"]["slides"]) == (4, 2, 4)


def test_evaluate_sampling_rate_below_20_khz_and_the_folds_used(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    report = tmp_path / "r"
    res = cli_here(capfd, "evaluate", *_files(tmp_path / "d", fs=2200.0), "--report", str(report), "--quick", "--experiments", "c")
    assert res.returncode == 0, res.stderr
    out = json.loads((report / "report.json").read_text())
    assert [r["fs"] for r in out["sampling_rate"]] == [2200.0, 550.0]  # the recordings' rate and a quarter of it
    assert all(len(r["ELM"]["folds"]) == 2 for r in out["sampling_rate"])
    assert (out["folds"], out["folds_requested"]) == (2, 5)  # two recordings per surface: two folds, whatever --folds asked
    md = (report / "report.md").read_text()
    assert "grouped 2-fold (5 asked for: the surface with fewest recordings has 2) cross-validation" in md and "| 550 Hz | 2 |" in md


def test_evaluate_names_a_surface_whose_files_gave_no_slide(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """A surface named only by file labels of recordings where the detector found nothing (silence) is one line naming it,
    exit 2, with a line per such file; evaluate left it out without a word (an audit found it in train)."""
    from tactiled.files.recording import Recording, save_recording

    files = _files(tmp_path / "d", surfaces="2")
    silent = [str(tmp_path / f"glass_{k}.npz") for k in range(2)]
    for k, path in enumerate(silent):  # silence, not the same samples twice (that is refused as one recording given twice)
        save_recording(path, Recording(samples=np.full((40_000, 2), k, np.int16), fs=20_000.0, label="Glass"))
    report = tmp_path / "r"
    res = cli_here(capfd, "evaluate", *files, *silent, "--report", str(report), "--quick", "--experiments", "a", "--folds", "2")
    lines = res.stderr.splitlines()
    assert res.returncode == 2 and lines[-1] == ("tactiled: error: surface(s) Glass: no slide detected in any of their recordings, "
                                                 "so nothing to evaluate them on"), res.stderr
    assert all(any(f"no slide detected in {path} (label Glass)" in line for line in lines) for path in silent), res.stderr
    assert not (report / "report.md").exists()
