"""Where a slide begins when the stream's start was undecided and a rise showed it began at rest (an outside audit,
nineteenth session: on a fingertip sliding from the first sample with dips, a slide was reported 2.85 s after it began).

Sans-IO: the detector fed a synthetic stream, every number in the docstrings.
"""

from __future__ import annotations

import numpy as np

from tactiled.config import Config
from tactiled.core.detect import SlideDetector
from tactiled.core.events import Onset

FS = 20_000.0


def _stream(parts: list[tuple[float, float]], seed: int = 3) -> np.ndarray:
    """White noise in pieces of (seconds, RMS volts), two films, (n, 2) float64."""
    rng = np.random.default_rng(seed)
    return np.concatenate([rng.normal(0.0, rms, (round(s * FS), 2)) for s, rms in parts])


def test_a_rise_from_rest_begins_before_a_dip_shorter_than_the_quiet_that_ends_a_slide() -> None:
    """0.5 s of rest, then a slide at 5 times its RMS (14 dB) that dips back to rest for 0.2 s after its first 0.1 s. The
    rise shows only once most of a 0.4 s window is loud (about 1 s in); the slide began at 0.5 s, since a dip shorter than
    ``off_hold_s`` (0.3 s) does not end a slide, so it cannot start one. It was reported at the end of the dip, 0.8 s."""
    config = Config().detector
    det = SlideDetector(config, FS, 2)
    x = _stream([(0.5, 0.01), (0.1, 0.05), (0.2, 0.01), (1.5, 0.05), (1.0, 0.01)])
    events = [ev for i in range(0, x.shape[0], 400) for ev in det.feed(i, x[i:i + 400])]
    onsets = [ev for ev in events if isinstance(ev, Onset)]
    assert len(onsets) == 1 and abs(onsets[0].start / FS - 0.5) < 0.02, onsets


def test_a_rise_after_a_quiet_as_long_as_the_one_that_ends_a_slide_begins_after_it() -> None:
    """The same, with the dip 0.4 s long (longer than ``off_hold_s``): the loud 0.1 s before it is no part of the slide,
    which begins after the dip, at 1.0 s."""
    det = SlideDetector(Config().detector, FS, 2)
    x = _stream([(0.5, 0.01), (0.1, 0.05), (0.4, 0.01), (1.5, 0.05), (1.0, 0.01)])
    events = [ev for i in range(0, x.shape[0], 400) for ev in det.feed(i, x[i:i + 400])]
    onsets = [ev for ev in events if isinstance(ev, Onset)]
    assert onsets and abs(onsets[-1].start / FS - 1.0) < 0.02, onsets


def test_taps_at_rest_before_the_rise_are_no_part_of_the_slide() -> None:
    """2 s of rest with a 5 ms tap every 0.25 s, then a slide from 2.0 s: the slide begins at 2.0 s. A walk back over each
    hop's own envelope linked the taps, less than ``off_hold_s`` apart, and began it at the first (0.1 s; a review)."""
    det = SlideDetector(Config().detector, FS, 2)
    parts: list[tuple[float, float]] = []
    for _ in range(8):
        parts += [(0.1, 0.01), (0.005, 0.05), (0.145, 0.01)]
    x = _stream([*parts, (1.5, 0.05), (1.0, 0.01)])
    events = [ev for i in range(0, x.shape[0], 400) for ev in det.feed(i, x[i:i + 400])]
    onsets = [ev for ev in events if isinstance(ev, Onset)]
    assert len(onsets) == 1 and abs(onsets[0].start / FS - 2.0) < 0.02, onsets


def _slides(x: np.ndarray) -> list[tuple[float, float]]:
    """(start, stop) in s of every slide the detector finds in ``x``, fed in blocks of 2000 samples, without a start level."""
    from tactiled.core.events import Offset

    det = SlideDetector(Config().detector, FS, 2)
    events = [e for i in range(0, len(x), 2000) for e in det.feed(i, x[i:i + 2000])] + det.finish()
    return [(e.start / FS, e.stop / FS) for e in events if isinstance(e, Offset) and e.reason != "too_short"]


def test_a_stream_begun_in_a_slide_with_a_tap_in_every_rest_is_split_at_its_rests() -> None:
    """An outside audit (twentieth session): five slides of 1 s at 20 mV RMS, the stream beginning in the first, 1 s rests
    at 0.2 mV each with a 4 ms tap at 50 mV in its middle. Judged hop by hop, each tap restarted the 0.7 s quiet that ends a
    slide the stream began in, and the whole 10 s came out as one slide; a click in a rest also kept it from splitting
    there. The median of three hops, as at rest and in a slide: five slides, each within 30 ms."""
    parts: list[tuple[float, float]] = []
    for _ in range(5):
        parts += [(1.0, 0.02), (0.5, 2e-4), (0.004, 0.05), (0.496, 2e-4)]
    found = _slides(_stream(parts))
    assert len(found) == 5, found
    for k, (a, b) in enumerate(found):
        assert abs(a - 2.0 * k) <= 0.03 and abs(b - (2.0 * k + 1.0)) <= 0.03, found


def test_a_stream_begun_at_rest_a_slide_within_its_first_tenths_starts_the_slide_where_it_begins() -> None:
    """0.2 s of rest, then a slide: the stream's initial level (0.4 s) is the slide's, so without a start level the detector
    waits for the quiet after it and then reports the slides the stream began in; the rest it began with (shorter than
    ``off_hold_s``) was taken into the first, reported from the first sample. It begins at 0.2 s."""
    found = _slides(_stream([(0.2, 2e-4), (1.2, 0.02), (1.0, 2e-4), (1.0, 0.02), (1.0, 2e-4)]))
    assert len(found) == 2 and abs(found[0][0] - 0.2) <= 0.03 and abs(found[1][0] - 2.4) <= 0.03, found


def test_a_knock_at_rest_shortly_before_a_slide_does_not_start_it() -> None:
    """A knock 0.25 s before a slide (an outside audit, twentieth session): an 800 Hz ring of 0.5 V decaying in 5 ms, loud
    for about 50 ms with its comb echo, then quiet for less than ``off_hold_s``, so the slide took the knock for its start,
    0.25 s early. A start loud for less than KNOCK_S (0.1 s) and quiet at least as long after it is a knock: the slide
    begins where it does."""
    x = _stream([(1.0, 2e-4), (1.0, 0.02), (1.0, 2e-4), (1.0, 0.02), (1.0, 2e-4)])  # the floor known from the first slide on
    t = np.arange(round(0.05 * FS)) / FS
    x[round(2.75 * FS):round(2.8 * FS)] += (0.5 * np.sin(2 * np.pi * 800 * t) * np.exp(-t / 0.005))[:, None]
    found = _slides(x)
    assert len(found) == 2 and abs(found[1][0] - 3.0) <= 0.03 and abs(found[1][1] - 4.0) <= 0.03, found
