"""A model whose analysis cannot keep up with the sensor is refused at load, in one line, unless forced."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tactiled.core.analysis import AnalysisSettings
from tactiled.errors import ModelError
from tactiled.learn.cost import MIN_SPEED, analysis_speed, check_speed
from tactiled.learn.model import Model, fit_pipeline, load_model
from tests.conftest import run_cli


def _tiny(tmp_path: Path) -> Path:
    """A linear model on 2-sample windows (Haar DWT, level 1): it passes every load check, and asks for 10 000 windows per second."""
    names = ("film1.time.A1.sd", "film1.time.D1.sd")
    rng = np.random.default_rng(0)
    y = np.repeat(["a", "b"], 20)
    x = np.abs(rng.standard_normal((40, 2))) + np.repeat([1.0, 3.0], 20)[:, None]
    pipe, refit = fit_pipeline(x, y, list(names), "linear", {"C": 1.0})
    settings = AnalysisSettings(duration_s=2 / 20000, names=names, wavelet="haar", level=1, fusion="features")
    Model("test", "linear", {"C": 1.0}, ["a", "b"], settings, 20000.0, 2, pipe, 1.0, 0, {}, "", refit, None).save(tmp_path / "tiny.npz")
    return tmp_path / "tiny.npz"


def test_the_shipped_model_keeps_up_and_a_model_on_two_sample_windows_does_not(tmp_path: Path) -> None:
    assert check_speed(load_model(), "shipped") >= MIN_SPEED
    tiny = load_model(_tiny(tmp_path))  # every load check passes
    speed, per_window = analysis_speed(tiny)
    assert speed < MIN_SPEED and per_window > 0
    with pytest.raises(ModelError, match=r"tiny: analysis runs at [\d.]+x real time .*--force runs it anyway"):
        check_speed(tiny, "tiny")
    assert check_speed(tiny, "tiny", force=True) == pytest.approx(speed, rel=10)


def test_a_model_that_keeps_up_costs_three_windows_and_one_that_does_not_is_measured_longer(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from tactiled.core.analysis import Analyser

    calls = 0
    analyse = Analyser.analyse

    def counted(self: Analyser, x: np.ndarray) -> object:
        nonlocal calls
        calls += 1
        return analyse(self, x)

    shipped, tiny = load_model(), load_model(_tiny(tmp_path))  # loading probes one window
    monkeypatch.setattr(Analyser, "analyse", counted)
    analysis_speed(shipped)
    assert calls == 3
    calls = 0
    analysis_speed(tiny)
    assert calls > 3


def test_run_refuses_a_model_that_cannot_keep_up_in_one_line(tmp_path: Path) -> None:
    tiny = _tiny(tmp_path)
    res = run_cli("run", "--model", str(tiny), "--port", str(tmp_path / "no-such-port"), "--publish", f"ipc://{tmp_path}/pub", timeout=60)
    assert res.returncode == 2 and res.stderr.strip().count("\n") == 0, res.stderr
    assert str(tiny) in res.stderr and "real time" in res.stderr


def test_replay_refuses_it_too_unless_forced(tmp_path: Path) -> None:
    from tactiled.files.recording import Recording, save_recording

    tiny = _tiny(tmp_path)
    save_recording(tmp_path / "r.npz", Recording(np.zeros((2000, 2), dtype=np.int16), 20000.0))
    res = run_cli("replay", "--model", str(tiny), str(tmp_path / "r.npz"), timeout=60)
    assert res.returncode == 2 and "real time" in res.stderr and res.stderr.strip().count("\n") == 0, res.stderr
    res = run_cli("replay", "--model", str(tiny), "--force", str(tmp_path / "r.npz"), timeout=60)
    assert res.returncode == 0 and "0 slides" in res.stdout, res.stdout + res.stderr
