"""Simulator scenes (docs/simulator.md) and the detector on each: one detection per slide, any rate, channel count and start."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from tactiled.config import Config
from tactiled.core.analysis import clipped_fraction
from tactiled.core.events import SlideResult
from tactiled.core.matching import detection_scores, match_slides
from tactiled.errors import TactiledError
from tactiled.files.recording import Recording, load_recording
from tactiled.learn.dataset import detect_slides
from tactiled.run.replay import replay_recording
from tactiled.sim.simulate import write_dataset
from tests.conftest import live_events

SCENES = ["hand", "robot", "continuous", "fluctuating", "hot-gain", "one-channel", "grating", "continuous,one-channel",
          "fluctuating,one-channel", "robot,hot-gain"]


@pytest.fixture(scope="module")
def datasets(tmp_path_factory: pytest.TempPathFactory) -> dict[str, list[Path]]:
    root = tmp_path_factory.mktemp("scenes")
    return {s: write_dataset(root / s, scene=s, seed=11, surfaces="5", files_per_surface=1, slides_per_file=3) for s in SCENES}


@pytest.mark.parametrize("scene", SCENES)
def test_detection_finds_each_slide_once(scene: str, datasets: dict[str, list[Path]]) -> None:
    paired = n_true = n_det = 0
    for path in datasets[scene]:
        rec = load_recording(path)
        truth = [(a, b) for a, b, _ in rec.slides()]
        s = detection_scores(detect_slides(rec, Config()), truth, rec.fs)
        paired, n_true, n_det = paired + s["paired"], n_true + s["n_true"], n_det + s["n_detected"]
    assert paired / n_true >= 0.98 and paired / max(1, n_det) >= 0.98, (scene, paired, n_true, n_det)


def test_scene_properties(datasets: dict[str, list[Path]]) -> None:
    cont = [load_recording(p) for p in datasets["continuous,one-channel"]]
    for rec in cont:  # one slide covering the whole file: under way at the first sample, still going at the last
        assert rec.slides() == [(0, rec.samples.shape[0], rec.slides()[0][2])] and 6.0 <= rec.samples.shape[0] / rec.fs <= 8.0
        assert rec.samples.dtype == np.float32 and rec.channels == 1 and rec.fs == 2200.0
        assert abs(float(np.median(rec.samples))) >= 0.05  # a DC offset
    hot = sorted((load_recording(p) for p in datasets["hot-gain"]), key=lambda r: float(r.ra_um[0]))  # type: ignore[index]
    clipped = [np.mean([clipped_fraction(r.samples[a:b]) for a, b, _ in r.slides()]) for r in hot]
    assert all(c == 0.0 for c in clipped[:4]) and 0.03 <= clipped[4] <= 0.5  # the roughest third (of 5: one) clips
    fl = load_recording(datasets["fluctuating"][2])
    v = fl.volts()[:, 0]
    a, b, _ = fl.slides()[0]
    hop = 400
    seg = v[a + 4000:b - 4000]
    rms = np.sqrt(np.mean(seg[: seg.size // hop * hop].reshape(-1, hop) ** 2, axis=1))
    assert 20 * np.log10(rms.min() / np.median(rms)) <= -8.0  # a dip of about 10-20 dB inside the slide


def test_bad_scene_specs_give_one_clear_error(tmp_path: Path) -> None:
    with pytest.raises(TactiledError, match="hand and robot contradict"):
        write_dataset(tmp_path, scene="hand,robot")
    with pytest.raises(TactiledError, match="unknown scene 'rough'"):
        write_dataset(tmp_path, scene="rough")
    with pytest.raises(TactiledError, match=r"unknown surface 'Ra1\.04'"):
        write_dataset(tmp_path, scene="robot", surfaces="Ra1.04")


def test_same_seed_same_files(tmp_path: Path) -> None:
    a = write_dataset(tmp_path / "a", scene="fluctuating,one-channel", seed=3, surfaces="2", files_per_surface=1, slides_per_file=2)
    b = write_dataset(tmp_path / "b", scene="fluctuating,one-channel", seed=3, surfaces="2", files_per_surface=1, slides_per_file=2)
    for x, y in zip(a, b, strict=True):
        assert np.array_equal(load_recording(x).samples, load_recording(y).samples)


def test_detector_under_way_at_start_dips_offsets_and_rates() -> None:
    """Synthetic: a slide under way at the first sample, a 0.25 s dip inside it, a DC offset and drift, at 1 kHz, 8 channels."""
    rng = np.random.default_rng(0)
    for fs, channels in ((1000.0, 8), (2200.0, 1), (20000.0, 2)):
        n = int(6 * fs)
        t = np.arange(n) / fs
        level = np.where(t < 2.0, 1.0, 0.0) + np.where((t > 3.0) & (t < 5.0), 1.0, 0.0)
        level[(t > 1.0) & (t < 1.25)] = 0.1  # a 20 dB dip for 0.25 s inside the first slide
        x = rng.standard_normal((n, channels)) * 0.002 + (level * 0.05)[:, None] * rng.standard_normal((n, channels))
        x += 0.7 + 0.05 * np.sin(2 * np.pi * 0.2 * t)[:, None]  # offset and drift
        rec = Recording(x.astype(np.float32), fs)
        found = detect_slides(rec, Config())
        assert len(found) == 2, (fs, found)
        assert found[0][0] == 0 and abs(found[0][1] / fs - 2.0) < 0.1 and abs(found[1][0] / fs - 3.0) < 0.1 and abs(found[1][1] / fs - 5.0) < 0.1
        # still going at the last sample: analysed as far as it goes
        tail = Recording(x[: int(4.0 * fs)].astype(np.float32), fs)
        last = detect_slides(tail, Config())[-1]
        assert last[1] == int(4.0 * fs) and abs(last[0] / fs - 3.0) < 0.1


def test_a_quiet_stream_is_no_slide_and_a_constant_level_is_one() -> None:
    rng = np.random.default_rng(1)
    quiet = Recording((rng.standard_normal((40000, 2)) * 0.002).astype(np.float32), 20000.0)
    # a stream at one level throughout cannot tell rest from slide: it is one slide (a continuous recording)
    assert detect_slides(quiet, Config()) == [(0, 40000)]
    silent = Recording(np.zeros((40000, 2), dtype=np.int16), 20000.0, 5 / 32768)
    assert detect_slides(silent, Config()) == []


@pytest.fixture(scope="module")
def small_model(tmp_path_factory: pytest.TempPathFactory, datasets: dict[str, list[Path]]) -> object:
    from tactiled.learn.dataset import load_recordings
    from tactiled.learn.search import Candidate, search

    root = tmp_path_factory.mktemp("model")
    recs = load_recordings(write_dataset(root, scene="continuous,one-channel", seed=12, surfaces="5", files_per_surface=2))
    model = search(recs, Config(), folds=2, candidates=[Candidate(("psd",), "linear", 0.5)]).model
    # trained on continuous slides only: a fluctuating one may be unknown; here every slide gets its label
    model.novelty_threshold = model.novelty_distance_threshold = math.inf
    return model


@pytest.mark.parametrize("scene", ["continuous,one-channel", "fluctuating,one-channel"])
def test_same_events_and_labels_in_any_block_size(scene: str, datasets: dict[str, list[Path]], small_model: object) -> None:
    rec = load_recording(datasets[scene][1])
    runs = []
    for block in (1, 7, 64, rec.samples.shape[0]):
        runs.append([(r.start, r.stop, r.window, r.label, r.reason, r.final, round(r.confidence or 0, 9)) for r in
                     replay_recording(rec, Config(), small_model, block=block)])
    live = [(r.start, r.stop, r.window, r.label, r.reason, r.final, round(r.confidence or 0, 9)) for r in
            live_events(rec, Config(), small_model, 64) if isinstance(r, SlideResult)]  # the daemon's path, a window at a time
    assert runs[0] == runs[1] == runs[2] == runs[3] == live and any(r[3] for r in runs[0])
    finals = [r for r in runs[0] if r[5]]
    truth = [(a, b) for a, b, _ in rec.slides()]
    assert all(j is not None for j in match_slides([(r[0], r[1]) for r in finals], truth))


def test_a_model_trained_on_clipping_surfaces_knows_them_all_and_scores_every_slide(datasets: dict[str, list[Path]]) -> None:
    """Clipping is a quality figure: the hot-gain surfaces that clip stay in training and every true slide is scored."""
    from tactiled.learn.score import score_recordings
    from tactiled.learn.search import Candidate
    from tactiled.learn.train import train

    paths = datasets["hot-gain"]
    result = train(paths, Config(), folds=2, candidates=[Candidate(("psd",), "linear", 0.5)], group_by="slide")
    recs = [(str(p), load_recording(p)) for p in paths]
    surfaces = sorted({s for _, r in recs for _, _, s in r.slides()})
    assert sorted(result.model.classes) == surfaces
    report = score_recordings(recs, Config(), result.model)
    assert report["n"] == sum(len(r.slides()) for _, r in recs) == 15 and report["coverage"] == 1.0
