"""One analysis of one window, shared by the live pipeline, replay, training and evaluation.

window samples → volts (float64) → quality (lost, saturated) → spike removal → features.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from tactiled.config import Config
from tactiled.errors import WindowError
from tactiled.features import FeaturePlan, feature_names
from tactiled.spikes import remove_spikes


@dataclass(frozen=True)
class AnalysisSettings:
    """How a window is placed and turned into features (stored in model files)."""

    start_s: float = 0.3
    duration_s: float = 0.5
    onset_lag_s: float = 0.0  # detector onset lag behind the true start of motion (measured in training)
    spikes: str = "mad"
    half_width: int = 5
    nsigma: float = 4.0
    wavelet: str = "coif5"
    level: int = 4
    mode: str = "symmetric"
    names: tuple[str, ...] = field(default_factory=tuple)

    @classmethod
    def from_config(cls, config: Config, channels: int) -> AnalysisSettings:
        f = config.features
        return cls(config.window.start_s, config.window.duration_s, 0.0, config.spikes.method, config.spikes.half_width,
                   config.spikes.nsigma, f.wavelet, f.level, f.mode, tuple(feature_names(channels, f.level, f.domains, f.stats)))

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["names"] = list(self.names)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> AnalysisSettings:
        return cls(**{**d, "names": tuple(d["names"])})

    def window(self, onset: int, stop: int, fs: float, from_truth: bool = False) -> tuple[int, int]:
        """[start, stop) of the analysis window of a slide with ``onset`` and end ``stop`` (sample positions).

        ``from_truth``: the onset is the true start of motion, so the detector's lag is added
        to land on the same signal as live use.
        """
        lo = onset + round(((self.onset_lag_s if from_truth else 0.0) + self.start_s) * fs)
        hi = min(lo + round(self.duration_s * fs), stop)
        return lo, max(lo, hi)


@dataclass
class WindowResult:
    features: npt.NDArray[np.float64] | None
    reason: str | None
    quality: dict[str, Any]


def fill_lost(volts: npt.NDArray[np.float64], valid: npt.NDArray[np.bool_]) -> npt.NDArray[np.float64]:
    """``volts`` (n, C) with invalid rows replaced by linear interpolation between valid neighbours."""
    good = np.flatnonzero(valid)
    if good.size == 0:
        return np.zeros_like(volts)
    bad = np.flatnonzero(~valid)
    out = volts.copy()
    for c in range(volts.shape[1]):
        out[bad, c] = np.interp(bad, good, volts[good, c])
    return out


class Analyser:
    """Turns one window of samples into a feature vector, or a reason it cannot."""

    def __init__(self, settings: AnalysisSettings, volts_per_count: float, integer: bool, max_saturated: float = 0.01,
                 max_lost: float = 0.02) -> None:
        self.settings = settings
        self.plan = FeaturePlan(settings.names, settings.wavelet, settings.mode)
        self.volts_per_count = volts_per_count
        self.integer = integer
        self.max_saturated = max_saturated
        self.max_lost = max_lost

    def analyse(self, samples: npt.NDArray[Any], valid: npt.NDArray[np.bool_] | None = None) -> WindowResult:
        """``samples`` (n, C): int16 counts (or float volts when not ``integer``); ``valid`` (n,)."""
        n = samples.shape[0]
        lost = 0 if valid is None else int(n - np.count_nonzero(valid))
        if self.integer:
            saturated = float(np.mean(np.any((samples >= 32767) | (samples <= -32768), axis=1))) if n else 0.0
            volts = samples.astype(np.float64) * self.volts_per_count
        else:
            saturated = 0.0
            volts = np.asarray(samples, dtype=np.float64)
        quality: dict[str, Any] = {"samples": n, "lost": lost, "saturated": round(saturated, 6), "spikes": 0}
        if lost > self.max_lost * n:
            return WindowResult(None, "samples_lost", quality)
        if lost:
            assert valid is not None
            volts = fill_lost(volts, valid)
        if n < self.plan.min_samples():
            return WindowResult(None, "window_too_short", quality)
        if saturated > self.max_saturated:
            return WindowResult(None, "saturated", quality)
        s = self.settings
        clean, spikes = remove_spikes(volts, s.spikes, s.half_width, s.nsigma)
        quality["spikes"] = spikes
        try:
            return WindowResult(self.plan.compute(clean), None, quality)
        except WindowError as exc:
            return WindowResult(None, exc.reason, quality)
