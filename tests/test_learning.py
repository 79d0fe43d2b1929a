"""ELM numerics, model files, train/score CLI."""

from __future__ import annotations

import json
import os
import pty
import select
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tactiled.elm import ELMClassifier
from tactiled.errors import ModelError
from tactiled.model import load_model
from tests.conftest import REPO, run_cli, tactiled_cmd


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


def test_tampered_models_are_refused(tmp_path: Path) -> None:
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
        res = run_cli("replay", "--model", str(path), str(path))
        assert res.returncode == 2 and len(res.stderr.strip().splitlines()) >= 1


def test_model_for_other_rate_is_refused(tmp_path: Path) -> None:
    model = load_model()
    with pytest.raises(ModelError, match="fs 20000 Hz, x is 2200 Hz"):
        model.check_stream(2200.0, 2, "x")


def test_train_and_score_one_channel_other_rate(tmp_path: Path) -> None:
    data = tmp_path / "data"
    res = run_cli("simulate", "dataset", "--out", str(data), "--surfaces", "3", "--files-per-surface", "2", "--slides-per-file", "3",
                  "--mode", "robot", "--fs", "2200", "--channels", "1")
    assert res.returncode == 0, res.stderr
    cfg = tmp_path / "c.toml"
    cfg.write_text("[window]\nstart_s = 0.2\nduration_s = 0.8\n[features]\nlevel = 3\n")
    model = tmp_path / "m.npz"
    files = sorted(str(p) for p in data.glob("*.npz"))
    res = run_cli("train", *files, "-o", str(model), "--features", "2", "--config", str(cfg))
    assert res.returncode == 0, res.stderr
    res = run_cli("score", str(model), *files, "--json")
    assert res.returncode == 0, res.stderr
    report = json.loads(res.stdout)
    assert report["n"] == 18 and report["accuracy"] > 0.6
    res = run_cli("replay", "--json", "--model", str(model), files[0])
    lines = [json.loads(line) for line in res.stdout.splitlines()]
    assert res.returncode == 0 and len(lines) == 3, res.stdout
    assert all(line["label"] or line["reason"] == "window_too_short" for line in lines), [line["reason"] for line in lines]
    assert sum(bool(line["label"]) for line in lines) >= 2


def test_monitor_shows_live_labels_in_a_terminal(tmp_path: Path) -> None:
    from tactiled.model import load_model as _lm
    from tactiled.sensor_model import SimParams

    assert _lm().fs == SimParams().fs
    master, slave = pty.openpty()
    env = {**os.environ, "TERM": "xterm", "COLUMNS": "100", "LINES": "30"}
    proc = subprocess.Popen(tactiled_cmd("demo", "--mode", "robot"), stdin=slave, stdout=slave, stderr=slave, env=env, close_fds=True)
    os.close(slave)
    screen = b""
    try:
        import time

        deadline = time.monotonic() + 90
        def shown() -> bool:
            return b"latency" in screen and b"Ra" in screen and (b"IDLE" in screen or b"SLIDING" in screen)

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
    assert b"latency" in screen and b"Ra" in screen
    assert proc.returncode == 0
