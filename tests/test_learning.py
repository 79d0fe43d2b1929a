"""ELM numerics, model files, train/score CLI."""

from __future__ import annotations

import importlib
import json
import os
import pty
import select
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tactiled.errors import ModelError
from tactiled.learn.elm import ELMClassifier
from tactiled.learn.model import load_model
from tactiled.sim.simulate import write_dataset
from tests.conftest import REPO, cli_here, run_cli, tactiled_cmd


def _data(n: int = 60, d: int = 4, k: int = 3, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    y = np.repeat(np.arange(k), n // k)
    x = rng.standard_normal((n, d)) + y[:, None]
    return x, y.astype(str)


@pytest.mark.parametrize("case", ["duplicates", "collinear", "wide", "constant"])
def test_elm_finite_on_hard_inputs(case: str) -> None:
    x, y = _data()
    if case == "duplicates":
        x = np.vstack([x, x, x])
        y = np.concatenate([y, y, y])
    elif case == "collinear":
        x = np.hstack([x, 2 * x, x[:, :1] - x[:, 1:2]])
    elif case == "constant":
        x[:, 0] = 0.0
    elm = ELMClassifier(n_hidden=500 if case == "wide" else 50, random_state=1).fit(x, y)
    assert np.all(np.isfinite(elm.beta_))
    p = elm.predict_proba(x)
    assert np.all(np.isfinite(p)) and np.allclose(p.sum(axis=1), 1.0)


def test_elm_deterministic_and_class_missing_from_fold() -> None:
    x, y = _data()
    a = ELMClassifier(random_state=3).fit(x, y).decision_function(x)
    b = ELMClassifier(random_state=3).fit(x, y).decision_function(x)
    assert np.array_equal(a, b)
    keep = y != "2"
    elm = ELMClassifier().fit(x[keep], y[keep])
    assert list(elm.classes_) == ["0", "1"] and elm.predict(x).shape == (60,)


def test_elm_is_a_sklearn_estimator() -> None:
    from sklearn.base import clone
    from sklearn.model_selection import cross_val_score

    x, y = _data(90)
    assert clone(ELMClassifier(n_hidden=30)).get_params()["n_hidden"] == 30
    assert cross_val_score(ELMClassifier(n_hidden=30), x, y, cv=3).mean() > 0.5


def test_shipped_model_round_trip(tmp_path: Path) -> None:
    model = load_model()
    x = np.abs(np.random.default_rng(0).standard_normal((5, len(model.names)))) * 0.01
    out = tmp_path / "m.npz"
    assert model.save(out) == model.fingerprint
    again = load_model(out)
    assert np.array_equal(again.predict_proba(x), model.predict_proba(x))


def _rewrite(src: Path, dst: Path, change: dict) -> None:
    with np.load(src, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays.update(change)
    np.savez(dst, **arrays)


def test_tampered_models_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = Path(load_model().fingerprint and (REPO / "tactiled" / "data" / "default_model.npz"))
    header = json.loads(np.load(src)["header"].item())
    cases = {
        "object": {"beta": np.array([{"x": 1}], dtype=object)},
        "version": {"header": np.str_(json.dumps({**header, "version": 99}))},
        "weights": {"scaler_mean": np.zeros(3)},
        "fs": {"header": np.str_(json.dumps({**header, "fs": 1000.0}))},
    }
    for name, change in cases.items():
        path = tmp_path / f"{name}.npz"
        _rewrite(src, path, change)  # np.savez pickles an object array: the loader must refuse it
        with pytest.raises(ModelError) as err:
            load_model(path)
        assert str(path) in str(err.value)
        res = cli_here(capsys, "replay", "--model", str(path), str(path))  # the refusal by main() in this process
        assert res.returncode == 2 and len(res.stderr.strip().splitlines()) >= 1


def test_model_for_other_rate_is_refused(tmp_path: Path) -> None:
    model = load_model()
    with pytest.raises(ModelError, match="fs 20000 Hz, x is 2200 Hz"):
        model.check_stream(2200.0, 2, "x")


def test_train_and_score_one_channel_other_rate(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """Each command by main() in this process (cli_here): the same handlers, lines and files, and --jobs 2 still on worker
    processes (this process's pool), without a new interpreter and pool per command (9 of them took 15 s of the 19)."""
    data = tmp_path / "data"
    write_dataset(data, scene="robot", surfaces="3", files_per_surface=2, slides_per_file=3, fs=2200.0, channels=1)
    model = tmp_path / "m.npz"
    files = sorted(str(p) for p in data.glob("*.npz"))
    res = cli_here(capfd, "train", *files, "-o", str(model), "--folds", "2", "--method", "quick")
    assert res.returncode == 0, res.stderr
    assert "leaderboard" in res.stdout and "nested CV" in res.stdout and "slides per surface" in res.stderr
    assert sum(line.startswith("* ") for line in res.stdout.splitlines()) == 1  # the choice is marked once
    nov = load_model(model).summary["novelty"]  # what train says of the unknown-surface tests is what the model holds
    assert nov["score"] == "spectrum" and nov["threshold"] is None and nov["distance_threshold"] is not None  # the default: no ratio test
    assert load_model(model).novelty_names is not None  # one channel at 2.2 kHz: its psd bands
    assert "whose spectral shape is farther from every taught surface than 95 % of the slides" in res.stdout
    res = cli_here(capfd, "train", *files, "-o", str(tmp_path / "c.npz"), "--folds", "2", "--method", "quick", "--novelty", "combined")
    nov = load_model(tmp_path / "c.npz").summary["novelty"]
    assert res.returncode == 0 and nov["score"] == "combined" and nov["untaught"] == 0.1, res.stderr
    assert ("distance-ratio test flags nothing" in res.stdout) == (nov["threshold"] is None)
    res = cli_here(capfd, "score", str(model), *files, "--json")
    assert res.returncode == 0, res.stderr
    report = json.loads(res.stdout)
    assert report["n"] == 18 and report["accuracy"] > 0.6 and report["coverage"] > 0.6
    two = cli_here(capfd, "score", str(model), *files, "--json", "--jobs", "2")  # two worker processes or this one: the same report
    assert two.returncode == 0 and json.loads(two.stdout) == report, two.stderr
    for jobs in ("1", "2"):
        res = cli_here(capfd, "features", *files, "-o", str(tmp_path / f"f{jobs}.npz"), "--jobs", jobs)
        assert res.returncode == 0, res.stderr
        assert f"features: windows: {len(files)}/{len(files)} files" in res.stderr  # progress, as train says it (an outside audit)
    with np.load(tmp_path / "f1.npz") as one, np.load(tmp_path / "f2.npz") as two:
        assert one.files == two.files and all(np.array_equal(one[k], two[k]) for k in one.files)
    one, two = (cli_here(capfd, "replay", "--json", "--model", str(model), *files, "--jobs", jobs) for jobs in ("1", "2"))
    assert one.returncode == two.returncode == 0 and one.stderr == two.stderr, two.stderr

    def timeless(quality: dict[str, object]) -> dict[str, object]:
        return {q: x for q, x in quality.items() if q != "compute_ms"}

    def steady(out: str) -> list[dict[str, object]]:  # every field but the time each took (the slide's, its provisional labels')
        return [{k: timeless(v) if k == "quality" else [{**p, "quality": timeless(p["quality"])} for p in v] if k == "provisional" else v
                 for k, v in json.loads(line).items() if k not in ("time_unix", "latency_ms")} for line in out.splitlines()]
    assert steady(one.stdout) == steady(two.stdout) and len(steady(one.stdout)) == 18  # the same slides and labels, in order
    res = cli_here(capfd, "replay", "--json", "--model", str(model), files[0])
    lines = [json.loads(line) for line in res.stdout.splitlines()]
    assert res.returncode == 0 and len(lines) == 3, res.stdout
    assert all(line["label"] for line in lines) and "3 slides, 3 labelled" in res.stderr


def test_choice_is_the_simplest_within_one_standard_error() -> None:
    """The best mean sets a bar one standard error below it; the simplest candidate at or above the bar wins."""
    from tactiled.learn.search import Candidate, choose, complexity

    linear, svm, elm = Candidate(("psd",), "linear", 0.5), Candidate(("psd", "tex"), "svm", 0.5, kbest=8), Candidate(("dwt",), "elm", 0.5)
    assert complexity(linear) < complexity(svm) < complexity(elm)
    whole = Candidate(("psd",), "linear", 0.5, fusion="features")
    assert complexity(whole) < complexity(linear)
    noisy = [0.9, 0.5, 0.7, 0.8, 0.6]  # mean 0.70, standard error 0.0707: the bar is 0.629
    assert choose([elm, svm, linear], [noisy, [0.66] * 5, [0.62] * 5]) == 1  # the linear model is under the bar: the svm
    assert choose([elm, svm, linear], [noisy, [0.66] * 5, [0.64] * 5]) == 2  # both above: the linear model
    assert choose([elm, svm, linear], [noisy, [0.62] * 5, [0.62] * 5]) == 0  # none but the best
    steady = [0.70] * 5  # no spread: the best alone
    assert choose([elm, svm, linear], [steady, [0.69] * 5, [0.69] * 5]) == 0
    assert choose([svm, linear], [[0.8], [0.1]]) == 0  # one fold: no spread to go by
    assert choose([svm, svm], [[0.5, 0.6], [0.5, 0.6]]) == 0  # equal: the earlier


def test_score_counts_every_true_slide_and_reads_file_labels(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """A slide the model cannot label counts as wrong; a record --label file (no per-slide truth) is scored from detected slides."""
    from tactiled.core.events import SlideResult
    from tactiled.files.recording import Recording, load_recording, save_recording
    from tactiled.learn.score import score

    rec = Recording(np.zeros((100, 1), dtype=np.int16), 1000.0, slide_start=np.array([0, 40]), slide_stop=np.array([30, 90]),
                    surface=np.array(["a", "b"]))
    ok = SlideResult(0, 2, 28, (2, 28), "a", None, 0.9, [("a", 0.9)], {})
    report = score([("f", rec)], [[ok]], ["a", "b"])
    assert report["n"] == 2 and report["correct"] == 1 and report["accuracy"] == 0.5 and report["coverage"] == 0.5
    assert report["abstained"] == {"missed_by_detector": 1}
    labelled = Recording(np.zeros((100, 1), dtype=np.int16), 1000.0, label="b")
    report = score([("g", labelled)], [[ok, SlideResult(1, 50, 90, (50, 90), None, "low_confidence", 0.2, [], {})]], ["a", "b"])
    assert report["n"] == 2 and report["correct"] == 0 and report["abstained"] == {"low_confidence": 1}
    assert report["untaught"] == {}
    # a surface the model was not taught: wrong in the accuracy, listed apart with how many came out unknown
    unknown = SlideResult(1, 42, 88, (42, 88), None, "unknown_surface", 0.4, [("a", 0.4)], {})
    report = score([("f", rec)], [[ok, unknown]], ["a"])
    assert report["correct"] == 1 and report["unknown"] == 1 and report["untaught"] == {"b": [1, 1]}
    # end to end: a file-level label recording scored through the CLI
    sim = tmp_path / "sim"
    write_dataset(sim, scene="robot", surfaces="2", files_per_surface=2, slides_per_file=2)
    files = sorted(sim.glob("*.npz"))
    model = tmp_path / "m.npz"
    assert cli_here(capfd, "train", *map(str, files), "-o", str(model), "--folds", "2", "--method", "quick").returncode == 0  # in this process
    truth = load_recording(files[0])
    only_label = tmp_path / "label.npz"
    save_recording(only_label, Recording(truth.samples, truth.fs, truth.volts_per_count, label=str(truth.surface[0])))
    res = cli_here(capfd, "score", str(model), str(only_label), "--json")
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    assert out["n"] == 2 and out["correct"] == 2


def test_score_measures_calibration_on_taught_surfaces_only_and_says_what_untaught_slides_got() -> None:
    """Calibration error, Brier score and reliability counted the slides of a surface the model was not taught, for which
    confidence means nothing (docs/messages.md); and score printed "3 of its 3 slides called unknown (the right answer), the
    rest labelled" with nothing left to label."""
    from tactiled.cli.cmd_learn import untaught_line
    from tactiled.core.events import SlideResult
    from tactiled.files.recording import Recording
    from tactiled.learn.score import score

    rec = Recording(np.zeros((100, 1), dtype=np.int16), 1000.0, slide_start=np.array([0, 40]), slide_stop=np.array([30, 90]),
                    surface=np.array(["a", "b"]))
    ok = SlideResult(0, 2, 28, (2, 28), "a", None, 0.9, [("a", 0.9)], {})
    wrong = SlideResult(1, 42, 88, (42, 88), "a", None, 0.6, [("a", 0.6)], {})  # "b" untaught: labelled "a"
    report = score([("f", rec)], [[ok, wrong]], ["a"])
    assert report["calibration_slides"] == 1 and report["brier"] == pytest.approx(0.01) and report["reliability"] == [[0.9, 1, 0.9, 1.0]]
    assert report["untaught"] == {"b": [1, 0]} and report["untaught_labelled"] == {"b": 1}
    assert untaught_line("b", 3, 3, 0) == "not a surface of the model: b, 3 of its 3 slides called unknown (the right answer)"
    assert untaught_line("b", 5, 2, 2).endswith("2 of its 5 slides called unknown (the right answer), 2 labelled and 1 without a label "
                                                 "for another reason")


def test_elm_passes_check_estimator() -> None:
    import warnings

    from sklearn.utils.estimator_checks import check_estimator

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        results = check_estimator(ELMClassifier(n_hidden=20), on_fail=None)
    failed = [r["check_name"] for r in results if r["status"] == "failed"]
    assert not failed and len(results) > 40


@pytest.mark.parametrize("kind", ["elm", "knn", "svm", "linear"])
@pytest.mark.parametrize("case", ["silent_class", "constant", "span_1e12", "one_per_class", "collinear", "two_classes", "fifty_classes"])
def test_every_classifier_trains_on_hard_data(kind: str, case: str, tmp_path: Path) -> None:
    """Finite, normalised probabilities, and a file that loads back to the same scores."""
    from tactiled.core.analysis import AnalysisSettings
    from tactiled.learn.model import Model, fit_pipeline, load_model

    rng = np.random.default_rng(0)
    k = {"two_classes": 2, "fifty_classes": 50}.get(case, 4)
    per = 1 if case == "one_per_class" else 6
    y = np.repeat([f"c{i}" for i in range(k)], per)
    names = ["film1.time.D1.sd", "film1.time.D2.energy", "film1.time.A1.mean", "film1.time.D3.kurt"]
    x = np.abs(rng.standard_normal((len(y), 4))) + np.repeat(np.arange(k), per)[:, None] * 0.5
    if case == "silent_class":
        x[y == "c0"] = 0.0
    elif case == "constant":
        x[:, 2] = 7.0
    elif case == "span_1e12":
        x[:, 1] *= 1e12
        x[:, 2] *= 1e-12
    elif case == "collinear":
        x[:, 3] = 2 * x[:, 2]
    params = {"n_neighbors": 1} if kind == "knn" else {}
    pipe, refit = fit_pipeline(x, y, names, kind, params)
    settings = AnalysisSettings(duration_s=0.5, names=tuple(names))
    model = Model("test", kind, params, [str(c) for c in pipe[-1].classes_], settings, 20000.0, 1, pipe, 1.0, 0, {}, "", refit)
    p = model.predict_proba(x)
    assert np.all(np.isfinite(p)) and np.allclose(p.sum(axis=1), 1.0)
    fused = model.fuse(model.scores(x[:3]))
    assert np.all(np.isfinite(fused)) and abs(fused.sum() - 1.0) < 1e-9
    path = tmp_path / "m.npz"
    model.save(path)
    again = load_model(path)
    assert np.allclose(again.scores(x), model.scores(x))


def test_training_on_a_local_dask_cluster(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--scheduler runs the cross-validation through joblib's Dask backend (a LocalCluster on loopback)."""
    distributed = importlib.import_module("distributed")  # in the dev extras: a missing one fails
    data = tmp_path / "d"
    write_dataset(data, scene="robot", surfaces="2", files_per_surface=2, slides_per_file=2)
    files = sorted(str(p) for p in data.glob("*.npz"))
    with distributed.LocalCluster(host="127.0.0.1", n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        # train by main() in this process (cli_here), its client on the cluster's workers: the same handler and lines, without a
        # new interpreter for each run
        res = cli_here(capsys, "train", *files, "-o", str(tmp_path / "m.npz"), "--folds", "2", "--method", "quick", "--scheduler",
                       cluster.scheduler_address)
        assert res.returncode == 0, res.stderr
        local = cli_here(capsys, "train", *files, "-o", str(tmp_path / "m2.npz"), "--folds", "2", "--method", "quick")
    fp = [line.rsplit("fingerprint ", 1)[1] for out in (res.stdout, local.stdout) for line in out.splitlines() if "fingerprint" in line]
    assert len(fp) == 2 and fp[0] == fp[1]  # the same model, wherever the folds ran
    from tactiled.cli.main import main  # the refusals in this process: the same handler, without a second of start-up each

    capsys.readouterr()
    code = main(["train", *files, "-o", str(tmp_path / "m3.npz"), "--scheduler", "tcp://127.0.0.1:1"])
    # refused: said at once, before any recording is read (dask's client retried it for 10 s, after the analysis)
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("tactiled: error: --scheduler tcp://127.0.0.1:1: cannot connect: "), lines
    for address in ("nonsense", "foo://127.0.0.1:1", ""):  # a traceback before: dask's ValueError; "" ran locally without a word
        code = main(["train", *files, "-o", str(tmp_path / "m3.npz"), "--scheduler", address])
        lines = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and "not a scheduler address" in lines[0] and address in lines[0], lines


def test_a_scheduler_port_that_says_nothing_is_refused_before_training(monkeypatch: pytest.MonkeyPatch) -> None:
    """A port that accepts and never answers (another service): dask's client waited for ever there, after the analysis."""
    import socket

    from tactiled.errors import TactiledError
    from tactiled.learn import search

    monkeypatch.setattr(search, "CONNECT_S", 0.5)
    with socket.create_server(("127.0.0.1", 0)) as server:  # the kernel accepts for it: connected, then silence
        host, port = server.getsockname()
        with pytest.raises(TactiledError, match=f"tcp://{host}:{port}: accepts connections but does not answer as a dask scheduler"):
            search.check_scheduler(f"tcp://{host}:{port}")


def test_headless_demo_prints_labels_with_the_truth_and_stops() -> None:
    res = run_cli("demo", "--headless", "--seconds", "10", "--scene", "robot", timeout=120)
    assert res.returncode == 0, res.stderr
    finals = [line for line in res.stdout.splitlines() if "final" in line]
    assert finals and all("true surface Ra" in line for line in finals)


def test_headless_demo_without_labels_exits_1_quoting_the_daemons_last_line(tmp_path: Path) -> None:
    """A daemon that cannot start (its endpoint's folder is missing): the demo says so in one line, exit 1, never 0."""
    endpoint = f"ipc://{tmp_path}/missing/pub"
    res = run_cli("demo", "--headless", "--seconds", "2", "--scene", "robot", "--publish", endpoint, timeout=120)
    assert res.returncode == 1 and res.stdout == ""
    line = res.stderr.strip()
    # the daemon stopped within the 2 s, or (a loaded machine) was waited for after them
    said = ("the daemon stopped; the daemon's last words:" in line) or ("no final label in 2 s; the daemon's last words:" in line)
    assert len(line.splitlines()) == 1 and said and f"cannot bind {endpoint}" in line, line


def test_demo_refuses_a_scene_its_daemon_cannot_read(capfd: pytest.CaptureFixture[str]) -> None:
    """The one-channel scene streams 1 channel at 2.2 kHz, the demo's daemon and the shipped model expect 2 at 20 kHz: one
    line saying so, exit 2, at once (it ran for --seconds and said only the daemon's start-up line). By main() in this
    process (cli_here): the same handler and line, said before any board or daemon starts."""
    res = cli_here(capfd, "demo", "--headless", "--seconds", "30", "--scene", "fluctuating,one-channel")
    assert res.returncode == 2 and res.stdout == ""
    line = res.stderr.strip()
    assert len(line.splitlines()) == 1 and "1 channel(s) at 2200 Hz" in line and "expect 2 at 20000 Hz" in line, line


def test_monitor_shows_live_labels_in_a_terminal(tmp_path: Path) -> None:
    from tactiled.learn.model import load_model as _lm
    from tactiled.sim.physics import SimParams

    assert _lm().fs == SimParams().fs
    master, slave = pty.openpty()
    env = {**os.environ, "TERM": "xterm", "COLUMNS": "100", "LINES": "30"}
    proc = subprocess.Popen(tactiled_cmd("demo", "--scene", "robot"), stdin=slave, stdout=slave, stderr=slave, env=env, close_fds=True)
    os.close(slave)
    screen = b""
    try:
        import time

        deadline = time.monotonic() + 90
        def shown() -> bool:
            return b"final" in screen and b"Ra" in screen and (b"IDLE" in screen or b"SLIDING" in screen)

        while time.monotonic() < deadline and not shown():
            ready, _, _ = select.select([master], [], [], 1.0)
            if ready:
                try:
                    screen += os.read(master, 65536)
                except OSError:
                    break
        os.write(master, b"q")
        proc.wait(15)
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(master)
    assert b"tactiled monitor" in screen and b"last labels" in screen
    assert b"final" in screen and b"Ra" in screen  # 100x30: the compact screen, a final label on it
    assert proc.returncode == 0


@pytest.mark.parametrize("per_surface, slides", [(3, 1), (3, 3), (2, 1), (7, 2)])
def test_folds_spread_each_surface_over_the_folds(per_surface: int, slides: int) -> None:
    """Every test fold holds at most one recording of a surface (while the surface with fewest recordings sets the
    number of folds), so every surface it tests keeps its other recordings for training; no fold splits a recording."""
    from tactiled.learn.search import grouped_splits

    surfaces = 15
    y = np.repeat(np.arange(surfaces), per_surface * slides)
    groups = np.repeat(np.arange(surfaces * per_surface), slides)
    folds = grouped_splits(y, groups, 5, seed=0)
    assert len(folds) == min(5, per_surface)
    tested = np.zeros(len(y), dtype=int)
    for train, test in folds:
        assert not set(groups[train]) & set(groups[test])
        recordings = {(int(y[i]), int(groups[i])) for i in test}
        per = np.bincount([s for s, _ in recordings], minlength=surfaces)
        assert per.max() <= -(-per_surface // len(folds))  # as even as the counts allow
        assert set(y[test]) <= set(y[train])  # nothing tested that training never saw
        tested[test] += 1
    assert (tested == 1).all()


def test_inner_folds_test_only_surfaces_they_train_on() -> None:
    """An outer training fold of surfaces recorded twice holds one recording of each: inner folds grouped by file would
    test each with nothing of its surface to train on, so they split by slide there, by file where they can, and there
    are none where a surface has a single slide (that fold then scores the winner itself)."""
    from types import SimpleNamespace

    from tactiled.learn.search import _inner_folds

    def windows(files_per_surface: int, slides: int) -> tuple[SimpleNamespace, np.ndarray]:
        labels = np.repeat([f"Ra{i}" for i in range(4)], files_per_surface * slides)
        files = np.repeat(np.arange(4 * files_per_surface), slides)
        return SimpleNamespace(slides=[SimpleNamespace(file=int(f)) for f in files], slide_labels=lambda: labels), files

    for per_surface, slides, how in ((1, 3, "slide"), (2, 3, "file"), (1, 1, "none")):
        ws, files = windows(per_surface, slides)
        train = np.arange(len(files))
        grouped, folds = _inner_folds(ws, train, 3, seed=0)  # type: ignore[arg-type]
        assert grouped == how
        assert bool(folds) is (how != "none")
        labels = ws.slide_labels()
        for tr, te in folds:
            assert set(labels[te]) <= set(labels[tr])
            if how == "file":
                assert not set(files[tr]) & set(files[te])


@pytest.mark.parametrize("method", ["auto", "paper"])
def test_nested_estimate_with_two_recordings_per_surface(tmp_path: Path, method: str) -> None:
    """Two recordings per surface: an outer fold trains on one of each, so its inner folds (the search's choice, the papers'
    forward selection) split by slide. Grouped by file they scored nothing anywhere: the search's nested estimate was that
    of the simplest candidate (62.5 % for a model every outer fold scored 100 %), the papers' cross-validation 12.5 %."""
    from tactiled.config import Config
    from tactiled.learn.train import train

    paths = write_dataset(tmp_path, scene="robot", seed=3, surfaces="4", files_per_surface=2, slides_per_file=2)
    res = train(paths, Config(), method=method, progress=lambda m: None)
    board = {r["candidate"]: r["mean"] for r in res.leaderboard}
    assert board[res.winner] == 1.0
    assert res.nested["mean"] >= 0.9
    if method == "auto":
        assert res.nested["inner_grouped_by"] == "slide"


def test_anova_f_warns_nothing_on_constant_columns_and_one_row_per_class() -> None:
    """The selection's F statistic: NaN (ranked last) where scikit-learn's would warn (a constant column; one row per
    class, no within-class degrees of freedom), the same value elsewhere."""
    import warnings

    from tactiled.learn.model import anova_f

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        f_one, _ = anova_f(np.array([[1.0, 0.0], [1.0, 1.0], [1.0, 2.0]]), np.array([0, 1, 2]))
        f_two, _ = anova_f(np.array([[1.0, 0.0], [1.0, 1.0], [1.0, 2.0], [1.0, 5.0]]), np.array([0, 0, 1, 1]))
    assert np.isnan(f_one).all() and np.isnan(f_two[0]) and f_two[1] == pytest.approx(3.6)


def test_nested_estimate_with_one_slide_per_surface_and_recording(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """Two recordings of one slide per surface (a robot sliding through each file): no inner folds can choose inside an
    outer fold, so those folds score the winner itself and train says the estimate is optimistic (it was the simplest
    candidate's, 58.3 % for a model every outer fold scored 100 %); an F statistic over one row per class warns nothing."""
    import warnings

    from joblib.externals.loky import get_reusable_executor

    from tactiled.config import Config
    from tactiled.learn.train import train

    paths = write_dataset(tmp_path, scene="continuous", seed=4, surfaces="4", files_per_surface=2, slides_per_file=1)
    said: list[str] = []
    # workers an earlier test started write to the stderr they inherited, not this test's: start this test's own
    get_reusable_executor().shutdown(wait=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = train(paths, Config(), method="quick", progress=said.append)  # two candidates, one of them ranking by F
    board = {r["candidate"]: r for r in res.leaderboard}
    assert res.nested["inner_grouped_by"] == "none"
    assert res.nested["folds"] == board[res.winner]["folds"]
    assert any("no inner folds can choose" in m for m in said) and "optimistic" in res.model.describe()
    assert "Warning" not in capfd.readouterr().err  # the workers write to the process's stderr


def test_folds_with_unlabelled_slides_and_single_recordings() -> None:
    """Unlabelled slides (-1) do not set the number of folds; a surface with a single recording leaves grouped folds only."""
    from tactiled.learn.search import grouped_splits

    y = np.array([0, 0, 0, 1, 1, 1, -1])
    groups = np.array([0, 1, 2, 3, 4, 5, 6])
    assert len(grouped_splits(y, groups, 5, seed=0)) == 3
    one = grouped_splits(np.array([0, 0, 1]), np.array([0, 1, 2]), 5, seed=0)
    assert len(one) == 3 and all(len(te) == 1 for _, te in one)
