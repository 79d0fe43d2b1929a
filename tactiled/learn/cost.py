"""What a model's analysis costs on this machine, and refusing a model that cannot keep up with the stream.

While a slide goes on the pipeline analyses every window of it (features, then the classifier for a provisional
label), so a model's cost per second of signal is its cost per window times windows per second (fs / hop). A
model file can pass every load check and still ask for windows so short, or features so many, that the daemon
falls behind the sensor: it is measured at load, on seeded noise, and refused below :data:`MIN_SPEED` times real
time unless forced.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from tactiled.core.analysis import Analyser
from tactiled.errors import ModelError
from tactiled.learn.model import Model

MIN_SPEED = 5.0  # times real time the analysis must reach on this machine
BUDGET_S = 0.05  # at most this long measuring a model that looks too slow (at least 3 windows): short, as it runs beside a live stream on a reload


def analysis_speed(model: Model) -> tuple[float, float]:
    """(times real time, seconds per window) of ``model``'s analysis and classifier on this machine, while sliding.

    One window of seeded noise at the model's rate and channels is analysed and classified (as for a provisional
    label) 3 times, and again for up to :data:`BUDGET_S` while the fastest run so far is below :data:`MIN_SPEED`;
    the fastest run counts, so that a busy machine does not refuse a model that fits, and a model that fits costs
    only its 3 windows (every command that loads a model pays for this check).
    """
    s = model.settings
    n = max(1, round(s.duration_s * model.fs))
    hop = max(1, round(s.hop() * model.fs))
    noise = np.round(np.random.default_rng(0).standard_normal((n, model.channels)) * 300).astype(np.int16)
    analyser = Analyser(s, model.fs, 1e-4, integer=True)
    best = float("inf")
    start = time.perf_counter()
    runs = 0
    hop_s = hop / model.fs  # seconds of signal per window analysed
    while runs < 3 or (best * MIN_SPEED > hop_s and time.perf_counter() - start < BUDGET_S and runs < 50):
        t0 = time.perf_counter()
        window = analyser.analyse(noise)
        if window.features is not None:
            model.assess(window.features[None, :])
        best = min(best, time.perf_counter() - t0)
        runs += 1
    per_second = best / hop_s  # seconds of work per second of signal
    return (1.0 / per_second if per_second > 0 else float("inf")), best


def check_speed(model: Model, where: str | Path, force: bool = False) -> float:
    """The model's speed (times real time, :func:`analysis_speed`); :class:`ModelError` naming ``where`` below
    :data:`MIN_SPEED` unless ``force``."""
    speed, per_window = analysis_speed(model)
    if speed < MIN_SPEED and not force:
        hop_ms = model.settings.hop() * 1e3
        raise ModelError(f"{where}: analysis runs at {speed:.1f}x real time on this machine ({per_window * 1e3:.2f} ms per window every "
                         f"{hop_ms:.3g} ms); at least {MIN_SPEED:g}x is needed to keep up with the sensor (--force runs it anyway)")
    return speed
