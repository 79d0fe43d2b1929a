"""The detector's start level, learnt from training recordings: where a stream's initial level stops being rest and is a slide's.

A detector that starts in the middle of a stream does not know whether the finger is at rest or already sliding, and
without a reference it can tell only from a change: a sustained rise (it was at rest) or a long drop (it was in a slide,
which has ended). Until then it reports nothing: a daemon started while a finger slides without a pause publishes no
label, and a quiet surface slid first is taken for rest when a louder one follows (docs/detection.md, *The states*). The
training recordings show both levels of this sensor: the envelope of its rests between slides, and that of its slides.
Where the two lie far apart, the level between them tells a stream's start after ``detector.initial_s``
(:attr:`tactiled.core.detect.SlideDetector.start_level`). Where they do not (no rests in the recordings, as with a finger
that slides from the first sample to the last, or rests as loud as the quietest slides), there is no start level and the
detector decides by the stream's changes, as before.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from tactiled.config import DetectorConfig
from tactiled.core.detect import front_end, median3_runs, stream_envelope
from tactiled.files.recording import Recording

EDGE_S = 0.1  # a slide's hops this close to its start or stop are left out of its level (the rise and the lift-off), s
REST_GAP_S = 0.3  # a rest's hops at least this far from every slide, s
SLIDE_QUANTILE = 0.05  # the quiet end of the slides' levels ...
REST_QUANTILE = 0.99  # ... and the loud end of the rests' hops
MIN_SLIDES = 3  # fewer slides with a level of their own, or ...
MIN_REST_S = 1.0  # ... less rest than this in all: no start level


def hop_envelope(rec: Recording, config: DetectorConfig) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.bool_], int]:
    """(envelope (h,) of the recording's whole hops, as the detector computes it from the stream's first sample; whether each
    hop's samples were all intact (h,); the hop in samples)."""
    fe = front_end(config, rec.fs)
    volts = rec.volts()  # as the detector is fed (tactiled.learn.dataset.detector_events): lost rows are 0 V
    valid = rec.valid_mask()
    volts[~valid] = 0.0
    hops = volts.shape[0] // fe.hop
    env = stream_envelope(np.zeros((fe.history, volts.shape[1])), volts, hops, fe)  # the detector's zeros before the stream
    intact: npt.NDArray[np.bool_] = np.asarray(valid[: hops * fe.hop].reshape(hops, fe.hop).all(axis=1), dtype=bool)
    return np.asarray(env, dtype=np.float64), intact, fe.hop


def start_level(recs: Sequence[Recording], slides: Sequence[Sequence[tuple[int, int]]], config: DetectorConfig) -> float | None:
    """The envelope level that tells a slide's start from rest on this sensor, or None where the recordings cannot say
    (:func:`learn_start_level` without its note)."""
    return learn_start_level(recs, slides, config)[0]


def learn_start_level(recs: Sequence[Recording], slides: Sequence[Sequence[tuple[int, int]]], config: DetectorConfig,
                      surfaces: Sequence[Sequence[str | None]] | None = None) -> tuple[float | None, str]:
    """(the envelope level that tells a slide's start from rest on this sensor, or None where the recordings cannot say;
    one line saying which, and why, for ``train`` to print).

    ``recs``: the training recordings; ``slides``: each one's slides, [start, stop) positions. A slide's level is the 80th
    percentile of its hops' envelope away from its edges (as the detector's reference over ``initial_s``); the rests' is
    the 99th percentile of every intact hop at least :data:`REST_GAP_S` from every slide (and past the front end's
    settling at the start), each the median of it and the two hops before (as the detector decides at rest: a knock of a
    hop or two between slides counts no more than it does there). With the quietest 5 % of slides' levels at least ``on_factor``² above the rests', the level is
    their geometric mean (a margin of ``on_factor`` each way: another unit's gain moves both by far less); else None.
    ``surfaces``: each slide's surface (as ``slides``), to name the surfaces whose slides are no louder than the rests then
    (recordings of rest labelled as a surface are the usual cause).
    """
    slide_levels: list[float] = []
    slide_surfaces: list[str | None] = []
    rest: list[npt.NDArray[np.float64]] = []
    rest_hops = 0
    for k, (rec, spans) in enumerate(zip(recs, slides, strict=True)):
        env, intact, hop = hop_envelope(rec, config)
        starts = np.arange(env.shape[0]) * hop
        edge, gap, settle = round(EDGE_S * rec.fs), round(REST_GAP_S * rec.fs), round((config.settle_s + config.initial_s) * rec.fs)
        near = np.zeros(env.shape[0], dtype=bool)
        for j, (a, b) in enumerate(spans):
            inside = intact & (starts >= a + edge) & (starts + hop <= b - edge)
            if inside.sum() * hop >= config.initial_s * rec.fs:
                slide_levels.append(float(np.quantile(env[inside], 0.8)))
                slide_surfaces.append(surfaces[k][j] if surfaces is not None else None)
            near |= (starts + hop > a - gap) & (starts < b + gap)
        quiet = intact & ~near & (starts >= settle) & (env > 0)
        rest.append(np.asarray(median3_runs(env.tolist()), dtype=np.float64)[quiet])
        rest_hops += int(quiet.sum())
    rest_s = rest_hops * (front_end(config, recs[0].fs).hop / recs[0].fs if recs else 0.0)
    unknown = "a daemon started while the finger slides labels that slide once it ends (docs/detection.md, The states)"
    if len(slide_levels) < MIN_SLIDES or rest_s < MIN_REST_S:
        return None, (f"no start level: the recordings hold {rest_s:.1f} s of rest {REST_GAP_S:g} s or more from any slide and "
                      f"{len(slide_levels)} slides with a level of their own ({MIN_REST_S:g} s and {MIN_SLIDES} needed); {unknown}")
    loud_rest = float(np.quantile(np.concatenate(rest), REST_QUANTILE))
    quiet_slide = float(np.quantile(slide_levels, SLIDE_QUANTILE))
    if not (loud_rest > 0 and quiet_slide >= loud_rest * config.on_factor**2):
        still = sorted({str(n) for n, v in zip(slide_surfaces, slide_levels, strict=True) if n is not None and v <= loud_rest})
        hint = (f"; the slides of {', '.join(still)} are no louder than the rests (recordings of rest labelled as a surface? the "
                "daemon would find no slide in them)") if still else ""
        return None, (f"no start level: the quietest slides lie only {quiet_slide / loud_rest if loud_rest > 0 else math.inf:.1f} times "
                      f"above the loudest rest ({config.on_factor**2:g} needed){hint}; {unknown}")
    level = math.sqrt(loud_rest * quiet_slide)
    return level, (f"start level {level:.3g} (the quietest slides {quiet_slide / loud_rest:.0f} times above the loudest rest): a daemon "
                   "started while the finger slides labels that slide as it goes")
