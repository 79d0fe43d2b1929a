"""Replay's offline path gives the live path's events: the detector over the whole recording first, then the windows
analysed many at a time, against the daemon's path (40 ms blocks, one window at a time), on a recording with slides,
provisional labels, withdrawn ends and extreme windows (clipped, spiky, silent, lost samples)."""

from __future__ import annotations

import dataclasses
import warnings
from typing import Any

import numpy as np
import pytest

from tactiled.config import Config
from tactiled.core.analysis import Analyser, AnalysisSettings
from tactiled.core.events import PipelineEvent
from tactiled.core.features import FeaturePlan, family_names, feature_names
from tactiled.files.recording import Recording
from tactiled.learn.model import load_model
from tactiled.run.replay import replay_recording
from tactiled.sim.physics import SensorSimulator, SimParams, default_surfaces
from tests.conftest import live_events

LIVE_BLOCK = 800  # 40 ms at 20 kHz: what the daemon hands the pipeline


@pytest.fixture(scope="module")
def extreme_recording() -> Recording:
    """40 s of the hand scene with, inside true slides, a clipped stretch, spikes, digital silence and lost samples
    (a short loss that is filled, a long one that rejects its window), and digital silence at rest."""
    p = SimParams()
    sim = SensorSimulator(p, 3)
    n = int(40 * p.fs)
    sim.schedule_random(default_surfaces(), n)
    x = sim.read(n)
    slides = [(t.start, t.stop) for t in sim.truth if t.stop <= n and t.stop - t.start > p.fs]
    assert len(slides) >= 5
    lost = []
    (a, _), (c, d), (e, _), (g, _), (i, _) = slides[:5]
    x[a + 6000: a + 8000: 2] = 32767  # clipped: held at the rail
    x[a + 6001: a + 8000: 2] = -32768
    x[c + 1000: d - 1000: 397, 0] = 32767  # single-sample spikes
    x[e + 5200: e + 5260] = 0  # 3 ms of digital silence inside a slide
    x[max(0, a - 30000): a - 10000] = 0  # a second of digital silence at rest
    lost += [(g + 2000, 40), (g + 12000, 400)]  # 40 lost rows are filled in; 400 (> 2 % of a window) reject it
    x[i + 3000: i + 3001, 1] = -32768
    x[i + 8000: i + 10400] = 0  # a 120 ms dip: the end published after 50 ms of quiet, then withdrawn
    for pos, count in lost:
        x[pos: pos + count] = 0
    return Recording(x, p.fs, p.volts_per_count, lost=np.array(lost, dtype=np.int64))


def _fields(ev: PipelineEvent) -> dict[str, Any]:
    d = dataclasses.asdict(ev)
    d.pop("compute_ms", None)  # a timing
    d["type"] = type(ev).__name__
    features = d.pop("features", None)
    d["features"] = None if features is None else np.asarray(features).tobytes()  # bit for bit
    return d


def test_replay_gives_the_live_paths_events_bit_for_bit(extreme_recording: Recording) -> None:
    """replay_recording (the detector first, then every window its slides need in batches, then the events) in any block
    size against the live path, every field of every event (features bit for bit)."""
    rec = extreme_recording
    model = load_model()
    live = [_fields(ev) for ev in live_events(rec, Config(), model, LIVE_BLOCK)]
    for block in (LIVE_BLOCK, 65536, rec.samples.shape[0]):
        events: list[PipelineEvent] = []
        replay_recording(rec, Config(), model, block=block, on_event=events.append)
        assert [_fields(ev) for ev in events] == live, block
    results = [e for e in live if e["type"] == "SlideResult"]
    finals = [r for r in results if r["final"]]
    assert len(finals) >= 5 and any(not r["final"] and r["label"] for r in results)  # provisional labels too
    assert any(r["quality"]["saturated"] > 0 for r in finals) and any(r["quality"]["spikes"] > 0 for r in finals)
    assert any(r["quality"]["lost"] > 0 for r in finals) and any(e["type"] == "SlideResumed" for e in live)


def test_many_windows_at_once_are_each_window_alone() -> None:
    """Analyser.analyse_many and FeaturePlan.compute_many against one window at a time: silent, constant, clipped, spiky,
    lost rows, and (float volts) samples whose energies are beyond float64, in one batch."""
    rng = np.random.default_rng(4)
    n = 3000
    noise = (rng.standard_normal((n, 2)) * 3000).astype(np.int16)
    clipped = np.where(np.arange(n) % 40 < 20, 32767, -32768)[:, None].repeat(2, axis=1).astype(np.int16)
    spiky = noise.copy()
    spiky[::301, 0] = 32767
    windows = np.stack([noise, np.zeros((n, 2), np.int16), np.full((n, 2), 700, np.int16), clipped, spiky, noise])
    valid = np.ones(windows.shape[:2], dtype=bool)
    valid[4, 100:130] = False  # filled in
    valid[5, 100:200] = False  # over max_lost: no features
    names = tuple(feature_names(2) + family_names("psd", 2, 20000.0) + family_names("tex", 2, 20000.0))
    for method in ("mad", "hampel"):
        analyser = Analyser(AnalysisSettings(names=names, spikes=method), 20000.0, 5 / 32768, True)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            many = analyser.analyse_many(windows, valid)
        for w, v, got in zip(windows, valid, many, strict=True):
            alone = analyser.analyse(w, v)
            assert (got.reason, got.quality) == (alone.reason, alone.quality)
            assert (got.features is None) == (alone.features is None)
            if got.features is not None and alone.features is not None:
                assert np.array_equal(got.features, alone.features) and np.all(np.isfinite(got.features))
        assert [r.reason for r in many] == [None, None, None, None, None, "samples_lost"] and many[4].quality["spikes"] > 0
    huge = np.stack([rng.standard_normal((n, 2)), rng.standard_normal((n, 2)) * 1e307, rng.standard_normal((n, 2)) * 1e100])
    floats = Analyser(AnalysisSettings(names=names), 20000.0, 1.0, False).analyse_many(huge)
    assert [r.reason for r in floats] == [None, "non_finite", None]
    plan = FeaturePlan(names)
    assert np.array_equal(plan.compute_many(huge[[0, 2]]), np.stack([plan.compute(huge[0]), plan.compute(huge[2])]))


def test_assessments_of_many_slides_at_once_are_each_alone() -> None:
    """Model.assess_many (replay assesses every prefix of every slide of a recording in one call) against Model.assess of
    each: silent, saturated, constant, spiky and noisy windows, one slide's prefixes and slides of their own, final and
    provisional, the shipped model's lean and scikit-learn pipelines: bit for bit, and finite."""
    rng = np.random.default_rng(7)
    n = 5000
    noise = (rng.standard_normal((n, 2)) * 3000).astype(np.int16)
    spiky = noise.copy()
    spiky[::301, 0] = 32767
    saturated = np.where(np.arange(n) % 40 < 20, 32767, -32768)[:, None].repeat(2, axis=1).astype(np.int16)
    windows = np.stack([noise, np.zeros((n, 2), np.int16), saturated, np.full((n, 2), 700, np.int16), spiky,
                        (rng.standard_normal((n, 2)) * 300).astype(np.int16)])
    for model in (load_model(), load_model(lean=False)):
        analysed = Analyser(model.settings, model.fs, 5 / 32768, True).analyse_many(windows)
        x = np.stack([r.features for r in analysed if r.features is not None])
        assert x.shape[0] == len(windows)
        rows = [(0, i) for i in range(1, len(x) + 1)] + [(i, i + 1) for i in range(len(x))] + [(1, 3), (2, 5)]
        for final in (True, False):
            proba, confidence, novelty = model.assess_many(x, rows, final)
            assert np.all(np.isfinite(proba)) and all(np.isfinite(confidence)) and all(v is not None and np.isfinite(v) for v in novelty)
            for i, (lo, hi) in enumerate(rows):
                p, c, v = model.assess(x[lo:hi], final)
                assert np.array_equal(proba[i], p) and confidence[i] == c and novelty[i] == v, (final, lo, hi)
