"""The detector says when a slide in progress goes quiet (Quiet) and when that quiet was only a dip (Loud); the pipeline
gives no provisional label from a window that reaches into a quiet until it knows the slide goes on, so a slide's last
provisional label never comes from its lift-off."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from tactiled.config import Config
from tactiled.core.analysis import AnalysisSettings
from tactiled.core.detect import SlideDetector
from tactiled.core.events import Loud, Offset, Onset, Pause, Quiet, Resume, SlideResult
from tactiled.core.pipeline import Pipeline
from tactiled.files.recording import Recording
from tactiled.learn.model import load_model
from tactiled.run.replay import replay_recording
from tactiled.sim.physics import SensorSimulator, SimParams, pick_surfaces

FS = 20_000.0


def _noise(seconds: float, level: float, rng: np.random.Generator) -> np.ndarray:
    return level * rng.standard_normal((round(seconds * FS), 2))


def test_a_dip_is_quiet_then_loud_a_longer_one_a_pause_and_the_end_quiet_then_offset() -> None:
    rng = np.random.default_rng(0)
    # rest, a slide with a 30 ms dip (15 ms below the quiet level, after the envelope's own smoothing: shorter than end_hold_s,
    # 50 ms) and a 100 ms one (longer: a Pause, then a Resume before off_hold_s, 300 ms), rest
    parts = [(1.0, 1e-3), (0.5, 0.1), (0.03, 1e-3), (0.5, 0.1), (0.1, 1e-3), (0.5, 0.1), (1.0, 1e-3)]
    volts = np.concatenate([_noise(s, a, rng) for s, a in parts])
    det = SlideDetector(Config().detector, FS, 2)
    events = det.feed(0, volts) + det.finish()
    kinds = [type(e) for e in events]
    assert kinds == [Onset, Quiet, Loud, Quiet, Pause, Resume, Quiet, Pause, Offset], events
    dip, long_dip, end = (e.stop for e in events if isinstance(e, Quiet))
    bounds = np.cumsum([round(s * FS) for s, _ in parts])
    for quiet, truth in ((dip, bounds[1]), (long_dip, bounds[3]), (end, bounds[5])):
        assert 0 <= quiet - truth <= 0.03 * FS  # where the envelope fell below the quiet level (its smoothing: 25 ms here)
    assert events[-1].stop == end and all(e.at >= e.stop for e in events if isinstance(e, Quiet))


def test_no_provisional_label_comes_from_a_window_past_its_slides_end() -> None:
    """Nine slides over three grades with rests between, replayed with the shipped model: every provisional label's
    windows end where its slide does at the latest (before the Quiet events, three of this recording's did not, the
    last window of a slide reaching into the lift-off and the rest after it, and their labels were wrong)."""
    p = SimParams()
    sim = SensorSimulator(p, seed=5)
    surfaces = pick_surfaces("Ra0.61,Ra1.40,Ra3.19")
    for i in range(9):
        sim.add_rest(0.6)
        sim.add_slide(surfaces[i % 3], 1.0 + 0.15 * (i % 4))
    sim.add_rest(0.8)
    rec = Recording(sim.read(sim.scheduled_end), p.fs, p.volts_per_count)
    results = replay_recording(rec, Config(), load_model())
    finals = {r.slide_id: r for r in results if r.final}
    provisional = [r for r in results if not r.final]
    assert len(finals) == 9 and len(provisional) >= 9
    assert all(r.window[1] <= finals[r.slide_id].stop for r in provisional), [(r.window, finals[r.slide_id].stop) for r in provisional]


class _Flipping:
    """A classifier whose label flips with every window a slide adds (so each window gives a provisional label), sure of it."""

    def __init__(self, settings: AnalysisSettings) -> None:
        self.classes, self.fingerprint, self.settings = ["odd", "even"], "flipping", settings

    def assess_many(self, features: np.ndarray, rows: Sequence[tuple[int, int]],
                    final: bool = True) -> tuple[np.ndarray, list[float], list[float | None]]:
        proba = np.array([[0.9, 0.1] if (hi - lo) % 2 else [0.1, 0.9] for lo, hi in rows])
        return proba, [0.9] * len(rows), [None] * len(rows)


def test_a_window_held_over_a_dip_gets_its_provisional_label_when_the_slide_goes_on() -> None:
    """A 30 ms dip whose quiet (Quiet at 29 900, Loud at 30 100) holds the window that completes at 30 000: its
    provisional label comes at the Loud, and every window of the slide has one."""
    rng = np.random.default_rng(0)
    parts = [(1.0, 1e-3), (0.465, 0.1), (0.03, 1e-3), (0.5, 0.1), (1.0, 1e-3)]  # the slide from 20 000, the dip from 29 300
    volts = np.concatenate([_noise(s, a, rng) for s, a in parts])
    config = Config()
    settings = replace(AnalysisSettings.from_config(config, 2, FS), duration_s=0.25, hop_s=0.0, names=("film1.tex.rms",))
    pipe = Pipeline(config, FS, 2, 1.0, integer=False, model=_Flipping(settings))
    seen = [ev for lo in range(0, len(volts), 800) for ev in pipe.feed(lo, volts[lo:lo + 800])] + pipe.finish()
    results = [ev for ev in seen if isinstance(ev, SlideResult)]
    provisional = [r for r in results if not r.final]
    final = next(r for r in results if r.final)
    assert final.start == 20_000
    windows = (final.stop - final.start) // 5_000
    assert [r.quality["windows"] for r in provisional] == list(range(1, windows + 1))  # one a window, the held one included
    assert all(r.window[1] <= final.stop for r in provisional)
