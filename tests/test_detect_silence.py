"""Rests of exact digital zeros between slides (a gated board, a recording edited to zero its rests): each slide is found,
as with rests of noise, and the first begins where the zeros end. Exact silence said nothing to a detector that had not
yet told the stream's level from rest, so the quiet after the first slide never came: one slide over the whole file,
confidently mislabelled (an audit)."""

from __future__ import annotations

import numpy as np

from tactiled.config import Config
from tactiled.core.matching import match_slides
from tactiled.files.recording import Recording
from tactiled.learn.dataset import detect_slides
from tactiled.sim.physics import SimParams, pick_surfaces, simulate_file


def test_rests_of_exact_zeros_keep_every_slide() -> None:
    params = SimParams()
    sim = simulate_file(params, pick_surfaces("Ra1.00")[0], 3, 4)
    truth = [(t.start, t.stop) for t in sim.truth]
    zeroed = np.zeros_like(sim.samples)
    for a, b in truth:
        zeroed[a:b] = sim.samples[a:b]
    for samples in (sim.samples, zeroed):
        found = detect_slides(Recording(samples, params.fs, params.volts_per_count), Config())
        assert len(found) == 3 and all(i is not None for i in match_slides(found, truth)), (found, truth)
        assert abs(found[0][0] - truth[0][0]) < 0.2 * params.fs  # not from the first sample of the file


def test_a_stream_of_exact_zeros_has_no_slide() -> None:
    assert detect_slides(Recording(np.zeros((40_000, 2), dtype=np.int16), 20_000.0, 1.0), Config()) == []
