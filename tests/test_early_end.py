"""The final label after a short quiet (detector.end_hold_s), withdrawn when the slide goes on."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from tactiled.config import Config
from tactiled.core.events import SlideEnded, SlideResult, SlideResumed
from tactiled.core.pipeline import Pipeline
from tactiled.files.recording import Recording
from tactiled.learn.model import load_model
from tactiled.run.replay import replay_recording

FS = 20_000.0


def _stream() -> tuple[Recording, list[tuple[int, int]]]:
    """Rest, a slide with a 0.15 s dip in it (longer than end_hold_s, shorter than off_hold_s), rest, a slide with a clean end, rest."""
    rng = np.random.default_rng(3)
    parts = [(0.5, 20.0), (1.0, 2000.0), (0.15, 20.0), (0.8, 2000.0), (1.0, 20.0), (0.8, 2000.0), (1.0, 20.0)]
    x = np.concatenate([rng.standard_normal((round(d * FS), 2)) * sd for d, sd in parts])
    edges = np.cumsum([0] + [round(d * FS) for d, _ in parts])
    rec = Recording(np.clip(np.rint(x), -32768, 32767).astype(np.int16), FS, 5 / 32768)
    return rec, [(int(edges[1]), int(edges[4])), (int(edges[5]), int(edges[6]))]


def _config(end_hold_s: float) -> Config:
    c = Config()
    return replace(c, detector=replace(c.detector, end_hold_s=end_hold_s))


def test_label_after_a_short_quiet_and_withdrawn_when_the_slide_goes_on() -> None:
    rec, truth = _stream()
    config = _config(0.05)
    pipe = Pipeline(config, FS, 2, rec.volts_per_count, model=load_model())
    block = 100
    seen: list[tuple[int, object]] = []  # (index fed up to, event)
    for lo in range(0, rec.samples.shape[0], block):
        seen += [(lo + block, ev) for ev in pipe.feed(lo, rec.samples[lo:lo + block])]
    seen += [(rec.samples.shape[0], ev) for ev in pipe.finish()]
    kinds = [type(ev).__name__ for _, ev in seen if not isinstance(ev, SlideResult) or ev.final]
    # slide 0: an end and a label at its dip, withdrawn, then its real end; slide 1: one end and label
    assert kinds == ["SlideStarted", "SlideEnded", "SlideResult", "SlideResumed", "SlideEnded", "SlideResult",
                     "SlideStarted", "SlideEnded", "SlideResult"], kinds
    resumed = next(ev for _, ev in seen if isinstance(ev, SlideResumed))
    assert resumed.slide_id == 0 and abs(resumed.stop - (truth[0][0] + FS)) < 0.03 * FS
    finals = [(at, ev) for at, ev in seen if isinstance(ev, SlideResult) and ev.final]
    ends = [ev for _, ev in seen if isinstance(ev, SlideEnded)]
    assert [ev.slide_id for _, ev in finals] == [0, 0, 1] and ends[1].stop == finals[1][1].stop
    # the standing labels cover the true slides, dip included, and come well before off_hold_s
    for (_, ev), (start, stop) in zip(finals[1:], truth, strict=True):
        assert abs(ev.start - start) < 0.05 * FS and abs(ev.stop - stop) < 0.03 * FS
    at, last = finals[2]
    assert at - last.stop <= (config.detector.end_hold_s + 0.03) * FS < config.detector.off_hold_s * FS
    assert pipe.slides == 2 and pipe.resumed == 1 and pipe.labels == sum(ev.label is not None for _, ev in finals[1:])


def test_early_ends_change_no_standing_result() -> None:
    rec, _ = _stream()
    model = load_model()
    early = replay_recording(rec, _config(0.05), model)
    late = replay_recording(rec, _config(0.0), model)

    def finals(rs: list[SlideResult]) -> list[tuple[object, ...]]:
        return [(r.slide_id, r.start, r.stop, r.window, r.label, r.reason, r.confidence, r.novelty) for r in rs if r.final]

    assert finals(early) == finals(late) and len(finals(late)) == 2
