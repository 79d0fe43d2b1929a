"""Features of analysis windows: pure functions, float64, finite on any input, any channel count and rate.

Three families; a feature's name says everything needed to compute it, and
:class:`FeaturePlan` computes only what the names of a model ask for.

``dwt``, the papers' statistics: ``film<c>.<domain>.<band>.<stat>``, e.g.
``film1.time.D3.energy``: ``c`` counts channels from 1; ``domain`` is ``time`` (the
window's samples, V) or ``freq`` (the magnitude of its real FFT, V), of the window less its
mean per channel when the plan is ``centred`` (as models trained since 2026-11-27 are: a
DC-coupled sensor's offset and drift belong to a recording, not to its surface); ``band`` is a DWT
approximation ``A1``… or detail ``D1``… (coif5, 4 levels by default; A_j and D_j come
from iterating ``pywt.dwt`` on A_{j-1}); ``stat`` is one of mean, sd (ddof 1), energy (Σc²),
rms, skew, kurt (Pearson's, 3 for a Gaussian). A constant band has sd 0, skew 0 and kurt 0.

``psd``, log band energies: ``film<c>.psd.<lo>-<hi>Hz.power`` (numbers with ``p`` for the
decimal point, e.g. ``film1.psd.20-25p2Hz.power``): the power (V²) of the window in
[lo, hi) Hz from its Welch PSD (Hann segments of ~50 ms, half overlapping, each segment's
mean removed), integrated with fractional bins so that any band width works at any
resolution. Bands are log-spaced, ``psd_bands_per_octave`` per octave from
``psd_low_hz`` to ``psd_high_frac``·fs (:func:`psd_bands`).

``tex``, texture descriptors: ``film<c>.tex.<name>``: ``centroid``, ``spread`` (Hz: mean
and standard deviation of frequency under the Welch PSD), ``rolloff`` (Hz below which 85 %
of the power lies), ``flatness`` (geometric / arithmetic mean of the PSD, 0..1), ``slope``
(of log10 PSD against log10 f, least squares over the psd band range), ``kurtosis``
(Pearson's, of the samples), ``crest`` (peak |x − mean| / RMS), ``zcr`` (zero crossings of
x − mean per second), ``rms`` (V). A silent window gives 0 for every descriptor.

Every feature is computed without overflow for any finite window: a window with samples beyond 2**100 V is scaled
down by a power of two first (exact) and its features scaled back by their degree (:func:`feature_degree`); one that
is still beyond float64 (the energy of samples near 1e307) is a :class:`WindowError` (``non_finite``), not inf.

Classifiers see log10 of the positive, decade-spanning features (:func:`is_log_feature`:
DWT sd/energy/rms, psd power, tex rms/centroid/spread/rolloff), floored at 1e-30; the
rest as they are (:func:`classifier_inputs`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

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


def film_levels(sums: npt.NDArray[np.float64], sumsq: npt.NDArray[np.float64], n: int, scale: float = 1.0) -> list[float]:
    """Each film's RMS about its mean over n samples, from their sums (C,) and sums of squares (C,), times ``scale`` (V per
    count), rounded to 1e-6: the status's ``level``. About the mean, so a DC-coupled film's offset does not hide its slides
    (the plain RMS of a film at 0.6 V of offset moved from 0.640 to 0.613..0.677 V between rest and slides). [] for n 0."""
    if n <= 0:
        return []
    var = np.maximum(sumsq / n - (sums / n) ** 2, 0.0)  # never below 0 by rounding
    return [round(float(np.sqrt(v)) * scale, 6) for v in var]


def row_dots(a: npt.NDArray[np.float64], b: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """(W,) the dot product of each row of ``a`` and ``b`` (W, m): the same values as ``np.dot`` of each pair of rows (matmul
    of vectors is BLAS ``ddot``, as ``np.dot`` is; ``einsum`` rounds differently)."""
    out: npt.NDArray[np.float64] = np.matmul(a[:, None, :], b[:, :, None])[:, 0, 0]
    return out


def rowwise_matmul(a: npt.NDArray[np.float64], b: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """``a @ b`` (n, p) of ``a`` (n, m) and ``b`` (m, p), each row computed as that row alone: one BLAS matrix-vector product
    per row, as ``a[i:i + 1] @ b`` is (a matrix product of several rows rounds differently), so a row's values do not
    depend on the rows computed with it."""
    if a.shape[0] == 1:
        return np.matmul(a, b)  # type: ignore[no-any-return]
    out: npt.NDArray[np.float64] = np.matmul(a[:, None, :], b)[:, 0, :]
    return out


def band_stats(c: npt.NDArray[np.float64], stats: Sequence[str]) -> dict[str, npt.NDArray[np.float64]]:
    """The asked statistics (each (W,)) of the rows of the coefficient arrays ``c`` (W, m), float64, m >= 1: every row at
    once in numpy, each value the same, row by row, as of each row alone (the same IEEE operations on each row's sums;
    skew and kurt, which divide by a power, on Python floats as ever)."""
    n = c.shape[1]
    means = c.sum(axis=1) / n  # as c.mean(axis=1), without its overhead
    d = c - means[:, None]
    m2 = row_dots(d, d) / n
    scale = np.maximum(np.maximum(np.abs(means), c.max(axis=1)), np.maximum(-c.min(axis=1), 1e-300))  # max |c|
    flat = m2 <= (1e-12 * scale) * (1e-12 * scale)  # a float product overflows to inf; ** would raise OverflowError
    energy = row_dots(c, c) if "energy" in stats or "rms" in stats else m2
    out: dict[str, npt.NDArray[np.float64]] = {}
    for s in stats:
        if s == "mean":
            out[s] = means
        elif s == "sd":
            out[s] = np.zeros_like(m2) if n < 2 else np.where(flat, 0.0, np.sqrt(m2 * n / (n - 1)))
        elif s == "energy":
            out[s] = energy
        elif s == "rms":
            out[s] = np.sqrt(energy / n)
        elif s in ("skew", "kurt"):
            out[s] = _shape_stat(s, d, m2, flat)
        else:
            raise ValueError(f"unknown statistic {s!r}")
    return out


def _shape_stat(stat: str, d: npt.NDArray[np.float64], m2: npt.NDArray[np.float64], flat: npt.NDArray[np.bool_]) -> npt.NDArray[np.float64]:
    """Skew or kurt (W,) of rows with deviations ``d`` (W, m) from their mean, second moments ``m2`` (W,) and ``flat``
    (W,) (a constant row: 0), per row on Python floats (``m2 ** 1.5`` as Python takes it)."""
    n = d.shape[1]
    if stat == "skew":
        cubes = ((d * d * d).sum(axis=1) / n).tolist()  # as np.mean(d * d * d) of each row
        values = [0.0 if f else cube / m ** 1.5 for f, cube, m in zip(flat.tolist(), cubes, m2.tolist(), strict=True)]
    else:
        fourths = (((d * d) ** 2).sum(axis=1) / n).tolist()
        values = [0.0 if f else fourth / (m * m) for f, fourth, m in zip(flat.tolist(), fourths, m2.tolist(), strict=True)]
    return np.array(values, dtype=np.float64)


FAMILIES = ("dwt", "psd", "tex")
TEX_NAMES = ("centroid", "spread", "rolloff", "flatness", "slope", "kurtosis", "crest", "zcr", "rms")
SEGMENT_S = 0.05  # Welch segment length, s (a power of two samples near it)
MIN_PSD_SAMPLES = 64  # the shortest window the psd and tex families analyse


def _num(x: float) -> str:
    return f"{x:.4g}".replace(".", "p")


def _unnum(text: str) -> float:
    return float(text.replace("p", "."))


def psd_bands(fs: float, low_hz: float = 20.0, high_frac: float = 0.45, per_octave: float = 3.0) -> list[tuple[float, float]]:
    """Log-spaced [lo, hi) bands in Hz, ``per_octave`` per octave from ``low_hz`` to ``high_frac``·fs.

    A band narrower than the Welch resolution of a ~50 ms segment is merged into the next,
    so the lowest bands hold at least one frequency bin. Raises ValueError for an empty range.
    """
    high = high_frac * fs
    if not (0 < low_hz < high <= fs / 2):
        raise ValueError(f"psd bands: need 0 < low ({low_hz:g} Hz) < high ({high:g} Hz) <= fs/2")
    n = max(1, round(math.log2(high / low_hz) * per_octave))
    edges = [float(f"{e:.4g}") for e in np.geomspace(low_hz, high, n + 1)]
    resolution = fs / welch_segment(fs, 1 << 30)
    bands: list[tuple[float, float]] = []
    lo = edges[0]
    for hi in edges[1:]:
        if hi - lo >= resolution or hi == edges[-1]:
            bands.append((lo, hi))
            lo = hi
    return bands


def welch_segment(fs: float, n: int) -> int:
    """Welch segment length (samples): the power of two nearest :data:`SEGMENT_S`·fs, at most ``n``, at least 8."""
    return int(max(8, min(n, 1 << max(3, round(math.log2(max(SEGMENT_S * fs, 8)))))))


def family_names(family: str, channels: int, fs: float, settings: Any = None) -> list[str]:
    """Every feature name of ``family`` for ``channels`` films at ``fs`` Hz.

    ``settings``: a :class:`tactiled.config.FeaturesConfig` (or anything with its attributes);
    None takes the defaults.
    """
    get = (lambda key, default: getattr(settings, key, default)) if settings is not None else (lambda key, default: default)
    if family == "dwt":
        return feature_names(channels, get("level", 4), get("domains", DOMAINS), get("stats", STAT_NAMES))
    if family == "psd":
        bands = psd_bands(fs, get("psd_low_hz", 20.0), get("psd_high_frac", 0.45), get("psd_bands_per_octave", 3.0))
        return [f"film{c + 1}.psd.{_num(lo)}-{_num(hi)}Hz.power" for c in range(channels) for lo, hi in bands]
    if family == "tex":
        return [f"film{c + 1}.tex.{t}" for c in range(channels) for t in TEX_NAMES]
    raise ValueError(f"unknown feature family {family!r}; known: {', '.join(FAMILIES)}")


SHORT_DWT = 1000  # rows of at most this many values go down one DWT level in one pywt.dwt call (FeaturePlan._downcoef)
HUGE_EXPONENT = 100  # a window with samples beyond 2**100 V, or all below 2**-100 V, is analysed scaled by a power of two


def pow2_normalised(x: npt.NDArray[np.float64]) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]:
    """(``x`` (W, ...) with each window scaled by 2**-k, k (W,)): k is 0 (the window as it is) unless the window's max |x|
    exceeds 2**:data:`HUGE_EXPONENT` or is below 2**-:data:`HUGE_EXPONENT` (and not 0), then the power of two that brings
    it into [0.5, 1). Scaling by a power of two is exact, so sums, squares and FFTs of the scaled window, scaled back, are
    the unscaled ones bit for bit wherever those are finite (what goes through a logarithm, to rounding); sums of squares
    of samples near 1e307 no longer overflow, and fourth moments of samples near 1e-85 no longer underflow to 0 (a
    kurtosis divided by zero)."""
    axes = tuple(range(1, x.ndim))
    top = np.maximum(x.max(axis=axes), -x.min(axis=axes)) if x.size else np.zeros(x.shape[0])
    off = ((top > 2.0 ** HUGE_EXPONENT) | ((top < 2.0 ** -HUGE_EXPONENT) & (top > 0))) & np.isfinite(top)
    if not off.any():
        return x, np.zeros(x.shape[0], dtype=np.int64)
    k = np.where(off, np.frexp(top)[1], 0).astype(np.int64)
    return np.ldexp(x, -k.reshape((-1,) + (1,) * (x.ndim - 1))), k


def feature_degree(name: str) -> int:
    """How a feature scales with the window's amplitude: ``a·x`` gives ``a**degree`` times it (0: scale-free, 1: volts,
    2: squared volts: DWT energy, psd power)."""
    fam = name_family(name)
    last = name.rsplit(".", 1)[-1]
    if fam == "psd":
        return 2
    if fam == "tex":
        return 1 if last == "rms" else 0
    return {"mean": 1, "sd": 1, "rms": 1, "energy": 2}.get(last, 0)


def name_family(name: str) -> str:
    """The family of a feature name: dwt, psd or tex."""
    part = name.split(".")[1] if name.count(".") >= 2 else ""
    return part if part in ("psd", "tex") else "dwt"


def is_log_feature(name: str) -> bool:
    """True for the features whose logarithm the classifiers see (positive, spanning decades)."""
    fam = name_family(name)
    last = name.rsplit(".", 1)[-1]
    if fam == "psd":
        return True
    if fam == "tex":
        return last in ("rms", "centroid", "spread", "rolloff")
    return last in ("sd", "energy", "rms")


@functools.lru_cache(maxsize=64)
def log_mask(names: tuple[str, ...]) -> npt.NDArray[np.bool_]:
    """(F,) True where :func:`is_log_feature` (cached: a model asks for the same names for every window)."""
    mask = np.array([is_log_feature(n) for n in names], dtype=bool)
    mask.setflags(write=False)
    return mask


def classifier_inputs(x: npt.NDArray[np.float64], names: Sequence[str]) -> npt.NDArray[np.float64]:
    """Features (n, F) as classifiers see them: log10 of :func:`is_log_feature` ones (floored at 1e-30), others as they are."""
    out = np.array(x, dtype=np.float64, copy=True)
    mask = log_mask(tuple(names))
    out[:, mask] = np.log10(np.maximum(out[:, mask], 1e-30))
    return out


def spectral_shape(powers: npt.NDArray[np.float64], names: Sequence[str]) -> npt.NDArray[np.float64]:
    """The shape of each channel's spectrum (n, B): log10 band powers (V², :func:`classifier_inputs`) of psd features
    ``powers`` (n, B) named ``names`` (``film<c>.psd.…``), less the mean over that channel's bands. A film's gain, which
    moves every band of its channel alike, leaves it unchanged; a silent channel (every band at the 1e-30 floor) is 0 (to rounding).
    Each row bit for bit that of the row alone (each channel's mean summed band by band: numpy sums the rows of a block in
    another order than one row)."""
    out = classifier_inputs(powers, names)
    for mine in channel_columns(tuple(names)):
        total = out[:, mine[0]].copy()
        for j in mine[1:]:
            total += out[:, j]
        out[:, mine] -= (total / len(mine))[:, None]
    return out


@functools.lru_cache(maxsize=64)
def channel_columns(names: tuple[str, ...]) -> tuple[list[int], ...]:
    """The columns of each channel among feature ``names`` (``film<c>.…``), channels in order (cached: a model asks for
    the same names for every slide)."""
    channels = [_channel(n) for n in names]
    return tuple([j for j, k in enumerate(channels) if k == c] for c in sorted(set(channels)))


def raw_features(inputs: npt.NDArray[np.float64], names: Sequence[str]) -> npt.NDArray[np.float64]:
    """The inverse of :func:`classifier_inputs`: raw features (n, F) whose classifier inputs are ``inputs`` (n, F)."""
    out = np.array(inputs, dtype=np.float64, copy=True)
    mask = log_mask(tuple(names))
    out[:, mask] = np.power(10.0, np.clip(out[:, mask], -300.0, 300.0))
    return out


@dataclass(frozen=True)
class ParsedName:
    """A DWT feature name, parsed."""

    channel: int  # 0-based
    domain: str
    kind: str  # "A" or "D"
    level: int
    stat: str


def parse_name(name: str) -> ParsedName:
    """Parse a DWT name ``film<c>.<domain>.<band>.<stat>``; ValueError naming the part that is wrong."""
    parts = name.split(".")
    if len(parts) != 4 or not parts[0].startswith("film") or not parts[0][4:].isdigit():
        raise ValueError(f"feature {name!r}: expected film<c>.<domain>.<band>.<stat>")
    channel = int(parts[0][4:]) - 1
    domain, band, stat = parts[1:]
    if channel < 0 or domain not in DOMAINS or len(band) < 2 or band[0] not in "AD" or not band[1:].isdigit() or int(band[1:]) < 1 \
            or stat not in STAT_NAMES:
        raise ValueError(f"feature {name!r}: unknown film, domain, band or statistic")
    return ParsedName(channel, domain, band[0], int(band[1:]), stat)


def _channel(name: str) -> int:
    head = name.split(".", 1)[0]
    if not head.startswith("film") or not head[4:].isdigit() or int(head[4:]) < 1:
        raise ValueError(f"feature {name!r}: expected film<c>.…")
    return int(head[4:]) - 1


def parse_psd(name: str, fs: float) -> tuple[int, float, float]:
    """(channel, lo Hz, hi Hz) of ``film<c>.psd.<lo>-<hi>Hz.power``; ValueError if malformed or beyond fs/2."""
    parts = name.split(".")
    try:
        if len(parts) != 4 or parts[3] != "power" or not parts[2].endswith("Hz"):
            raise ValueError
        lo, hi = (_unnum(v) for v in parts[2][:-2].split("-"))
    except ValueError:
        raise ValueError(f"feature {name!r}: expected film<c>.psd.<lo>-<hi>Hz.power") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo < hi <= fs / 2):
        raise ValueError(f"feature {name!r}: band must satisfy 0 <= lo < hi <= fs/2 = {fs / 2:g} Hz")
    return _channel(name), lo, hi


def psd_of(x: npt.NDArray[np.float64], fs: float) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """(f (m,) Hz, Welch PSD (..., m) V²/Hz) of signals ``x`` (..., n) (one channel of one window or of W windows): Hann
    segments of ~50 ms, half overlapping, mean removed.

    The same values as ``scipy.signal.welch(x, fs, "hann", nper, nper // 2, detrend="constant")`` (to rounding), in numpy;
    each signal's the same as alone.
    """
    x = np.asarray(x, dtype=np.float64)
    nper = welch_segment(fs, x.shape[-1])
    step = nper - nper // 2
    # the segments as a view, every step-th of sliding_window_view(x, nper)'s (as_strided directly: a tenth of its cost)
    last = x.strides[-1]
    segments = np.lib.stride_tricks.as_strided(x, (*x.shape[:-1], (x.shape[-1] - nper) // step + 1, nper),
                                               (*x.strides[:-1], step * last, last), writeable=False)
    f, window, scale = _welch_constants(nper, fs)
    spec = np.fft.rfft((segments - segments.mean(axis=-1, keepdims=True)) * window, axis=-1)
    p = (spec.real**2 + spec.imag**2).mean(axis=-2) / scale
    p[..., 1:-1 if nper % 2 == 0 else None] *= 2  # one-sided: every bin but DC (and Nyquist) holds both signs
    return f, np.asarray(p, dtype=np.float64)


@functools.lru_cache(maxsize=64)
def _welch_constants(nper: int, fs: float) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], float]:
    """(frequencies (m,) Hz, periodic Hann window (nper,), as scipy.signal.welch's "hann", and the PSD's scale fs·Σw²) of
    :func:`psd_of`'s segments of ``nper`` samples (cached, read-only: every window of a stream has the same)."""
    window = 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(nper) / nper)
    f = np.asarray(np.fft.rfftfreq(nper, 1.0 / fs), dtype=np.float64)
    window.setflags(write=False)
    f.setflags(write=False)
    return f, window, fs * float(np.dot(window, window))


def band_powers(f: npt.NDArray[np.float64], p: npt.NDArray[np.float64], bands: Sequence[tuple[float, float]]) -> npt.NDArray[np.float64]:
    """Power (V²) of each [lo, hi) band (..., B) of PSDs ``p`` (..., m) at frequencies ``f`` (m,), evenly spaced from 0: the
    integral of the PSD, linear between bins (fractional bins at the edges). Every row at once, each the values
    ``np.interp`` gives for that row alone (its formula, :func:`_interp_plan`)."""
    df = float(f[1] - f[0]) if f.size > 1 else 1.0
    rows = np.asarray(p, dtype=np.float64).reshape(-1, p.shape[-1])
    cum = np.concatenate((np.zeros((rows.shape[0], 1)), np.cumsum(rows, axis=1) * df), axis=1)  # power below each bin's upper edge
    lo, hi = _interp_plan(f.size, df, float(f[-1]), tuple(float(b[0]) for b in bands), tuple(float(b[1]) for b in bands))
    out: npt.NDArray[np.float64] = np.maximum(_interpolate(cum, hi) - _interpolate(cum, lo), 0.0).reshape(*p.shape[:-1], len(bands))
    return out


InterpPlan = tuple[npt.NDArray[np.intp], npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.intp], npt.NDArray[np.intp]]


@functools.lru_cache(maxsize=256)
def _interp_plan(m: int, df: float, f_last: float, *points: tuple[float, ...]) -> tuple[InterpPlan, ...]:
    """For each tuple of ``points`` (k,): where ``np.interp`` finds them on the bin edges of m bins ``df`` apart (the edges
    ``f - df / 2`` and ``f[-1] + df / 2``, floored at 0, ``f`` from 0): the interval j (k,), the point's offset from its
    start ``x - xp[j]`` and its width ``xp[j + 1] - xp[j]`` (k,) (numpy's formula: ``slope * (x - xp[j]) + fp[j]``), and the
    points that take an edge's value as it is: (point, edge) pairs (k',), (k',) (at an edge, beyond the ends). Cached: a
    model asks for the same bands at the same resolution for every window."""
    f = np.arange(m, dtype=np.float64) * df if m > 1 else np.zeros(1)
    f[-1] = f_last
    xp = np.concatenate((f - df / 2, [f_last + df / 2])).clip(min=0.0)
    plans = []
    for pts in points:
        x = np.asarray(pts, dtype=np.float64)
        j = np.clip(np.searchsorted(xp, x, side="right") - 1, 0, len(xp) - 2)
        edge = np.where(x < xp[0], 0, np.where(x >= xp[-1], len(xp) - 1, np.where(x == xp[j], j, -1)))
        taken = np.flatnonzero(edge >= 0)
        plans.append((j, x - xp[j], xp[j + 1] - xp[j], taken, edge[taken]))
    return tuple(plans)


def _interpolate(fp: npt.NDArray[np.float64], plan: InterpPlan) -> npt.NDArray[np.float64]:
    """(n, k) ``np.interp`` of every row of ``fp`` (n, m + 1) at the points of ``plan`` (:func:`_interp_plan`)."""
    j, offset, width, taken, edge = plan
    out: npt.NDArray[np.float64] = (fp[:, j + 1] - fp[:, j]) / width * offset + fp[:, j]
    if len(taken):
        out[:, taken] = fp[:, edge]
    return out


def texture(x: npt.NDArray[np.float64], f: npt.NDArray[np.float64], p: npt.NDArray[np.float64], fs: float,
            wanted: Iterable[str], slope_range: tuple[float, float]) -> dict[str, float]:
    """The asked texture descriptors (see the module docstring) of one channel ``x`` (n,) V with its PSD."""
    out: dict[str, float] = {}
    total = float(p.sum())
    d = x - x.mean()
    m2 = float(np.dot(d, d)) / max(1, d.size)
    silent = total <= 0.0 or m2 <= (1e-12 * max(float(np.max(np.abs(x))), 1e-300)) ** 2
    for name in wanted:
        if silent:
            out[name] = 0.0
        elif name in ("centroid", "spread"):
            c = float(np.dot(f, p)) / total
            out[name] = c if name == "centroid" else math.sqrt(max(float(np.dot((f - c) ** 2, p)) / total, 0.0))
        elif name == "rolloff":
            out[name] = float(f[min(int(np.searchsorted(np.cumsum(p), 0.85 * total)), f.size - 1)])
        elif name == "flatness":
            q = p[1:] if p.size > 1 else p
            out[name] = float(np.exp(np.mean(np.log(np.maximum(q, 1e-300)))) / max(float(q.mean()), 1e-300))
        elif name == "slope":
            keep = (f >= slope_range[0]) & (f <= slope_range[1]) & (p > 0)
            if keep.sum() >= 2:
                out[name] = float(np.polyfit(np.log10(f[keep]), np.log10(p[keep]), 1)[0])
            else:
                out[name] = 0.0
        elif name == "kurtosis":
            out[name] = float(np.mean(d**4)) / (m2 * m2)
        elif name == "crest":
            out[name] = float(np.max(np.abs(d))) / math.sqrt(m2)
        elif name == "zcr":
            out[name] = float(np.count_nonzero(np.signbit(d[1:]) != np.signbit(d[:-1]))) * fs / max(1, d.size)
        elif name == "rms":
            out[name] = math.sqrt(m2)
        else:
            raise ValueError(f"unknown texture descriptor {name!r}")
    return out


class FeaturePlan:
    """What to compute for a list of feature names (any mix of families); :meth:`compute` returns them in that order."""

    def __init__(self, names: Sequence[str], wavelet: str = "coif5", mode: str = "symmetric", fs: float = 20_000.0,
                 centred: bool = False) -> None:
        if not (math.isfinite(fs) and fs > 0):
            raise ValueError(f"fs must be finite and > 0, got {fs}")
        self.fs = fs
        self.names = list(names)
        self.centred = centred  # the dwt family of each window less its mean per channel (psd and tex are centred by definition)
        self.wavelet = pywt.Wavelet(wavelet)
        self.mode = mode
        # dwt: (channel, domain) -> max level needed; (channel, domain, band) -> stats
        self._levels: dict[tuple[int, str], int] = {}
        self._stats: dict[tuple[int, str, str], list[str]] = {}
        self._psd: dict[int, list[tuple[float, float]]] = {}  # channel -> its bands (lo, hi), Hz
        self._psd_at: dict[int, list[int]] = {}  # channel -> the column of each of its bands
        self._tex: dict[int, list[str]] = {}  # channel -> descriptors
        self._other_at: list[tuple[int, str]] = []  # (column, name) of every dwt and tex feature
        channels = []
        for i, n in enumerate(self.names):
            fam = name_family(n)
            if fam == "psd":
                c, lo, hi = parse_psd(n, fs)
                self._psd.setdefault(c, []).append((lo, hi))
                self._psd_at.setdefault(c, []).append(i)
            elif fam == "tex":
                c, last = _channel(n), n.split(".")
                if len(last) != 3 or last[2] not in TEX_NAMES:
                    raise ValueError(f"feature {n!r}: expected film<c>.tex.<one of {', '.join(TEX_NAMES)}>")
                self._tex.setdefault(c, []).append(last[2])
                self._other_at.append((i, n))
            else:
                p = parse_name(n)
                c = p.channel
                key = (p.channel, p.domain)
                self._levels[key] = max(self._levels.get(key, 0), p.level)
                stats = self._stats.setdefault((p.channel, p.domain, f"{p.kind}{p.level}"), [])
                if p.stat not in stats:
                    stats.append(p.stat)
                self._other_at.append((i, n))
            channels.append(c)
        self.channels_needed = 1 + max(channels, default=-1)
        self._degrees = np.array([feature_degree(n) for n in self.names], dtype=np.int64)
        self._slope_range = (20.0, 0.45 * fs)
        self._min_samples = self._shortest()

    def min_samples(self) -> int:
        """The shortest window every feature of the plan can be computed on (DWT: no boundary-only coefficients)."""
        return self._min_samples

    def _shortest(self) -> int:
        need = MIN_PSD_SAMPLES if (self._psd or self._tex) else 0
        for (_, domain), level in self._levels.items():
            n = (self.wavelet.dec_len - 1) * 2 ** level
            need = max(need, n if domain == "time" else 2 * (n - 1))
        return need

    def compute(self, x: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """Feature vector (len(names),) of window ``x`` (n, C) in volts, float64 (:meth:`compute_many` of one window).

        Raises :class:`WindowError` (reason ``window_too_short``) when n < :meth:`min_samples`, ``non_finite`` when a
        feature is beyond float64, and ValueError if x has fewer channels than the names need.
        """
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] < self.channels_needed:
            raise ValueError(f"window must have shape (n, >= {self.channels_needed}), got {x.shape}")
        out: npt.NDArray[np.float64] = self.compute_many(x[None])[0]
        # energies of a saturated window reach ~1e9; a non-finite one comes only from samples beyond any real sensor
        if not np.all(np.isfinite(out)):
            k = int(pow2_normalised(x[None])[1][0])
            raise WindowError("non_finite", "features are not finite" + (f" (samples up to 2^{k} V: their energies are beyond float64)" if k > 0 else ""))
        return out

    def compute_many(self, x: npt.NDArray[np.float64], *, bounded: bool = False) -> npt.NDArray[np.float64]:
        """Feature vectors (W, len(names)) of W windows ``x`` (W, n, C) in volts, float64, each row the same values as the
        window alone (the transforms run on all windows at once: offline, a slide's windows cost one call). ``bounded``:
        the caller knows that no |x| exceeds 2**:data:`HUGE_EXPONENT` and none but 0 is below 2**-:data:`HUGE_EXPONENT` (int16
        counts in volts), so no window is scaled.

        A row with a feature beyond float64 (the energy of samples near 1e307) holds inf (:meth:`compute` raises ``non_finite``).
        Raises :class:`WindowError` (reason ``window_too_short``) when n < :meth:`min_samples`, and ValueError if x has fewer
        channels than the names need. ``centred``: the dwt family reads each window less its mean per channel.
        """
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 3 or x.shape[2] < self.channels_needed:
            raise ValueError(f"windows must have shape (W, n, >= {self.channels_needed}), got {x.shape}")
        if x.shape[1] < self.min_samples():
            raise WindowError("window_too_short", f"window of {x.shape[1]} samples is shorter than the {self.min_samples()} the features need")
        x, k = (x, np.zeros(x.shape[0], dtype=np.int64)) if bounded else pow2_normalised(x)
        xt = x.transpose(0, 2, 1)  # (W, C, n): each channel's samples contiguous (free after remove_spikes_many)
        if not xt.flags.c_contiguous:
            xt = np.ascontiguousarray(xt)
        out = np.empty((x.shape[0], len(self.names)))
        values: dict[str, npt.NDArray[np.float64]] = {}  # the dwt and tex features by name
        for (channel, domain), level in self._levels.items():
            sig = xt[:, channel]
            if domain == "freq":
                sig = np.abs(np.fft.rfft(sig, axis=1))
                if self.centred:  # the spectrum of the window less its mean: the same but for the DC bin, which is 0
                    sig[:, 0] = 0.0
            elif self.centred:
                sig = sig - sig.mean(axis=1, keepdims=True)
            approx = sig
            skipped = 0  # levels whose approximation is needed only for the next: taken with the next in one call
            for j in range(1, level + 1):
                want = {kind: self._stats.get((channel, domain, f"{kind}{j}")) for kind in "AD"}
                if not (want["A"] or want["D"]) and j < level:
                    skipped += 1
                    continue
                if skipped and want["D"]:  # pywt.downcoef over several levels gives the levels' coefficients exactly
                    approx, skipped = self._downcoef("a", approx, skipped), 0
                # only the half of the transform the plan needs: pywt.downcoef gives dwt's coefficients exactly, at half the cost
                if want["D"] and (want["A"] or j < level):
                    approx, detail = pywt.dwt(approx, self.wavelet, mode=self.mode, axis=1)
                    coeffs = {"A": approx, "D": detail}
                elif want["D"]:
                    coeffs = {"D": self._downcoef("d", approx)}
                else:
                    approx, skipped = self._downcoef("a", approx, skipped + 1), 0
                    coeffs = {"A": approx}
                for kind, band in coeffs.items():
                    stats = want[kind]
                    if stats:
                        for stat, value in band_stats(band, stats).items():
                            values[f"film{channel + 1}.{domain}.{kind}{j}.{stat}"] = value
        for channel in sorted(set(self._psd) | set(self._tex)):
            f, p = psd_of(xt[:, channel], self.fs)
            if channel in self._psd:
                out[:, self._psd_at[channel]] = band_powers(f, p, self._psd[channel])
            if channel in self._tex:
                rows = [texture(xt[w, channel], f, p[w], self.fs, self._tex[channel], self._slope_range) for w in range(x.shape[0])]
                for t in self._tex[channel]:
                    values[f"film{channel + 1}.tex.{t}"] = np.array([r[t] for r in rows])
        for i, name in self._other_at:
            out[:, i] = values[name]
        if k.any():  # back to each window's own scale; a feature beyond float64 (energy of samples near 1e307) becomes inf
            with np.errstate(over="ignore"):
                out = np.ldexp(out, k[:, None] * self._degrees[None, :])
        return out

    def _downcoef(self, part: str, a: npt.NDArray[np.float64], levels: int = 1) -> npt.NDArray[np.float64]:
        """The ``part`` ("a" or "d") coefficients ``levels`` levels down of each row of ``a`` (W, m): pywt.downcoef is one
        signal at a time; one level of rows of at most :data:`SHORT_DWT` values, one pywt.dwt of all rows (the same
        coefficients: the same convolution per row; it computes the other half too, which costs less there than a call per row)."""
        if levels == 1 and a.shape[0] > 1 and a.shape[1] <= SHORT_DWT:
            coeffs: npt.NDArray[np.float64] = pywt.dwt(a, self.wavelet, mode=self.mode, axis=1)[0 if part == "a" else 1]
            return coeffs
        rows = [pywt.downcoef(part, row, self.wavelet, mode=self.mode, level=levels) for row in a]
        return np.stack(rows) if len(rows) > 1 else rows[0][None]
