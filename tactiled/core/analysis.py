"""One analysis of one window, shared by the live pipeline, replay, training and evaluation.

window samples → volts (float64) → quality (lost, saturated) → spike removal → features.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from tactiled.config import Config
from tactiled.core.features import HUGE_EXPONENT, FeaturePlan, family_names, feature_names
from tactiled.core.spikes import median_last, remove_spikes_many, row_counts
from tactiled.errors import WindowError


@dataclass(frozen=True)
class AnalysisSettings:
    """How windows are placed in a slide and turned into features (stored in model files).

    A slide [start, stop) is analysed as successive windows of ``duration_s``, the first
    ``start_s`` after the slide's start, one every ``hop_s`` (``hop_s`` 0: = duration_s),
    at most ``max_windows`` of them (0: as many as the slide holds). ``fusion`` says how they
    make the slide's label (:meth:`tactiled.learn.model.Model.slide_proba`): ``scores`` averages the
    windows' class scores, ``features`` classifies the average of their features (a
    whole-slide spectrum, for the psd family). A slide too short
    for one such window is analysed on its last ``duration_s`` (or all of it). ``centred``: the DWT
    features read each window less its mean per channel (:class:`~tactiled.core.features.FeaturePlan`); every
    model ``train`` writes since 2026-11-27 is, and a model file without the field (written before) is read as not.
    """

    start_s: float = 0.0
    duration_s: float = 0.5
    hop_s: float = 0.0
    max_windows: int = 0
    spikes: str = "mad"
    half_width: int = 5
    nsigma: float = 4.0
    wavelet: str = "coif5"
    level: int = 4
    mode: str = "symmetric"
    names: tuple[str, ...] = field(default_factory=tuple)
    fusion: str = "scores"  # scores: average the windows' class scores; features: classify the average of their features
    centred: bool = False  # the DWT of each window less its mean per channel (window_settings: True)

    @classmethod
    def from_config(cls, config: Config, channels: int, fs: float = 20_000.0) -> AnalysisSettings:
        """The config's windows and feature families (the DWT with fewer levels, or left out, when the windows are too short for it)."""
        w, fams = config.window, list(config.features.families)
        st = window_settings(config, channels, fs, w.duration_s, fams, w.start_s, w.max_windows, w.hop_s)
        if st is None and "dwt" in fams and len(fams) > 1:
            st = window_settings(config, channels, fs, w.duration_s, [f for f in fams if f != "dwt"], w.start_s, w.max_windows, w.hop_s)
        if st is None:
            raise WindowError("window_too_short", f"window.duration_s = {w.duration_s:g} s at {fs:g} Hz is too short for features.families = "
                              f"{', '.join(fams)} (the DWT needs longer windows; psd and tex need 0.45 fs above features.psd_low_hz = "
                              f"{config.features.psd_low_hz:g} Hz)")
        return st

    def to_dict(self) -> dict[str, Any]:
        """The settings as a JSON-ready dict (``names`` a list), as stored in model files."""
        d = asdict(self)
        d["names"] = list(self.names)
        return d

    @classmethod
    def from_dict(cls, d: Any) -> AnalysisSettings:
        """Settings from a dict of :meth:`to_dict` (a model file's ``settings``).

        Every key a model file has always had (every format tactiled reads, 2 on) must be there: a default in its place would
        analyse with windows the model was not trained on, silently (a file without ``duration_s`` was read with 0.5 s
        windows where its model had 0.25 s ones, and labelled every Ra0.44 slide of an audit Ra0.85). ``fusion`` (since 2026-11-23)
        and ``centred`` (2026-11-27), which older files lack, keep their defaults (scores; not centred). Raises
        :class:`ValueError` naming the key (``settings.duration_s: missing``) for a missing or unknown key, ``d`` not an
        object or ``names`` not a list."""
        if not isinstance(d, dict):
            raise ValueError("settings: must be an object")
        required = ("start_s", "duration_s", "hop_s", "max_windows", "spikes", "half_width", "nsigma", "wavelet", "level", "mode", "names")
        missing = [k for k in required if k not in d]
        if missing:
            raise ValueError(f"settings.{missing[0]}: missing (every model file has it; the file is damaged or not tactiled's)"
                             if len(missing) == 1 else f"settings: {', '.join(missing)} missing (every model file has them)")
        unknown = sorted(set(d) - set(cls.__dataclass_fields__))
        if unknown:
            raise ValueError(f"settings.{unknown[0]}: not a setting this tactiled knows (a model file of a later version?)")
        if not isinstance(d["names"], list):
            raise ValueError("settings.names: must be a list of feature names")
        return cls(**{**d, "names": tuple(d["names"])})

    def hop(self) -> float:
        """Seconds between successive windows."""
        return self.hop_s if self.hop_s > 0 else self.duration_s

    def spans(self, start: int, stop: int, fs: float, min_samples: int = 1) -> list[tuple[int, int]]:
        """The windows [lo, hi) of a slide [start, stop) (sample positions), in time order.

        Windows that fit entirely in the slide, from ``start + start_s`` every ``hop_s``; if
        none fits, the slide's last ``duration_s`` (or the whole slide), when it holds at
        least ``min_samples``; else none.
        """
        n = max(1, round(self.duration_s * fs))
        hop = max(1, round(self.hop() * fs))
        lo = start + round(self.start_s * fs)
        out: list[tuple[int, int]] = []
        while lo + n <= stop and (self.max_windows <= 0 or len(out) < self.max_windows):
            out.append((lo, lo + n))
            lo += hop
        if not out and stop - start >= min_samples:
            out.append((max(start, stop - n), stop))
        return out

    def first_span(self, start: int, fs: float) -> tuple[int, int]:
        """The first full window of a slide starting at ``start``."""
        lo = start + round(self.start_s * fs)
        return lo, lo + max(1, round(self.duration_s * fs))



ANALYSIS_SECTIONS = ("window", "spikes", "features")


def sections_a_model_overrides(config: Config) -> list[str]:
    """The config's analysis sections (``[window]``, ``[spikes]``, ``[features]``) set away from their defaults.

    A loaded model analyses with the settings it was trained with, so these apply only without a model.
    """
    default = Config()
    return [name for name in ANALYSIS_SECTIONS if getattr(config, name) != getattr(default, name)]


def dwt_level(channels: int, fs: float, duration_s: float, config: Config) -> int:
    """The most DWT levels (at most ``features.level``) whose bands fit in a window of ``duration_s``; 0 if none."""
    n = round(duration_s * fs)
    f = config.features
    for level in range(f.level, 0, -1):
        if FeaturePlan(feature_names(channels, level, f.domains, f.stats), f.wavelet, f.mode, fs=fs).min_samples() <= n:
            return level
    return 0


def window_settings(config: Config, channels: int, fs: float, duration_s: float, families: Sequence[str], start_s: float = 0.0,
                    max_windows: int = 0, hop_s: float = 0.0) -> AnalysisSettings | None:
    """Settings computing every name of ``families`` on windows of ``duration_s``; None if a family cannot fit such a window."""
    names: list[str] = []
    level = config.features.level
    for fam in families:
        if fam == "dwt":
            level = dwt_level(channels, fs, duration_s, config)
            if level == 0:
                return None
            names += feature_names(channels, level, config.features.domains, config.features.stats)
        else:
            try:
                names += family_names(fam, channels, fs, config.features)
            except ValueError:  # no band fits below 0.45 fs at this rate
                return None
    s = config.spikes
    st = AnalysisSettings(start_s, duration_s, hop_s, max_windows, s.method, s.half_width, s.nsigma, config.features.wavelet, level,
                          config.features.mode, tuple(names), centred=True)
    plan = FeaturePlan(st.names, st.wavelet, st.mode, fs=fs)
    return st if plan.min_samples() <= round(duration_s * fs) else None


@dataclass
class WindowResult:
    """One window's analysis: ``features`` (F,) float64 in the settings' ``names`` order, or None and a ``reason``.

    ``quality``: samples, lost (rows), saturated (fraction of rows clipped), spikes (removed).
    """

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


def clipped_fraction(samples: npt.NDArray[Any]) -> float:
    """Fraction of rows of ``samples`` (n, C) where some channel sits at a rail.

    A rail is the int16 limit, or a channel's own extreme value held for 3 or more
    consecutive samples (an ADC or amplifier that clips at another level, int or float);
    for integer samples such an extreme must be at least 1024 counts from zero, so the
    quantisation steps of a quiet signal are not mistaken for clipping.
    """
    return float(clipped_fractions(np.asarray(samples)[None])[0])


def clipped_fractions(samples: npt.NDArray[Any]) -> npt.NDArray[np.float64]:
    """:func:`clipped_fraction` of each of W windows ``samples`` (W, n, C), int or float: (W,)."""
    x = np.asarray(samples)
    # (W, C, n): per channel, contiguous (numpy reduces strided columns ~15x slower)
    return clipped_row_fractions(np.ascontiguousarray(x.transpose(0, 2, 1)))


def clipped_row_fractions(rows: npt.NDArray[Any]) -> npt.NDArray[np.float64]:
    """:func:`clipped_fraction` of each of W windows given as rows ``rows`` (W, C, n), each channel's samples: (W,)."""
    w, _, n = rows.shape
    if n < 3:
        return np.zeros(w)
    integer = np.issubdtype(rows.dtype, np.integer)
    high, low = rows.max(axis=2), rows.min(axis=2)  # (W, C)
    hits = np.zeros((w, n), dtype=bool)
    if rows.dtype == np.int16 and bool(((high >= 32767) | (low <= -32768)).any()):
        hits |= ((rows >= 32767) | (rows <= -32768)).any(axis=1)
    for rail in (high, low):
        # held for three samples in a row (a single extreme sample, the usual case, is not a rail)
        candidate = high != low
        if integer:
            candidate &= np.abs(rail.astype(np.int64)) >= 1024
        if not candidate.any():
            continue
        at = rows == rail[..., None]
        candidate &= row_counts(at) >= 3
        for i, c in zip(*np.nonzero(candidate), strict=True):
            row = at[i, c]
            if bool(np.any(row[:-2] & row[1:-1] & row[2:])):
                hits[i] |= row
    out: npt.NDArray[np.float64] = row_counts(hits) / n
    return out


def volts_bound(dtype: np.dtype[Any], volts_per_count: float) -> float:
    """The largest |volts| that samples of the integer ``dtype`` can give at ``volts_per_count`` (inf for any other dtype)."""
    if not np.issubdtype(dtype, np.integer):
        return math.inf
    info = np.iinfo(dtype)
    return max(-float(info.min), float(info.max)) * abs(volts_per_count)


class Analyser:
    """Turns one window of samples into a feature vector, or a reason it cannot (:meth:`analyse`); offline, many windows at
    once (:meth:`analyse_many`)."""

    def __init__(self, settings: AnalysisSettings, fs: float, volts_per_count: float, integer: bool, max_saturated: float = 1.0,
                 max_lost: float = 0.02) -> None:
        self.settings = settings
        self.fs = fs
        self.plan = FeaturePlan(settings.names, settings.wavelet, settings.mode, fs=fs, centred=settings.centred)
        self.volts_per_count = volts_per_count
        self.integer = integer
        self.max_saturated = max_saturated
        self.max_lost = max_lost

    def analyse(self, samples: npt.NDArray[Any], valid: npt.NDArray[np.bool_] | None = None) -> WindowResult:
        """``samples`` (n, C): int16 counts (or float volts when not ``integer``); ``valid`` (n,)."""
        return self.analyse_many(np.asarray(samples)[None], None if valid is None else np.asarray(valid)[None])[0]

    def analyse_many(self, samples: npt.NDArray[Any], valid: npt.NDArray[np.bool_] | None = None) -> list[WindowResult]:
        """W windows of the same length at once: ``samples`` (W, n, C) int16 counts (or float volts when not ``integer``),
        ``valid`` (W, n); each result the same as :meth:`analyse` of the window alone (the transforms run once for all)."""
        w, n = samples.shape[:2]
        lost = np.zeros(w, dtype=np.int64) if valid is None else n - row_counts(np.ascontiguousarray(valid))
        # volts in one pass, each channel's samples contiguous (W, C, n) as spike removal and the transforms read them (this
        # call's own scratch); counts too, as the clipping check and the medians read them
        rows = np.empty((w, samples.shape[2], n))
        counts = None
        if self.integer:
            counts = np.ascontiguousarray(samples.transpose(0, 2, 1))
            saturated = clipped_row_fractions(counts)
            np.multiply(counts, self.volts_per_count, out=rows)
        else:
            saturated = clipped_fractions(samples)
            rows[...] = samples.transpose(0, 2, 1)
        volts = rows.transpose(0, 2, 1)
        results: list[WindowResult | None] = [None] * w
        todo: list[int] = []
        too_short = n < self.plan.min_samples()
        for i, (lost_i, saturated_i) in enumerate(zip(cast(list[int], lost.tolist()), cast(list[float], saturated.tolist()), strict=True)):
            quality: dict[str, Any] = {"samples": n, "lost": lost_i, "saturated": round(saturated_i, 6), "spikes": 0}
            reason = None
            if lost_i > self.max_lost * n:
                reason = "samples_lost"
            elif too_short:
                reason = "window_too_short"
            elif saturated_i > self.max_saturated:
                reason = "saturated"
            results[i] = WindowResult(None, reason, quality)
            if reason is None:
                todo.append(i)
                if lost_i:
                    assert valid is not None
                    volts[i] = fill_lost(volts[i], valid[i])
        if todo:
            s = self.settings
            medians = self._medians(counts, rows, todo, lost) if s.spikes == "mad" and counts is not None else None
            clean, spikes = remove_spikes_many(volts[todo] if len(todo) < w else volts, s.spikes, s.half_width, s.nsigma, overwrite=True,
                                               medians=medians)
            # counts in volts: no |x| beyond 2**HUGE_EXPONENT, and none but 0 below 2**-HUGE_EXPONENT (one count is that far up)
            bounded = (self.integer and volts_bound(samples.dtype, self.volts_per_count) <= 2.0 ** HUGE_EXPONENT
                       and self.volts_per_count >= 2.0 ** -HUGE_EXPONENT)
            features = self.plan.compute_many(clean, bounded=bounded)
            finite = cast(list[bool], np.isfinite(features).all(axis=1).tolist())
            for j, (i, removed) in enumerate(zip(todo, cast(list[int], spikes.tolist()), strict=True)):
                r = results[i]
                assert r is not None
                r.quality["spikes"] = removed
                if finite[j]:
                    r.features, r.reason = features[j], None
                else:  # energies of samples near 1e307: beyond float64
                    r.reason = "non_finite"
        return [r for r in results if r is not None]

    def _medians(self, counts: npt.NDArray[Any], rows: npt.NDArray[np.float64], todo: list[int],
                 lost: npt.NDArray[np.int64]) -> npt.NDArray[np.float64] | None:
        """(len(todo), C) the medians of the volts ``rows`` (W, C, n) of the windows ``todo``, chosen among their integer
        ``counts`` (W, C, n) (cheaper; the same values, see :func:`median_last`), those of windows with lost samples (filled
        in volts) from their volts; None (spike removal takes them) unless the counts are integers at a positive scale."""
        vpc = self.volts_per_count
        if not (np.issubdtype(counts.dtype, np.integer) and 0.0 < vpc < math.inf):
            return None
        medians = median_last(counts[todo] if len(todo) < counts.shape[0] else counts, scale=vpc)
        for j, i in enumerate(todo):
            if lost[i]:
                medians[j] = median_last(rows[i])
        return medians
