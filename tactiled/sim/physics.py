"""A physically grounded model of the fingertip (docs/simulator.md).

Causes → effects, per slide:

1. kinematics v(t): hand mode rests, accelerates 0 → v_max (~0.09 m/s, varying slide to
   slide) as v_max·min(t/t_ramp, 1)^p with 5 % tremor, cruises and stops; robot mode runs a
   fixed speed with a 20 ms ramp.  x(t) = Σ v / fs.
2. surface z(x): a Gaussian self-affine profile (PSD flat below q_r = 2π/ℓc, ∝ q^(−1−2H)
   above) on a 2 µm grid, scaled so that Rq = √(π/2)·Ra (Gaussian heights), one fresh track
   per slide; ℓc and H differ between specimens.
3. contact averaging: a Gaussian spatial low-pass of width a (also the anti-alias filter).
4. excitation e(t) = d z_f(x(t))/dt = v·z_f′(x(t)) [m/s]; film k sees a wider contact and a
   lower gain, plus cross-talk; stick-slip bursts at onset.
5. fingertip mechanics: a 2nd-order resonance ωn²/(s² + 2ζωn s + ωn²) per film,
   discretised exactly (zero-order hold, scipy.signal.cont2discrete) and run with lfilter.
6. PVDF + buffer: gain G (V per m/s) times a per-slide contact-force factor exp(σ_F·N(0,1)),
   then the first-order RC high-pass (τ = RC, bilinear).
7. disturbances: mains 50 Hz + 150 Hz (−12 dB), white noise, 1/f drift, Poisson spikes.
8. ADC: ±5 V, 16 bits, clipping, rounding.

Every LTI block carries its filter state from chunk to chunk, so reading the stream in any
chunk sizes gives the same samples as reading it at once; everything is seeded.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy import signal

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Surface:
    """A specimen: name, arithmetic roughness Ra (µm), lateral correlation length ℓc (µm), Hurst H.

    A grating (``period_um`` > 0) is a sinusoid of that spatial period carrying ``grating_share``
    of the roughness power, on a random self-affine background carrying the rest. Another specimen
    of a grade (:func:`new_specimens`) keeps the name and holds the grade's nominal Ra in ``nominal_ra_um``.
    """

    name: str
    ra_um: float
    corr_um: float
    hurst: float
    period_um: float = 0.0
    grating_share: float = 0.0
    nominal_ra_um: float = 0.0  # the grade's nominal Ra (µm) when this is another specimen of it (:func:`new_specimens`); 0: ``ra_um``

    @property
    def grade_ra_um(self) -> float:
        """The grade's nominal Ra, µm: the label a lab writes on the specimen (``ra_um`` is what the specimen has)."""
        return self.nominal_ra_um if self.nominal_ra_um > 0 else self.ra_um


def default_surfaces(specimen: int = 0) -> list[Surface]:
    """The 15 polished surfaces, Ra 0.44 … 4.43 µm spaced geometrically, named ``Ra0.44`` ….

    ``specimen`` 0: the nominal specimens (fixed seed, the same in every run); N >= 1: new specimens of the same grades
    (:func:`new_specimens`)."""
    ras = np.geomspace(0.44, 4.43, 15)
    rng = np.random.default_rng(20180649)  # fixed: the specimens are the same in every run
    corr = rng.uniform(20.0, 60.0, ras.size)
    hurst = rng.uniform(0.6, 0.9, ras.size)
    nominal = [Surface(f"Ra{ra:.2f}", float(ra), float(c), float(h)) for ra, c, h in zip(ras, corr, hurst, strict=True)]
    return new_specimens(nominal, specimen)


def grating_surfaces(specimen: int = 0) -> list[Surface]:
    """15 gratings: spatial periods 100 µm … 1 mm (geometric), Ra 1 … 3 µm, on a weak random background; named ``G0.10mm`` ….

    ``specimen`` as in :func:`default_surfaces` (a new specimen keeps its grating's period)."""
    periods = np.geomspace(100.0, 1000.0, 15)
    rng = np.random.default_rng(20171211)
    ras = rng.uniform(1.0, 3.0, periods.size)
    corr = rng.uniform(20.0, 60.0, periods.size)
    nominal = [Surface(f"G{p / 1000:.2f}mm", float(ra), float(c), 0.8, float(p), 0.8) for p, ra, c in zip(periods, ras, corr, strict=True)]
    return new_specimens(nominal, specimen)


@dataclass(frozen=True)
class Tolerance:
    """How much two units of the same fingertip, or two specimens of the same grade, differ: uniform, relative ± half-widths.

    A unit's PVDF films are cut, glued and embedded in silicone by hand: the film's position in the
    silicone and the silicone's cure set each film's resonance (±15 %, independently per film) and
    damping (±20 %); the glue layer and the film's area set its gain (±20 %, independently per film);
    the films' spacing the cross-talk (±30 %); the buffer's RC (1 %–10 % parts, a 10 % capacitor) its
    high-pass time constant (±10 %); cable and shielding the white-noise level (×0.7…1.5). A new
    specimen of a grade (a second sheet of the same sandpaper, a second polished sample) keeps the
    grade's name and nominal Ra; what it has lies within the grade's tolerance: Ra ±10 %, correlation
    length ±15 %, Hurst exponent ±0.05 (absolute).
    """

    resonance: float = 0.15  # each film's fn, independently
    damping: float = 0.2
    film_gain: float = 0.2  # each film's gain, independently
    crosstalk: float = 0.3
    tau_hp: float = 0.1
    noise: tuple[float, float] = (0.7, 1.5)  # factor on noise_v (a range, not ±)
    ra: float = 0.1  # a specimen's Ra around its grade's nominal value
    corr: float = 0.15
    hurst: float = 0.05  # absolute, clipped to [0.5, 0.95]


TOLERANCE = Tolerance()
"""The manufacturing tolerances :func:`other_unit` and :func:`new_specimens` draw within (docs/simulator.md)."""


def other_unit(params: SimParams, unit: int, tol: Tolerance = TOLERANCE) -> SimParams:
    """The parameters of unit ``unit`` of the same fingertip model: unit 0 is ``params``; others are drawn within ``tol``.

    Drawn uniformly, deterministically from ``unit`` alone: each film's resonance ``fn_hz`` (Hz) and gain ``film_gain``
    (relative) independently, the damping ratio ``zeta``, the cross-talk (relative), the buffer's high-pass time constant
    ``tau_hp_s`` (s) and the white-noise level ``noise_v`` (V RMS). A film's resonance stays below 0.45 fs; damping in
    (0.05, 0.95). ValueError for a negative ``unit``.
    """
    if unit < 0:
        raise ValueError(f"unit must be >= 0, got {unit}")
    if unit == 0:
        return params
    rng = np.random.default_rng([20261124, unit])

    def vary(value: float, width: float) -> float:
        return float(value * (1.0 + rng.uniform(-width, width)))

    films = max(params.channels, len(params.fn_hz), len(params.film_gain))
    fn = tuple(min(vary(params.for_channel(params.fn_hz, k, 1.2), tol.resonance), 0.45 * params.fs) for k in range(films))
    gain = tuple(vary(params.for_channel(params.film_gain, k, 0.7), tol.film_gain) for k in range(films))
    return replace(params, fn_hz=fn, film_gain=gain, zeta=float(np.clip(vary(params.zeta, tol.damping), 0.05, 0.95)),
                   crosstalk=vary(params.crosstalk, tol.crosstalk), tau_hp_s=vary(params.tau_hp_s, tol.tau_hp),
                   noise_v=float(params.noise_v * rng.uniform(*tol.noise)))


def new_specimens(surfaces: Sequence[Surface], specimen: int, tol: Tolerance = TOLERANCE) -> list[Surface]:
    """Specimen ``specimen`` of each grade in ``surfaces`` (a whole family, in order: the draws follow it).

    0 is ``surfaces``; N >= 1 keeps the names (the grades), each grade's nominal Ra (``grade_ra_um``, µm) and a grating's
    period, and draws the specimen's own Ra (µm), correlation length (µm) and Hurst exponent within ``tol``, uniformly,
    deterministically from ``specimen``. ValueError for a negative ``specimen``."""
    if specimen < 0:
        raise ValueError(f"specimen must be >= 0, got {specimen}")
    if specimen == 0:
        return list(surfaces)
    rng = np.random.default_rng([20261125, specimen])
    out = []
    for s in surfaces:
        ra = s.ra_um * (1.0 + rng.uniform(-tol.ra, tol.ra))
        corr = s.corr_um * (1.0 + rng.uniform(-tol.corr, tol.corr))
        hurst = float(np.clip(s.hurst + rng.uniform(-tol.hurst, tol.hurst), 0.5, 0.95))
        out.append(replace(s, ra_um=float(ra), corr_um=float(corr), hurst=hurst, nominal_ra_um=s.grade_ra_um))
    return out


def family_surfaces(family: str, specimen: int = 0) -> list[Surface]:
    """The 15 specimens of a surface family (self-affine: :func:`default_surfaces`; grating: :func:`grating_surfaces`);
    ``specimen`` as there."""
    return grating_surfaces(specimen) if family == "grating" else default_surfaces(specimen)


def pick_surfaces(spec: str | int | None, family: str = "self-affine", specimen: int = 0) -> list[Surface]:
    """``None``: all 15 of ``family``; an int N (or "N"): N spread over the range; else names, e.g. ``Ra0.44,Ra4.43``.

    ``specimen``: which specimens of the grades (:func:`new_specimens`); a grade's specimen does not depend on the pick."""
    surfaces = family_surfaces(family, specimen)
    if spec is None or spec == "":
        return surfaces
    if isinstance(spec, int) or str(spec).isdigit():
        n = int(spec)
        if not 1 <= n <= len(surfaces):
            raise ValueError(f"--surfaces: N must be in 1..{len(surfaces)}, got {n}")
        return [surfaces[i] for i in np.round(np.linspace(0, len(surfaces) - 1, n)).astype(int)]
    by_name = {s.name: s for s in surfaces}
    out = []
    for name in str(spec).split(","):
        if name.strip() not in by_name:
            raise ValueError(f"--surfaces: unknown surface {name.strip()!r}; known: {', '.join(by_name)}")
        if by_name[name.strip()] in out:  # its files would overwrite the first's (named by surface and number)
            raise ValueError(f"--surfaces: {name.strip()!r} is named twice")
        out.append(by_name[name.strip()])
    return out


@dataclass(frozen=True)
class SimParams:
    """Every parameter of the model, with the ranges the notes justify. Units in names."""

    fs: float = 20_000.0
    channels: int = 2
    mode: str = "manual"  # manual | robot
    volts_per_count: float = 5.0 / 32768.0
    full_scale_v: float = 5.0
    # kinematics
    v_max_mps: tuple[float, float] = (0.085, 0.095)
    t_ramp_s: tuple[float, float] = (0.2, 0.35)
    ramp_power: tuple[float, float] = (1.0, 1.5)
    tremor: float = 0.05
    robot_speed_mps: float = 0.08
    slide_s: tuple[float, float] = (1.1, 1.6)
    rest_s: tuple[float, float] = (0.5, 1.2)
    # surface and contact
    dx_um: float = 2.0
    contact_um: float = 50.0
    # electromechanics
    gain_v_per_mps: float = 150.0
    force_sigma: float = 0.06
    robot_force_sigma: float = 0.01
    fn_hz: tuple[float, ...] = (900.0, 1200.0)
    zeta: float = 0.3
    tau_hp_s: float = 0.024
    film_gain: tuple[float, ...] = (1.0, 0.7)
    crosstalk: float = 0.15
    stick_slip: bool = True
    # disturbances
    mains_hz: float = 50.0
    mains_v: float = 0.01
    noise_v: float = 0.002
    drift_v: float = 0.003
    spike_rate_hz: float = 2.0
    spike_v: tuple[float, float] = (0.5, 2.0)
    # scenes (docs/simulator.md)
    continuous: bool = False  # one slide from before the first sample to after the last
    continuous_s: tuple[float, float] = (6.0, 8.0)
    dips_db: tuple[float, float] = (0.0, 0.0)  # fluctuating: level dips of this depth (dB) inside slides
    dip_s: tuple[float, float] = (0.1, 0.3)  # ... lasting this long
    dips_per_s: float = 0.0  # ... this often
    extra_gain: float = 1.0  # hot-gain: this file's gain factor (set per surface by the dataset writer)
    float_output: bool = False  # float32 volts (no ADC), with an offset and a wander
    dc_offset_v: tuple[float, float] = (0.0, 0.0)
    wander_v: float = 0.0  # slow baseline wander (RMS, V), below ~1 Hz
    family: str = "self-affine"  # surface family: self-affine | grating

    def for_channel(self, values: tuple[float, ...], c: int, step: float) -> float:
        """Channel ``c``'s value of a per-channel tuple: its own, or beyond the tuple the last one times ``step`` per channel further."""
        return values[c] if c < len(values) else values[-1] * step ** (c - len(values) + 1)

    def to_meta(self) -> dict[str, Any]:
        """Every parameter as a dict (a recording's ``meta["simulator"]``)."""
        return asdict(self)


@dataclass
class SlideTruth:
    """Ground truth of one slide: start of motion and end (absolute sample indices), surface."""

    start: int
    stop: int
    surface: Surface
    v_max_mps: float
    force: float


def _self_affine_profile(n: int, dx: float, surface: Surface, rng: np.random.Generator) -> tuple[npt.NDArray[np.complex128], FloatArray]:
    """Spectrum Z(q) of a Gaussian self-affine profile of n points, scaled to Rq = √(π/2)·Ra; and q (rad/m)."""
    q = np.asarray(2 * np.pi * np.fft.rfftfreq(n, dx), dtype=np.float64)
    q_r = 2 * np.pi / (surface.corr_um * 1e-6)
    shape = np.where(q < q_r, 1.0, (np.maximum(q, 1e-12) / q_r) ** (-(1 + 2 * surface.hurst)))
    spec = (rng.standard_normal(q.size) + 1j * rng.standard_normal(q.size)) * np.sqrt(shape)
    spec[0] = 0.0
    # scale by the ensemble variance (E|X_k|² = 2·shape_k, irfft weights interior bins twice):
    # the specimen has this Rq, each finite track fluctuates around it as a measured track would
    expected_var = 4.0 * float(shape[1:].sum()) / n**2
    rq = math.sqrt(math.pi / 2) * surface.ra_um * 1e-6
    random_share = 1.0 - surface.grating_share if surface.period_um > 0 else 1.0
    scaled = np.asarray(spec * (rq * math.sqrt(random_share) / math.sqrt(expected_var)), dtype=np.complex128)
    if surface.period_um > 0:  # a sinusoid of the grating's period with the rest of the power, random phase
        k = max(1, round(n * dx / (surface.period_um * 1e-6)))
        amplitude = math.sqrt(2 * surface.grating_share) * rq  # a sine of amplitude A has variance A²/2
        scaled[k] += amplitude * n / 2 * np.exp(1j * rng.uniform(0, 2 * np.pi))
    return scaled, q


class SensorSimulator:
    """A stream of samples from a fingertip sliding over ``surfaces``.

    Call :meth:`add_slide` / :meth:`add_rest` to schedule episodes (or let
    :meth:`schedule_random` do it), then :meth:`read` / :meth:`read_volts` any number of
    samples in any chunks. ``truth`` lists the slides scheduled so far.
    """

    def __init__(self, params: SimParams, seed: int = 0) -> None:
        if params.family not in ("self-affine", "grating"):
            raise ValueError(f"family must be self-affine or grating, got {params.family!r}")
        if params.mode not in ("manual", "robot"):
            raise ValueError(f"mode must be manual or robot, got {params.mode!r}")
        if params.channels < 1 or params.fs <= 0:
            raise ValueError("channels must be >= 1 and fs > 0")
        self.p = params
        self.rng = np.random.default_rng(seed)
        self.truth: list[SlideTruth] = []
        self._scheduled: list[FloatArray] = []  # episodes (n, C, 4): excitation [m/s], white [V], drift, spikes [V]
        self._scheduled_n = 0
        self._pos = 0  # absolute index of the next sample read
        self._buffer = np.zeros((0, params.channels))
        self._buffer_start = 0
        fs, c = params.fs, params.channels
        self._mech = []
        for k in range(c):
            fn = min(params.for_channel(params.fn_hz, k, 1.2), 0.45 * fs)
            wn = 2 * np.pi * fn
            a_c = np.array([[0.0, 1.0], [-wn * wn, -2 * params.zeta * wn]])
            b_c = np.array([[0.0], [wn * wn]])
            ad, bd, cd, dd, _ = signal.cont2discrete((a_c, b_c, np.array([[1.0, 0.0]]), np.array([[0.0]])), 1 / fs, method="zoh")
            b, a = signal.ss2tf(ad, bd, cd, dd)
            self._mech.append((np.asarray(b[0], dtype=np.float64), np.asarray(a, dtype=np.float64)))
        self._hp = signal.bilinear([params.tau_hp_s, 0.0], [params.tau_hp_s, 1.0], fs)
        self._zi_mech = [np.zeros(max(len(a), len(b)) - 1) for b, a in self._mech]
        self._zi_hp = [np.zeros(1) for _ in range(c)]
        self._zi_drift = [np.zeros(1) for _ in range(c)]
        self._gains: list[FloatArray] = []
        self._mains_phase = self.rng.uniform(0, 2 * np.pi, 2)
        # a DC offset and a slow baseline wander (a few sub-Hz sinusoids), one per channel (one-channel scene)
        self._offset = self.rng.uniform(*params.dc_offset_v, c) * self.rng.choice((-1.0, 1.0), c)
        self._wander = [(self.rng.uniform(0.02, 0.5, 4), self.rng.uniform(0, 2 * np.pi, 4)) for _ in range(c)]

    # ---- scheduling -------------------------------------------------------------------------

    @property
    def scheduled_end(self) -> int:
        """Absolute index one past the last scheduled sample."""
        return self._scheduled_n

    def add_rest(self, seconds: float) -> None:
        """Schedule ``seconds`` without contact (noise, hum and spikes only)."""
        n = max(1, round(seconds * self.p.fs))
        self._push(np.zeros((n, self.p.channels)), np.ones(n))

    def add_slide(self, surface: Surface, seconds: float | None = None) -> SlideTruth:
        """Schedule one slide over ``surface``; returns its ground truth."""
        p, rng, fs = self.p, self.rng, self.p.fs
        dur = seconds if seconds is not None else rng.uniform(*p.slide_s)
        n = max(2, round(dur * fs))
        t = np.arange(n) / fs
        if p.mode == "manual":
            v_max = rng.uniform(*p.v_max_mps)
            ramp = np.minimum(t / rng.uniform(*p.t_ramp_s), 1.0) ** rng.uniform(*p.ramp_power)
            tremor = 1 + p.tremor * np.sin(2 * np.pi * rng.uniform(3, 10) * t + rng.uniform(0, 2 * np.pi))
            stop_s = 0.1
            force = math.exp(p.force_sigma * rng.standard_normal())
        else:
            v_max = p.robot_speed_mps
            ramp = np.minimum(t / 0.02, 1.0)
            tremor = np.ones(n)
            stop_s = 0.02
            force = math.exp(p.robot_force_sigma * rng.standard_normal())
        v = v_max * ramp * tremor * np.clip((dur - t) / stop_s, 0.0, 1.0)
        v[0] = 0.0
        v = np.maximum(v, 0.0)
        level = self._dips(t, dur)  # fluctuating contact: the vibration level dips (speed and force each take half, in dB)
        v = v * np.sqrt(level)
        x = np.concatenate(([0.0], np.cumsum(v[:-1]) / fs))
        dx = p.dx_um * 1e-6
        m = int(x[-1] / dx) + 64
        m += m % 2
        grid = np.arange(m) * dx
        exc = np.zeros((n, p.channels))
        spec, q = _self_affine_profile(m, dx, surface, rng)
        for k in range(p.channels):
            a = p.contact_um * 1e-6 * (1 + 0.5 * k)
            slope = np.fft.irfft(1j * q * spec * np.exp(-0.5 * (q * a) ** 2), m)
            exc[:, k] = p.for_channel(p.film_gain, k, 0.7) * v * np.interp(x, grid, slope)
        if p.channels > 1:
            exc[:, 1:] += p.crosstalk * exc[:, :1]
        if p.stick_slip:
            onset_n = np.flatnonzero(v > 0)[0]
            for _ in range(rng.integers(1, 4)):
                t0 = onset_n / fs + rng.uniform(0.0, 0.12)
                tt = t - t0
                burst = rng.uniform(3e-4, 1.5e-3) * np.exp(-np.maximum(tt, 0) / rng.uniform(0.003, 0.01)) * np.sin(2 * np.pi * rng.uniform(50, 300) * tt)
                burst[tt < 0] = 0.0
                exc += burst[:, None] * rng.uniform(0.5, 1.0, p.channels)
        moving = np.flatnonzero(v > 0)
        truth = SlideTruth(self._scheduled_n + int(moving[0]), self._scheduled_n + int(moving[-1]) + 1, surface, float(v_max), float(force))
        self.truth.append(truth)
        self._push(exc, force * p.extra_gain * np.sqrt(level))
        return truth

    def _dips(self, t: FloatArray, dur: float) -> FloatArray:
        """Amplitude factor (n,) of a slide: 1, with smooth dips of ``dips_db`` lasting ``dip_s`` (fluctuating scene)."""
        p, rng = self.p, self.rng
        level = np.ones(t.size)
        if p.dips_per_s <= 0 or dur < 0.8:
            return level
        for _ in range(max(1, int(rng.poisson(p.dips_per_s * dur)))):
            width = rng.uniform(*p.dip_s)
            centre = rng.uniform(0.3 + width / 2, max(0.3 + width / 2, dur - 0.3 - width / 2))
            floor = 10 ** (-rng.uniform(*p.dips_db) / 20)
            # a raised-cosine dip: full depth over its middle, 25 % of its width to get there on each side
            u = np.clip((np.abs(t - centre) - 0.25 * width) / (0.25 * width), 0.0, 1.0)
            level = np.minimum(level, floor + (1 - floor) * (0.5 - 0.5 * np.cos(np.pi * u)))
        return level

    def schedule_random(self, surfaces: Sequence[Surface], until: int) -> None:
        """Rest and slide over randomly chosen ``surfaces`` until ``until`` samples are scheduled."""
        while self._scheduled_n < until:
            self.add_rest(self.rng.uniform(*self.p.rest_s))
            self.add_slide(surfaces[int(self.rng.integers(len(surfaces)))])

    def _push(self, exc: FloatArray, gain: FloatArray) -> None:
        """Queue an episode with all its random disturbances drawn now, so reads are chunk-invariant."""
        p, rng = self.p, self.rng
        n, c = exc.shape
        white = p.noise_v * rng.standard_normal((n, c))
        drift = rng.standard_normal((n, c))
        spikes = np.zeros((n, c))
        for _ in range(rng.poisson(p.spike_rate_hz * n / p.fs)):
            at, width, k = int(rng.integers(n)), int(rng.integers(1, 4)), int(rng.integers(c))
            spikes[at:at + width, k] += rng.choice((-1.0, 1.0)) * rng.uniform(*p.spike_v)
        self._scheduled.append(np.stack([exc, white, drift, spikes], axis=2))
        self._gains.append(gain)
        self._scheduled_n += n

    # ---- reading ----------------------------------------------------------------------------

    def read_volts(self, n: int) -> FloatArray:
        """The next ``n`` samples in volts (n, C), before the ADC; schedules rest if needed."""
        if self._scheduled_n - self._pos < n:
            self.add_rest((n - (self._scheduled_n - self._pos)) / self.p.fs)
        block, gain = self._take(n)
        exc, white, drift_in, spikes = (block[:, :, i] for i in range(4))
        p, fs = self.p, self.p.fs
        out = np.empty_like(exc)
        idx = np.arange(self._pos, self._pos + n)
        t_abs = idx / fs
        mains = p.mains_v * (np.sin(2 * np.pi * p.mains_hz * t_abs + self._mains_phase[0])
                             + 0.25 * np.sin(2 * np.pi * 3 * p.mains_hz * t_abs + self._mains_phase[1]))
        drift_b, drift_a = [1.0 - 0.999], [1.0, -0.999]
        for k in range(p.channels):
            b, a = self._mech[k]
            y, self._zi_mech[k] = signal.lfilter(b, a, exc[:, k], zi=self._zi_mech[k])
            y = y * p.gain_v_per_mps * gain
            y, self._zi_hp[k] = signal.lfilter(self._hp[0], self._hp[1], y, zi=self._zi_hp[k])
            drift, self._zi_drift[k] = signal.lfilter(drift_b, drift_a, drift_in[:, k], zi=self._zi_drift[k])
            out[:, k] = y + mains * (1.0 - 0.3 * k) + white[:, k] + p.drift_v * 22.0 * drift + spikes[:, k]
            if p.wander_v > 0 or self._offset[k] != 0:
                f, phase = self._wander[k]
                wander = np.sin(2 * np.pi * f[:, None] * t_abs[None, :] + phase[:, None]).sum(axis=0) * (p.wander_v / math.sqrt(2))
                out[:, k] += self._offset[k] + wander
        self._pos += n
        return out

    def _take(self, n: int) -> tuple[FloatArray, FloatArray]:
        parts, gains, need = [], [], n
        while need:
            block, gain = self._scheduled[0], self._gains[0]
            take = min(need, block.shape[0])
            parts.append(block[:take])
            gains.append(gain[:take])
            if take == block.shape[0]:
                self._scheduled.pop(0)
                self._gains.pop(0)
            else:
                self._scheduled[0] = block[take:]
                self._gains[0] = gain[take:]
            need -= take
        return np.concatenate(parts), np.concatenate(gains)

    def read(self, n: int) -> npt.NDArray[np.int16]:
        """The next ``n`` samples as int16 ADC counts (n, C): clipped at ±full scale, rounded."""
        return adc(self.read_volts(n), self.p.volts_per_count, self.p.full_scale_v)

    @property
    def position(self) -> int:
        """Samples read so far: the index of the next sample."""
        return self._pos


def adc(volts: FloatArray, volts_per_count: float, full_scale_v: float = 5.0) -> npt.NDArray[np.int16]:
    """Clip to ±``full_scale_v`` and quantise to int16 counts."""
    counts = np.round(np.clip(volts, -full_scale_v, full_scale_v) / volts_per_count)
    return np.clip(counts, -32768, 32767).astype(np.int16)


@dataclass
class SimulatedFile:
    """One simulated recording: ``samples`` (n, C) int16 counts or float32 volts, and the ground truth of its slides."""

    samples: npt.NDArray[Any]  # (n, C) int16 counts, or float32 volts
    truth: list[SlideTruth] = field(default_factory=list)


def simulate_file(params: SimParams, surface: Surface, slides: int, seed: int) -> SimulatedFile:
    """One recording: ``slides`` slides over one surface, rests between and around them.

    ``params.continuous``: one slide under way before the first sample and after the last
    (``continuous_s`` long, cut from the middle of a longer slide), ground truth the whole file.
    ``params.float_output``: float32 volts (clipped at the rails, not quantised), else int16 counts.
    """
    model = SensorSimulator(params, seed)
    lead = 0
    if params.continuous:
        keep = round(model.rng.uniform(*params.continuous_s) * params.fs)
        lead = round(1.0 * params.fs)
        truth = model.add_slide(surface, (keep + 2 * lead) / params.fs)
    else:
        for _ in range(slides):
            model.add_rest(model.rng.uniform(*params.rest_s))
            model.add_slide(surface)
        model.add_rest(0.4)
    volts = model.read_volts(model.scheduled_end)
    if params.continuous:
        volts = volts[lead:lead + keep]
        model.truth = [replace(truth, start=0, stop=keep)]
    return SimulatedFile(output(volts, params), model.truth)


def output(volts: FloatArray, params: SimParams) -> npt.NDArray[Any]:
    """What the sensor gives for ``volts`` (n, C): float32 volts clipped at the rails (``params.float_output``), else int16
    counts (:func:`adc`); either times ``params.volts_per_count`` is volts (a float scene's is 1)."""
    if params.float_output:
        return np.clip(volts, -params.full_scale_v, params.full_scale_v).astype(np.float32)
    return adc(volts, params.volts_per_count, params.full_scale_v)


SCENES = ("hand", "robot", "continuous", "fluctuating", "hot-gain", "one-channel", "grating")
_EXCLUSIVE = (("hand", "robot"),)
_SCENE_CHANGES: dict[str, dict[str, Any]] = {
    "hand": {"mode": "manual"},
    "robot": {"mode": "robot"},
    "continuous": {"continuous": True},
    "fluctuating": {"dips_db": (10.0, 20.0), "dip_s": (0.1, 0.3), "dips_per_s": 1.0, "slide_s": (1.8, 3.0), "force_sigma": 0.1},
    "hot-gain": {},  # the dataset writer raises the gain of the roughest third of the surfaces (extra_gain)
    "one-channel": {"fs": 2200.0, "channels": 1, "float_output": True, "dc_offset_v": (0.1, 1.0), "wander_v": 0.03, "volts_per_count": 1.0},
    "grating": {"family": "grating"},
}


def parse_scene(spec: str) -> list[str]:
    """The scene names of a comma list (``continuous,one-channel``); ValueError for unknown or contradictory ones."""
    names = [n.strip() for n in spec.split(",") if n.strip()]
    if not names:
        raise ValueError(f"--scene: empty; choose from {', '.join(SCENES)}")
    for n in names:
        if n not in SCENES:
            raise ValueError(f"--scene: unknown scene {n!r}; known: {', '.join(SCENES)}")
    for group in _EXCLUSIVE:
        both = [n for n in names if n in group]
        if len(both) > 1:
            raise ValueError(f"--scene: {' and '.join(both)} contradict each other")
    if "continuous" in names and "fluctuating" in names:
        pass  # a continuous slide with dips: allowed
    return names


def scene_params(spec: str, base: SimParams | None = None) -> SimParams:
    """The simulator parameters of a scene spec (comma list); ``robot`` kinematics unless ``hand`` is named, except
    that the default (no kinematics named, not continuous) is ``hand``."""
    names = parse_scene(spec)
    params = base or SimParams()
    changes: dict[str, Any] = {}
    if not {"hand", "robot"} & set(names):
        changes["mode"] = "robot" if "continuous" in names else "manual"
    for n in names:
        changes.update(_SCENE_CHANGES[n])
    return replace(params, **changes)


def hot_gain(surfaces: Sequence[Surface], surface: Surface, params: SimParams, seed: int = 0) -> float:
    """The hot-gain scene's gain factor for ``surface``: 1, except for the roughest third of ``surfaces``, whose gain
    is raised so that 5 % (the least rough of them) to 40 % (the roughest) of a slide's samples clip.

    Measured on a pilot slide: a Gaussian signal of RMS σ clipped at ±V exceeds it with probability
    2·(1 − Φ(V/σ)), so the gain sets V/σ from 1.96 (5 %) down to 0.84 (40 %)."""
    order = sorted(surfaces, key=lambda s: s.ra_um)
    hot = order[len(order) - max(1, len(order) // 3):] if len(order) >= 3 else order[-1:]
    if surface not in hot:
        return 1.0
    rank = hot.index(surface) / max(1, len(hot) - 1) if len(hot) > 1 else 1.0
    k = 1.96 + (0.84 - 1.96) * rank
    pilot = SensorSimulator(replace(params, extra_gain=1.0, dips_per_s=0.0, spike_rate_hz=0.0), seed)
    truth = pilot.add_slide(surface, 1.5)
    volts = pilot.read_volts(pilot.scheduled_end)[truth.start + round(0.4 * params.fs):truth.stop]
    sigma = float(np.sqrt(np.mean(np.var(volts, axis=0))))
    return params.full_scale_v / (k * max(sigma, 1e-9))


def with_mode(params: SimParams, mode: str | None, fs: float | None, channels: int | None = None) -> SimParams:
    """``params`` with the CLI's mode, rate and channel count applied."""
    changes: dict[str, Any] = {}
    if mode:
        changes["mode"] = mode
    if fs:
        changes["fs"] = float(fs)
    if channels:
        changes["channels"] = int(channels)
    return replace(params, **changes)
