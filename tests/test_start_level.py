"""The detector's start level, learnt in training from the recordings' rests and slides (tactiled.learn.levels): a stream
that begins in a slide is known as one after ``detector.initial_s`` (its labels flow while the finger still slides), a
stream at rest is rest from then on (never one long slide at its end), and a quiet surface slid first stays a slide when
a louder one follows. Without a start level (no rests in the training recordings) the detector decides as before."""

from __future__ import annotations

import copy
import functools
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tactiled.config import Config
from tactiled.core.detect import SlideDetector, front_end_settings
from tactiled.core.events import DetectorEvent, Offset, Onset
from tactiled.core.pipeline import Pipeline
from tactiled.errors import ModelError
from tactiled.files.recording import Recording, load_recording
from tactiled.learn.levels import hop_envelope, start_level
from tactiled.learn.model import load_model
from tactiled.sim.physics import SensorSimulator, SimParams, output, pick_surfaces, simulate_file
from tests.conftest import cli_here

FS = 20_000
DETECTOR = Config().detector


def _recording(params: SimParams, surface: str, slides: int, seed: int) -> Recording:
    sim = simulate_file(params, pick_surfaces(surface)[0], slides, seed)
    return Recording(sim.samples, params.fs, params.volts_per_count, slide_start=np.array([t.start for t in sim.truth]),
                     slide_stop=np.array([t.stop for t in sim.truth]))


@functools.cache
def _level() -> float:
    """The start level learnt from six recordings of three slides each, rests between (once per test process)."""
    params = SimParams()
    recs = [_recording(params, s, 3, seed) for seed, s in enumerate(("Ra0.44", "Ra1.40", "Ra4.43") * 2)]
    level = start_level(recs, [list(zip(r.slide_start.tolist(), r.slide_stop.tolist(), strict=True)) for r in recs], DETECTOR)
    assert level is not None
    return level


def _models() -> tuple[Any, Any]:
    """(the shipped model without a start level, the same with the level of :func:`_level`)."""
    plain: Any = copy.copy(load_model())
    plain.start_level = None
    knowing: Any = copy.copy(load_model())
    knowing.start_level, knowing.start_front = _level(), front_end_settings(DETECTOR)
    return plain, knowing


def _volts(*parts: tuple[str | None, float], seed: int = 5, gain: float = 1.0) -> np.ndarray:
    """A stream of the simulator's volts: each part a slide over a surface (or rest, None) of so many seconds."""
    params = SimParams()
    sim = SensorSimulator(params, seed=seed)
    for surface, seconds in parts:
        if surface is None:
            sim.add_rest(seconds)
        else:
            sim.add_slide(pick_surfaces(surface)[0], seconds)
    counts = output(sim.read_volts(sim.scheduled_end) * gain, params)
    return np.asarray(counts, dtype=np.float64) * params.volts_per_count


def _events(volts: np.ndarray, level: float | None, block: int = 2000) -> list[tuple[int, DetectorEvent]]:
    """(samples fed when it came, event) of every event of ``volts`` fed in blocks, then the stream's end."""
    det = SlideDetector(DETECTOR, FS, volts.shape[1], start_level=level)
    out: list[tuple[int, DetectorEvent]] = []
    for lo in range(0, volts.shape[0], block):
        out += [(lo + block, e) for e in det.feed(lo, volts[lo:lo + block])]
    out += [(volts.shape[0], e) for e in det.finish()]
    return out


def _spans(events: list[tuple[int, DetectorEvent]]) -> list[tuple[int, int, str]]:
    return [(e.start, e.stop, e.reason) for _, e in events if isinstance(e, Offset)]


def test_training_recordings_with_rests_give_a_level_between_rest_and_slides_and_continuous_ones_none() -> None:
    level = _level()
    vpc = SimParams().volts_per_count

    def env(volts: np.ndarray) -> np.ndarray:
        return hop_envelope(Recording(np.rint(volts / vpc).astype(np.int16), FS, vpc), DETECTOR)[0][100:-40]  # past the settling

    assert np.quantile(env(_volts((None, 3.0))), 0.99) < level < np.quantile(env(_volts(("Ra0.44", 3.0))), 0.2)  # rest, the quietest grade
    continuous = SimParams(continuous=True)
    recs = [_recording(continuous, s, 1, seed) for seed, s in enumerate(("Ra0.44", "Ra1.40", "Ra4.43"))]
    assert start_level(recs, [[(0, r.samples.shape[0])] for r in recs], DETECTOR) is None  # no rest to learn from


def test_a_stream_that_begins_in_a_slide_is_one_from_initial_s_with_the_same_end() -> None:
    volts = _volts(("Ra2.29", 2.5), (None, 2.0), ("Ra2.29", 1.2), (None, 1.5))
    with_level, without = _events(volts, _level()), _events(volts, None)
    first = next((fed, e) for fed, e in with_level if isinstance(e, Onset))
    assert first[1].start == 0 and first[0] <= round((DETECTOR.initial_s + 0.1) * FS)  # known within initial_s, not at the end
    assert next(fed for fed, e in without if isinstance(e, Onset)) > round(2.5 * FS)  # before: only once the quiet came
    assert _spans(with_level) == _spans(without)  # the same slides


def test_a_stream_at_rest_gives_no_slide_at_its_end() -> None:
    volts = _volts((None, 3.0))
    assert _spans(_events(volts, _level())) == []
    assert [r for _, _, r in _spans(_events(volts, None))] == ["end_of_stream"]  # without a level: the whole stream one slide


def test_a_quiet_surface_slid_first_stays_a_slide_when_a_louder_one_follows() -> None:
    """Two slides: the quiet surface's, ended where the louder one begins, and the louder one's (without a level the
    first 2 s were taken for rest)."""
    volts = _volts(("Ra0.44", 2.0), ("Ra4.43", 2.0), (None, 2.0))
    spans = _spans(_events(volts, _level()))
    assert [r for _, _, r in spans] == ["quiet", "quiet"] and spans[0][0] == 0, spans
    assert abs(spans[0][1] - 2 * FS) < 0.2 * FS and spans[1][0] == spans[0][1] and spans[1][1] >= round(3.9 * FS), spans
    assert _spans(_events(volts, None))[0][0] >= 1.8 * FS  # before


def test_labels_flow_while_the_finger_slides_in_the_slide_the_stream_began_in() -> None:
    """The pipeline with a model that learnt a start level: provisional labels before the slide's end is fed."""
    volts = _volts(("Ra2.29", 3.0), (None, 1.5))
    counts = np.rint(volts / SimParams().volts_per_count).astype(np.int16)
    model: Any = copy.copy(load_model())
    model.start_front = front_end_settings(DETECTOR)
    for level, want in ((_level(), True), (None, False)):
        model.start_level = level
        pipe = Pipeline(Config(), FS, 2, SimParams().volts_per_count, model=model)
        early = [r for lo in range(0, round(2.9 * FS), 2000) for r in pipe.feed(lo, counts[lo:lo + 2000]) if getattr(r, "final", None) is False]
        assert bool(early) is want


def test_train_learns_the_level_and_the_model_file_keeps_it(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "d"
    assert cli_here(capfd, "simulate", "dataset", "--out", str(data), "--surfaces", "3", "--files-per-surface", "2", "--slides-per-file", "3",
                    "--scene", "robot", "--jobs", "1").returncode == 0
    out = tmp_path / "m.npz"
    res = cli_here(capfd, "train", "--method", "quick", "--folds", "2", "-o", str(out), *map(str, sorted(data.glob("*.npz"))))
    assert res.returncode == 0
    level = load_model(out).start_level
    assert f"train: start level {level:.3g} (the quietest slides" in res.stderr  # train says it kept one, and why
    assert level is not None and level > 0
    recs = [load_recording(p) for p in sorted(data.glob("*.npz"))]
    assert level == pytest.approx(start_level(recs, [list(zip(r.slide_start.tolist(), r.slide_stop.tolist(), strict=True)) for r in recs],
                                              DETECTOR), rel=0.5)


@pytest.mark.parametrize("value", [-1.0, 0.0, float("inf"), "loud", True])
def test_a_model_file_with_a_bad_start_level_is_refused_in_one_line(tmp_path: Path, value: Any) -> None:
    model: Any = load_model()
    model.start_level = value
    path = tmp_path / "bad.npz"
    model.save(path)  # the fingerprint covers it: only the value is wrong
    with pytest.raises(ModelError, match=r"header.detector.start_level: must be a positive finite number") as err:
        load_model(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_the_slide_the_stream_began_in_gives_the_same_labels_whatever_the_block_size() -> None:
    """Its quiets are reported as a slide's (Quiet, Loud): a window reaching into the quiet after it waits, so a daemon fed in
    small batches publishes what a replay in large blocks does (no provisional label from the rest after the slide)."""
    import dataclasses

    from tactiled.core.events import SlideResult

    volts = _volts(("Ra2.29", 2.5), (None, 2.0), ("Ra2.29", 1.2), (None, 1.5))
    counts = np.rint(volts / SimParams().volts_per_count).astype(np.int16)
    model: Any = _models()[1]

    def published(block: int) -> list[tuple[Any, ...]]:
        pipe = Pipeline(Config(), FS, 2, SimParams().volts_per_count, model=model)
        events = [e for lo in range(0, counts.shape[0], block) for e in pipe.feed(lo, counts[lo:lo + block])] + pipe.finish()
        return [("result", e.slide_id, e.start, e.stop, e.label, e.final) if isinstance(e, SlideResult) else
                (type(e).__name__, *dataclasses.astuple(e)) for e in events]

    small = published(800)
    assert small == published(65536)
    assert any(k[0] == "result" and k[1] == 0 and k[5] is False for k in small)  # provisional labels of the first slide


def test_a_few_knocks_between_slides_keep_the_level() -> None:
    """A 4 ms knock every 2 s of rest, as loud as the slides' peaks: the rests are judged as the detector judges them (a
    median of three hops), so the level is learnt still (the single hops' 99th percentile lost it to 9 knocks in 50 s)."""
    params = SimParams()
    recs = [_recording(params, s, 3, seed) for seed, s in enumerate(("Ra0.44", "Ra1.40", "Ra4.43") * 2)]
    t = np.arange(round(0.004 * FS)) / FS
    knocked, knocks = [], 0
    for r in recs:
        x = r.samples.astype(np.float64)
        burst = np.percentile(np.abs(x[r.slide_start[0]:r.slide_stop[0]]), 99) * np.exp(-t / 0.001) * np.sin(2 * np.pi * 3000 * t)
        near = np.zeros(len(x), dtype=bool)
        for a, b in zip(r.slide_start, r.slide_stop, strict=True):
            near[max(0, a - round(0.35 * FS)): b + round(0.35 * FS)] = True
        for p in range(round(0.5 * FS), len(x) - len(t), round(2.0 * FS)):
            if not near[p:p + len(t)].any():
                x[p:p + len(t)] += burst[:, None]
                knocks += 1
        knocked.append(Recording(np.clip(np.rint(x), -32768, 32767).astype(np.int16), r.fs, r.volts_per_count, slide_start=r.slide_start,
                                 slide_stop=r.slide_stop))
    assert knocks >= 3, knocks
    spans = [list(zip(r.slide_start.tolist(), r.slide_stop.tolist(), strict=True)) for r in recs]
    assert start_level(knocked, spans, DETECTOR) == pytest.approx(_level(), rel=0.2)


def test_a_model_with_a_level_loaded_while_the_start_is_undecided_decides_it() -> None:
    """The daemon started with a model that knows no level, the finger sliding; a model that knows one is loaded a second
    later: the slide under way is known at once and labelled as it goes (the level reached only detectors made later)."""
    from tactiled.core.events import SlideStarted

    volts = _volts(("Ra2.29", 3.0), (None, 1.5))
    counts = np.rint(volts / SimParams().volts_per_count).astype(np.int16)
    plain, knowing = _models()
    pipe = Pipeline(Config(), FS, 2, SimParams().volts_per_count, model=plain)
    first = [e for lo in range(0, FS, 2000) for e in pipe.feed(lo, counts[lo:lo + 2000])]
    assert first == [] and pipe.detector.undecided
    pipe.swap_model(knowing)
    later = [e for lo in range(FS, round(2.9 * FS), 2000) for e in pipe.feed(lo, counts[lo:lo + 2000])]
    assert any(isinstance(e, SlideStarted) for e in later)
    assert any(getattr(e, "final", None) is False for e in later)  # provisional labels before the slide's end


def test_a_shadow_splits_the_stream_as_the_live_pipeline_after_an_unplug() -> None:
    """A shadow model with a level follows the live pipeline's detector, after an unplug too (each made its new detector
    with its own model's level, so the shadow's slides were not the live ones)."""
    from tactiled.core.events import SlideEnded, SlideStarted

    volts = _volts(("Ra2.29", 4.0), (None, 1.5))
    counts = np.rint(volts / SimParams().volts_per_count).astype(np.int16)
    plain, knowing = _models()
    live = Pipeline(Config(), FS, 2, SimParams().volts_per_count, model=plain)
    shadow = Pipeline(Config(), FS, 2, SimParams().volts_per_count, model=knowing)
    shadow.follow(live)

    def slides(events: list[tuple[int, Any]]) -> list[tuple[Any, ...]]:  # each with the samples fed when it came
        return [(type(e).__name__, e.slide_id, e.start, fed) for fed, e in events if isinstance(e, SlideStarted | SlideEnded)]

    got: dict[str, list[tuple[int, Any]]] = {"live": [], "shadow": []}
    for lo in range(0, counts.shape[0], 2000):
        if lo == 2 * FS:  # the port lost and back
            got["live"] += [(lo, e) for e in live.disconnected()]
            got["shadow"] += [(lo, e) for e in shadow.disconnected()]
        got["live"] += [(lo, e) for e in live.feed(lo, counts[lo:lo + 2000])]
        got["shadow"] += [(lo, e) for e in shadow.feed(lo, counts[lo:lo + 2000])]
    got["live"] += [(counts.shape[0], e) for e in live.finish()]
    got["shadow"] += [(counts.shape[0], e) for e in shadow.finish()]
    assert slides(got["shadow"]) == slides(got["live"]) and slides(got["live"])


def test_a_level_is_used_only_under_the_front_end_it_was_measured_with(tmp_path: Path) -> None:
    """Another mains notch (60 Hz where the model learnt at 50, or none) gives other envelope values: a rest above the
    level was one slide for good, every slide after it lost (a review). The level is used only under its own settings."""
    from tactiled.config import DetectorConfig

    _, knowing = _models()
    params = SimParams()
    counts = np.rint(_volts((None, 1.0), ("Ra2.29", 1.2), (None, 1.0), ("Ra2.29", 1.2), (None, 1.0)) / params.volts_per_count).astype(np.int16)
    for mains in (50.0, 60.0, 0.0):
        config = Config().override({"detector.mains_hz": mains})
        pipe = Pipeline(config, FS, 2, params.volts_per_count, model=knowing)
        assert (pipe.detector.start_level is not None) is (mains == 50.0)
        events = [e for lo in range(0, counts.shape[0], 4000) for e in pipe.feed(lo, counts[lo:lo + 4000])] + pipe.finish()
        assert sum(getattr(e, "final", False) is True for e in events) == 2, (mains, events)
    assert front_end_settings(DetectorConfig(mains_hz=60.0)) != knowing.start_front


def test_a_rest_louder_than_the_level_costs_the_start_not_every_slide() -> None:
    """A rest above the model's level (louder where the daemon runs than in training: motors, hum) is taken for a slide
    at first; the first real slide's rise withdraws it (cancelled, too short to be a slide) and every slide is found
    (it stayed one slide for good: 0 slides live in 21 s)."""
    volts = _volts((None, 2.0), ("Ra2.29", 1.2), (None, 1.5), ("Ra2.29", 1.2), (None, 1.5))
    vpc = SimParams().volts_per_count
    rest = float(np.quantile(hop_envelope(Recording(np.rint(volts[:FS] / vpc).astype(np.int16), FS, vpc), DETECTOR)[0][100:], 0.8))
    plain = _spans(_events(volts, None))
    for level, withdrawn in ((rest / 2, "too_short"), (rest / 1000, "quiet")):  # just below the rest: withdrawn; far below: a slide
        spans = _spans(_events(volts, level))
        assert spans[0][0] == 0 and spans[0][2] == withdrawn, spans  # the early "slide", ended where the first real one begins
        assert spans[1:] == plain, (spans, plain)


@pytest.mark.parametrize("lead_s", [0.1, 0.2, 0.3])
def test_a_stream_begun_just_before_a_slide_finds_it_from_rest_and_ends_it_at_a_short_rest(lead_s: float) -> None:
    """A recording or daemon started ``lead_s`` before the finger moves (less than initial_s): the initial level is a
    slide's, yet the stream began at rest. The slide starts where it does, not at the first sample, and a rest of 0.55 s
    (shorter than the off_hold_s + initial_s that ends a slide the stream began in) ends it: it took the next slide in, up
    to the first longer rest, and the rest before it into its label."""
    volts = _volts((None, lead_s), ("Ra1.40", 1.5), (None, 0.55), ("Ra3.76", 1.2), (None, 1.0), ("Ra0.85", 1.2), (None, 1.0))
    spans = _spans(_events(volts, _level()))
    truth = [(lead_s, lead_s + 1.5), (lead_s + 2.05, lead_s + 3.25), (lead_s + 4.25, lead_s + 5.45)]
    assert len(spans) == 3, spans
    for (a, b, reason), (ta, tb) in zip(spans, truth, strict=True):
        assert reason == "quiet" and abs(a / FS - ta) <= 0.1 and abs(b / FS - tb) <= 0.1, (spans, truth)
