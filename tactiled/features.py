"""DWT features of analysis windows: pure functions, float64, finite on any input.

A feature is named ``film<c>.<domain>.<band>.<stat>``, e.g. ``film1.time.D3.energy``:
``c`` counts channels from 1; ``domain`` is ``time`` (the window's samples, V) or ``freq``
(the magnitude of its real FFT, V); ``band`` is a DWT approximation ``A1``… or detail
``D1``… (coif5, 4 levels by default; A_j and D_j come from iterating ``pywt.dwt`` on
A_{j-1}); ``stat`` is one of mean, sd (ddof 1), energy (Σc²), rms, skew, kurt (Pearson's,
3 for a Gaussian). A constant band has sd 0, skew 0 and kurt 0.

:class:`FeaturePlan` is derived from the names a model asks for and computes only what they
need: fewer channels, domains, levels or statistics.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import pywt

from tactiled.config import STAT_NAMES
from tactiled.errors import WindowError

DOMAINS = ("time", "freq")


def feature_names(channels: int, level: int = 4, domains: Sequence[str] = DOMAINS, stats: Sequence[str] = STAT_NAMES) -> list[str]:
    """All names for ``channels`` films, in the canonical order (film, domain, band, stat)."""
    bands = [f"A{j}" for j in range(1, level + 1)] + [f"D{j}" for j in range(1, level + 1)]
    return [f"film{c + 1}.{d}.{b}.{s}" for c in range(channels) for d in domains for b in bands for s in stats]


def band_stats(c: npt.NDArray[np.float64], stats: Iterable[str]) -> dict[str, float]:
    """The asked statistics of one coefficient array (float64, non-empty)."""
    n = c.shape[0]
    mean = float(c.mean())
    d = c - mean
    m2 = float(np.dot(d, d)) / n
    out: dict[str, float] = {}
    scale = max(abs(mean), float(np.max(np.abs(c))), 1e-300)
    flat = m2 <= (1e-12 * scale) ** 2
    for s in stats:
        if s == "mean":
            out[s] = mean
        elif s == "sd":
            out[s] = 0.0 if flat or n < 2 else math.sqrt(m2 * n / (n - 1))
        elif s == "energy":
            out[s] = float(np.dot(c, c))
        elif s == "rms":
            out[s] = math.sqrt(float(np.dot(c, c)) / n)
        elif s == "skew":
            out[s] = 0.0 if flat else float(np.mean(d * d * d)) / m2 ** 1.5
        elif s == "kurt":
            out[s] = 0.0 if flat else float(np.mean((d * d) ** 2)) / (m2 * m2)
        else:
            raise ValueError(f"unknown statistic {s!r}")
    return out


FAMILIES = ("dwt",)


def name_family(name: str) -> str:
    """The family of a feature name (interim: the DWT family only)."""
    return "dwt"


def family_names(family: str, channels: int, fs: float, settings: object = None) -> list[str]:
    """Every feature name of ``family`` (interim: the DWT family only)."""
    return feature_names(channels) if family == "dwt" else []


SCALE_STATS = ("sd", "energy", "rms")  # positive, spanning decades: classifiers see their log


def log_mask(names: Sequence[str]) -> npt.NDArray[np.bool_]:
    """True for the features whose logarithm the classifiers see (scale statistics)."""
    return np.array([n.rsplit(".", 1)[-1] in SCALE_STATS for n in names], dtype=bool)


def classifier_inputs(x: npt.NDArray[np.float64], names: Sequence[str]) -> npt.NDArray[np.float64]:
    """Features (n, F) as classifiers see them: log10 of scale statistics (floored at 1e-30), others as they are."""
    out = np.array(x, dtype=np.float64, copy=True)
    mask = log_mask(names)
    out[:, mask] = np.log10(np.maximum(out[:, mask], 1e-30))
    return out


@dataclass(frozen=True)
class ParsedName:
    channel: int  # 0-based
    domain: str
    kind: str  # "A" or "D"
    level: int
    stat: str


def parse_name(name: str) -> ParsedName:
    """Parse ``film<c>.<domain>.<band>.<stat>``; ValueError naming the part that is wrong."""
    parts = name.split(".")
    if len(parts) != 4 or not parts[0].startswith("film") or not parts[0][4:].isdigit():
        raise ValueError(f"feature {name!r}: expected film<c>.<domain>.<band>.<stat>")
    channel = int(parts[0][4:]) - 1
    domain, band, stat = parts[1:]
    if channel < 0 or domain not in DOMAINS or len(band) < 2 or band[0] not in "AD" or not band[1:].isdigit() or int(band[1:]) < 1 \
            or stat not in STAT_NAMES:
        raise ValueError(f"feature {name!r}: unknown film, domain, band or statistic")
    return ParsedName(channel, domain, band[0], int(band[1:]), stat)


class FeaturePlan:
    """What to compute for a list of feature names; :meth:`compute` returns them in that order."""

    def __init__(self, names: Sequence[str], wavelet: str = "coif5", mode: str = "symmetric", fs: float = 20_000.0) -> None:
        self.fs = fs
        self.names = list(names)
        self.wavelet = pywt.Wavelet(wavelet)
        self.mode = mode
        parsed = [parse_name(n) for n in self.names]
        # (channel, domain) -> max level needed; (channel, domain, band) -> stats
        self._levels: dict[tuple[int, str], int] = {}
        self._stats: dict[tuple[int, str, str], list[str]] = {}
        for p in parsed:
            key = (p.channel, p.domain)
            self._levels[key] = max(self._levels.get(key, 0), p.level)
            self._stats.setdefault((p.channel, p.domain, f"{p.kind}{p.level}"), [])
            if p.stat not in self._stats[(p.channel, p.domain, f"{p.kind}{p.level}")]:
                self._stats[(p.channel, p.domain, f"{p.kind}{p.level}")].append(p.stat)
        self.channels_needed = 1 + max((p.channel for p in parsed), default=-1)

    def min_samples(self) -> int:
        """The shortest window every band of the plan can be computed on without boundary-only coefficients."""
        need = 0
        for (_, domain), level in self._levels.items():
            n = (self.wavelet.dec_len - 1) * 2 ** level
            need = max(need, n if domain == "time" else 2 * (n - 1))
        return need

    def compute(self, x: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """Feature vector (len(names),) of window ``x`` (n, C) in volts, float64.

        Raises :class:`WindowError` (reason ``window_too_short``) when n < :meth:`min_samples`,
        and ValueError if x has fewer channels than the names need.
        """
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] < self.channels_needed:
            raise ValueError(f"window must have shape (n, >= {self.channels_needed}), got {x.shape}")
        if x.shape[0] < self.min_samples():
            raise WindowError("window_too_short", f"window of {x.shape[0]} samples is shorter than the {self.min_samples()} the features need")
        values: dict[str, float] = {}
        for (channel, domain), level in self._levels.items():
            sig = x[:, channel]
            if domain == "freq":
                sig = np.abs(np.fft.rfft(sig))
            approx = sig
            for j in range(1, level + 1):
                approx, detail = pywt.dwt(approx, self.wavelet, mode=self.mode)
                for kind, coeffs in (("A", approx), ("D", detail)):
                    stats = self._stats.get((channel, domain, f"{kind}{j}"))
                    if stats:
                        for stat, value in band_stats(coeffs, stats).items():
                            values[f"film{channel + 1}.{domain}.{kind}{j}.{stat}"] = value
        out = np.array([values[n] for n in self.names], dtype=np.float64)
        # energies of a saturated window reach ~1e9; anything non-finite would be a bug upstream
        if not np.all(np.isfinite(out)):
            raise WindowError("non_finite", "features are not finite")
        return out
