"""The psd and tex feature families: names, values against direct computation, extremes, any rate and channel count."""

from __future__ import annotations

import itertools
import warnings

import numpy as np
import pytest
from scipy import signal

from tactiled.core.features import FeaturePlan, classifier_inputs, family_names, is_log_feature, name_family, psd_bands


@pytest.mark.parametrize("fs", [1000.0, 2200.0, 20000.0, 50000.0])
def test_bands_are_log_spaced_contiguous_and_resolvable(fs: float) -> None:
    bands = psd_bands(fs)
    assert bands[0][0] == 20.0 and bands[-1][1] == pytest.approx(0.45 * fs, rel=1e-3)
    assert all(a[1] == b[0] and a[0] < a[1] for a, b in itertools.pairwise(bands))
    resolution = fs / 2 ** round(np.log2(0.05 * fs))
    assert all(hi - lo >= resolution for lo, hi in bands[:-1])


def test_names_round_trip_and_families() -> None:
    names = family_names("psd", 2, 2200.0) + family_names("tex", 2, 2200.0) + family_names("dwt", 2, 2200.0)
    assert {name_family(n) for n in names} == {"psd", "tex", "dwt"}
    plan = FeaturePlan(names, fs=2200.0)
    assert plan.channels_needed == 2 and plan.min_samples() > 64
    assert is_log_feature("film1.psd.20-40p47Hz.power") and is_log_feature("film2.tex.centroid") and not is_log_feature("film1.tex.flatness")
    with pytest.raises(ValueError, match="fs/2"):
        FeaturePlan(["film1.psd.20-2000Hz.power"], fs=2200.0)
    with pytest.raises(ValueError, match="tex"):
        FeaturePlan(["film1.tex.colour"])


def test_band_power_matches_the_welch_integral_and_the_variance() -> None:
    fs = 20000.0
    rng = np.random.default_rng(0)
    x = rng.standard_normal((100_000, 1)) * 0.1
    names = family_names("psd", 1, fs)
    values = FeaturePlan(names, fs=fs).compute(x)
    f, p = signal.welch(x[:, 0], fs=fs, nperseg=1024)
    inside = (f >= 20) & (f < 0.45 * fs)
    assert values.sum() == pytest.approx(p[inside].sum() * (f[1] - f[0]), rel=0.02)
    # white noise: the power in [20 Hz, 0.45 fs) is that fraction of the variance
    assert values.sum() == pytest.approx(0.01 * (0.45 * fs - 20) / (fs / 2), rel=0.03)


def test_texture_descriptors_of_a_tone_and_of_noise() -> None:
    fs = 20000.0
    t = np.arange(20000) / fs
    tone = np.sin(2 * np.pi * 1000 * t)[:, None]
    names = [f"film1.tex.{n}" for n in ("centroid", "rolloff", "crest", "zcr", "rms", "kurtosis", "flatness")]
    v = dict(zip(names, FeaturePlan(names, fs=fs).compute(tone), strict=True))
    assert v["film1.tex.centroid"] == pytest.approx(1000, rel=0.02) and v["film1.tex.rolloff"] == pytest.approx(1000, rel=0.05)
    assert v["film1.tex.crest"] == pytest.approx(np.sqrt(2), rel=0.01) and v["film1.tex.zcr"] == pytest.approx(2000, rel=0.01)
    assert v["film1.tex.rms"] == pytest.approx(1 / np.sqrt(2), rel=0.01) and v["film1.tex.kurtosis"] == pytest.approx(1.5, rel=0.01)
    noise = np.random.default_rng(1).standard_normal((20000, 1))
    w = dict(zip(names, FeaturePlan(names, fs=fs).compute(noise), strict=True))
    assert w["film1.tex.flatness"] > 0.5 > v["film1.tex.flatness"]


@pytest.mark.parametrize("fs", [1000.0, 20000.0])
@pytest.mark.parametrize("channels", [1, 8])
@pytest.mark.parametrize("kind", ["zeros", "constant", "square", "spike", "shortest"])
def test_extreme_windows_give_finite_features(fs: float, channels: int, kind: str) -> None:
    names = family_names("psd", channels, fs) + family_names("tex", channels, fs)
    plan = FeaturePlan(names, fs=fs)
    n = plan.min_samples() if kind == "shortest" else int(fs // 2)
    x = {"zeros": np.zeros((n, channels)), "constant": np.full((n, channels), 3.3), "spike": np.zeros((n, channels)),
         "square": np.where(np.arange(n) % 40 < 20, 5.0, -5.0)[:, None] * np.ones((1, channels)),
         "shortest": np.random.default_rng(0).standard_normal((n, channels))}[kind]
    if kind == "spike":
        x[n // 2, 0] = 1e6
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        f = plan.compute(x)
        assert f.shape == (len(names),) and np.all(np.isfinite(f))
        assert np.all(np.isfinite(classifier_inputs(f[None, :], names)))
    if kind in ("zeros", "constant"):
        assert np.all(f[[name_family(n) == "tex" for n in names]] == 0.0)


def test_a_plan_computes_only_what_it_names() -> None:
    fs = 20000.0
    x = np.random.default_rng(3).standard_normal((10000, 2))
    every = family_names("psd", 2, fs) + family_names("tex", 2, fs)
    full = dict(zip(every, FeaturePlan(every, fs=fs).compute(x), strict=True))
    subset = [every[5], "film2.tex.centroid", every[-1]]
    assert FeaturePlan(subset, fs=fs).compute(x).tolist() == [full[n] for n in subset]
    assert FeaturePlan(["film2.tex.rms"], fs=fs).channels_needed == 2


def test_a_window_of_tiny_volts_gives_the_features_of_its_shape_and_its_scale() -> None:
    """Samples near 1e-87 V (a float recording in other units: finite and valid): every family's features are finite, the
    scale-free ones (kurtosis, skew, crest, centroid, ...) as those of the same window at 1e-3 V, the others scaled by the
    power of two (an outside review: the fourth moment underflowed to 0 and the kurtosis raised ZeroDivisionError)."""
    fs = 2200.0
    names = family_names("dwt", 2, fs) + family_names("psd", 2, fs) + family_names("tex", 2, fs)
    plan = FeaturePlan(names, fs=fs)
    x = 1e-3 * np.random.default_rng(4).standard_normal((1100, 2))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        big, tiny = plan.compute(x), plan.compute(np.ldexp(x, -280))
    assert np.all(np.isfinite(tiny))
    degree = np.array([plan._degrees[i] for i in range(len(names))])
    assert np.allclose(tiny[degree == 0], big[degree == 0], rtol=1e-12, atol=0.0)  # exact but what goes through a logarithm
    assert np.allclose(tiny[degree > 0], np.ldexp(big[degree > 0], -280 * degree[degree > 0]), rtol=1e-12, atol=0.0)
