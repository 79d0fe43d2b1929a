"""The DWT features of a window less its mean (``centred``): what a DC offset no longer changes, and which model files
are analysed that way (those trained now) and which as before (those written without the field)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tactiled.config import Config
from tactiled.core.analysis import Analyser, AnalysisSettings, window_settings
from tactiled.core.features import FeaturePlan, family_names
from tactiled.errors import ModelError
from tactiled.learn.model import default_model_path, load_model
from tactiled.learn.search import Candidate
from tactiled.learn.train import train
from tactiled.sim.simulate import write_dataset
from tests.test_spectral_novelty import _rewritten

FS = 20_000.0
DWT = ["film1.time.A4.energy", "film1.time.A4.sd", "film2.time.D2.rms", "film1.freq.A1.sd", "film2.freq.A3.energy", "film1.freq.D2.sd"]
OTHERS = [*family_names("psd", 2, FS)[:3], "film1.tex.rms", "film2.tex.centroid", "film1.tex.kurtosis"]


def _window(n: int = 5000) -> np.ndarray:
    return np.random.default_rng(7).standard_normal((n, 2)) * np.array([0.01, 0.03])


def test_centred_dwt_features_ignore_an_offset_and_the_other_families_are_the_same() -> None:
    x, offset = _window(), np.array([0.7, -1.3])  # an offset 70 and 40 times the noise, as a DC-coupled film's
    centred, raw = FeaturePlan(DWT + OTHERS, fs=FS, centred=True), FeaturePlan(DWT + OTHERS, fs=FS)
    d = len(DWT)
    assert np.allclose(centred.compute(x + offset), centred.compute(x), rtol=1e-9, atol=0.0)
    assert np.allclose(centred.compute(x + offset), raw.compute(x - x.mean(axis=0)), rtol=1e-9, atol=0.0)
    shifted = raw.compute(x + offset)[:d] / raw.compute(x)[:d]
    assert shifted[0] > 100 and shifted[3] > 10 and shifted[5] > 10  # uncentred, the offset is what A4 and the spectrum hold
    assert np.allclose(centred.compute(x + offset)[d:], raw.compute(x + offset)[d:], rtol=1e-12, atol=0.0)  # psd, tex: centred already


def test_a_constant_window_gives_finite_centred_features() -> None:
    for value in (0.0, 3.0, -1e6):
        f = FeaturePlan(DWT + OTHERS, fs=FS, centred=True).compute(np.full((5000, 2), value))
        assert np.all(np.isfinite(f)) and np.all(np.abs(f[: len(DWT)]) <= 1e-9 * max(1.0, abs(value)))  # 0 but for the FFT's rounding


@pytest.fixture(scope="module")
def dwt_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A model of DWT features trained now on three surfaces (one channel at 2.2 kHz, two recordings each)."""
    root = tmp_path_factory.mktemp("centred")
    paths = write_dataset(root / "d", scene="robot", seed=5, surfaces="3", files_per_surface=2, slides_per_file=2, fs=2200.0, channels=1)
    res = train(paths, Config(), folds=2, candidates=[Candidate(("dwt",), "linear", 0.5)])
    path = root / "m.npz"
    res.model.save(path)
    return path


def test_models_trained_now_are_centred_and_say_so_in_their_file(dwt_model: Path) -> None:
    settings = window_settings(Config(), 2, FS, 0.5, ["dwt", "psd"])
    assert settings is not None and settings.centred and AnalysisSettings.from_config(Config(), 2).centred
    model = load_model(dwt_model)
    assert model.settings.centred and any(".time." in n or ".freq." in n for n in model.names)
    with np.load(dwt_model) as f:
        assert json.loads(f["header"].item())["settings"]["centred"] is True
    assert Analyser(model.settings, model.fs, 1.0, False).plan.centred


def _without_centred(header: dict[str, Any], arrays: dict[str, Any]) -> None:
    header["settings"].pop("centred", None)


def test_a_model_file_without_the_field_is_analysed_as_it_was_trained(dwt_model: Path, tmp_path: Path) -> None:
    """A file written before the field existed: its features are of the samples as they are, as when it was trained."""
    old = load_model(_rewritten(dwt_model, tmp_path / "old.npz", _without_centred))
    assert not old.settings.centred and not Analyser(old.settings, old.fs, 1.0, False).plan.centred
    x = np.random.default_rng(1).standard_normal((round(old.settings.duration_s * old.fs), 1)) * 0.01 + 0.5
    now = Analyser(load_model(dwt_model).settings, old.fs, 1.0, False).analyse(x).features
    before = Analyser(old.settings, old.fs, 1.0, False).analyse(x).features
    assert now is not None and before is not None and not np.allclose(now, before)
    shipped = load_model(_rewritten(default_model_path(), tmp_path / "shipped.npz", _without_centred))
    assert not shipped.settings.centred


@pytest.mark.parametrize("value", ["yes", 1, None])
def test_a_centred_field_that_is_not_a_boolean_is_one_line(value: Any, dwt_model: Path, tmp_path: Path) -> None:
    bad = _rewritten(dwt_model, tmp_path / "bad.npz", lambda h, a: h["settings"].update(centred=value))
    with pytest.raises(ModelError, match=r"settings.centred: must be true or false") as err:
        load_model(bad)
    assert "\n" not in str(err.value) and "bad.npz" in str(err.value)
