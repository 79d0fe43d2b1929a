"""Sensor sample index → host time, from when the samples arrived: monotonic and smooth.

Two layers.

**The estimate** (``fs``, the line ``offset + index / fs``). A sample is taken before it arrives:
every (index, arrival time) pair is an upper bound on the time the sample was taken. The estimate
is the lower envelope of those bounds: the rate is the slope between the earliest arrivals
(relative to the nominal rate) in the older and the newer half of the last ``span_s`` seconds,
and the offset puts the line through the earliest arrival of all. So it never lies after an
arrival and tracks the board's crystal (its true rate) rather than the nominal one. What stays
is the smallest transport delay (USB + read interval), a constant of a few ms. A host stall
only delays arrivals, which the envelope ignores. The line is measured again only when arrivals
stay more than ``reset_s`` after it for ``persist_s`` on end (a board restart that continues the
timeline); an arrival before the line (a forward jump, a board faster than nominal) moves it
down at once. The estimate itself jumps: down whenever an earlier arrival shows up (at the start
by the first read's extra delay, tens of ms), and with every new rate.

**The map** (:meth:`mono`, :meth:`host`, :meth:`rate`): what is published. A continuous,
strictly increasing, piecewise-linear function of the index that follows the estimate without
ever stepping back. It has a knot at the end of the samples received at each :meth:`observe`;
the part up to that knot never changes afterwards (every time already handed out stays true). From
the last knot to the new end the map runs at the estimate's rate, corrected towards the estimate
by ``e / tau_s`` of it for an error of e s, at most ``max_slew`` (50 %): an exponential approach
with a time constant of ``tau_s`` (0.1 s). So the first read's extra delay (30 ms) is gone
to 0.5 ms within 0.5 s, and once settled (the rate is measured from 2 s on; 3 s in all) the
errors left are the envelope's sub-millisecond refinements, which move the local rate by
e / tau_s (0.3 ms: 0.3 %). Two cases step instead, forward only: an estimate more than
``step_s`` (50 ms) ahead of the map (a board restart, the line measured again) is joined at once;
an index jump that would put the map more than ``reset_s`` after the estimate (the board skipped
indices, no time passed) joins the estimate at the new end, squeezing the skipped indices (no
samples there) between the two knots.

The wall clock (unix times) is the map plus the host's ``time.time() - time.monotonic()``, which
the map follows at most 500 ppm per second (the fastest an NTP slew moves it), so unix times
increase too; a wall-clock step of more than ``wall_step_s`` (NTP step, date set) is followed at
once, in either direction.

**Arrival** is when the host read the bytes that completed the samples: the time of the read that returned them
(``SerialSource.read_at``), not when they were decoded nor the time of the newest read. A consumer that lags (the
daemon "overloaded: input 1.4 s behind") decodes bytes read long ago; fed the newest read's time, every pair would
look late by the lag, and a lag over ``reset_s`` held for ``persist_s`` would be taken for a board restart and the line
measured again from the late pairs (stamps up to 1.1 s late, then 0.8 s early, local rates of 645 Hz to 2e8 Hz at 20 kHz).

Driven by the host clock by nature (it measures it); the pipeline never uses it.
"""

from __future__ import annotations

import bisect
import math
import time
from array import array
from collections import deque
from collections.abc import Callable

BUCKET_S = 0.1  # one envelope point per this much host time
MIN_SPAN_S = 2.0  # the rate is the nominal one until arrivals span this long
MAX_KNOTS = 65_536  # knots kept (one per observe while the map slews, ~8 a second in the daemon: 2 hours); the oldest quarter
# goes when full (earlier indices: extrapolated). 24 bytes a knot in typed arrays (1.5 MB when full; ~100 as Python objects)
WALL_SLEW = 5e-4  # how fast the unix offset follows the host's, s per s of the map
WALL_BAND_S = 5e-6  # a wall-offset difference the map ignores (the two clocks are read one after the other)


RATE_TOLERANCE = 0.25  # a measured sample rate this far off sensor.fs (a fraction) is said once (a crystal is 1e-4 off)


def rate_mismatch(sensor_id: str, measured: float, nominal: float) -> str | None:
    """The one line a daemon or a recorder logs when samples arrive at ``measured`` Hz, more than :data:`RATE_TOLERANCE`
    away from ``sensor.fs`` = ``nominal`` (the board does not send its rate: one configured wrong times every slide and
    feature wrong, and is written into every recording); None within it."""
    if abs(measured / nominal - 1.0) <= RATE_TOLERANCE:
        return None
    return f"sensor {sensor_id}: samples arrive at about {measured:.0f} Hz, sensor.fs is {nominal:g} Hz: set [sensor] fs to the board's rate"


def wall_offset(tries: int = 3, monotonic: Callable[[], float] = time.monotonic, wall: Callable[[], float] = time.time) -> float:
    """The host's ``time.time() - time.monotonic()`` now, s: the wall clock read between two monotonic reads, less their
    midpoint, from the tightest of up to ``tries`` such triples. A thread preempted between two reads (a loaded host) would
    otherwise put the preemption, milliseconds, into the offset: past :data:`WALL_BAND_S` the unix map slews, past a
    map's ``wall_step_s`` it steps."""
    best_gap, best = math.inf, 0.0
    for _ in range(tries):
        m0 = monotonic()
        w = wall()
        m1 = monotonic()
        if m1 - m0 < best_gap:
            best_gap, best = m1 - m0, w - 0.5 * (m0 + m1)
        if best_gap <= 1e-6:
            break
    return best


class ClockMap:
    """Feed :meth:`observe` with (index one past the newest sample received, host monotonic time of the read that returned
    it: its arrival, not when it was decoded); read :meth:`mono` / :meth:`host`."""

    def __init__(self, fs_nominal: float, span_s: float = 30.0, reset_s: float = 0.5, persist_s: float = 1.0, tau_s: float = 0.1,
                 max_slew: float = 0.5, step_s: float = 0.05, wall_step_s: float = 0.1) -> None:
        self.fs_nominal = fs_nominal
        self.fs = fs_nominal  # the estimate's rate, samples per host second
        self.span_s = span_s
        self.reset_s = reset_s
        self.persist_s = persist_s
        self.tau_s = tau_s
        self.max_slew = max_slew
        self.step_s = step_s
        self.wall_step_s = wall_step_s
        self._late_since: float | None = None  # host time of the first of a run of arrivals later than reset_s
        self._points: deque[tuple[int, float]] = deque()  # (index, t) earliest arrival per bucket
        self._bucket: tuple[int, float] | None = None
        self._bucket_t0 = 0.0
        self._offset: float | None = None  # the estimate: host mono time of index 0
        self._ki = array("q")  # the map's knots: index, host mono time, unix - mono offset
        self._kt = array("d")
        self._ku = array("d")
        self._head = 1.0 / fs_nominal  # s per sample before the first knot (fixed: those times may have been handed out)
        self.resets = 0
        self.steps = 0  # forward steps of the map (restarts, index jumps)

    @property
    def ready(self) -> bool:
        """True once :meth:`observe` has placed a knot: :meth:`mono` and :meth:`host` can be read."""
        return bool(self._ki)

    def estimate(self, index: int) -> float:
        """The estimate's host monotonic time of sample ``index`` (may jump between calls; :meth:`mono` never does), s."""
        if self._offset is None:
            raise ValueError("ClockMap: no samples observed yet")
        return self._offset + index / self.fs

    def observe(self, end_index: int, t_mono: float, wall: float | None = None) -> None:
        """Samples up to ``end_index`` (exclusive) had arrived by ``t_mono`` (host monotonic, s).

        ``t_mono``: the time of the read that returned the bytes completing them (the module docstring, "Arrival"); not the
        time they were decoded, nor of a later read, or a consumer's lag reads as a late board.
        ``wall``: the host's ``time.time() - time.monotonic()`` then (default: measured now).
        """
        self._envelope(end_index, t_mono)
        self._plan(end_index, wall_offset() if wall is None else wall)

    def _envelope(self, end_index: int, t_mono: float) -> None:
        if self._offset is not None:
            # until the rate is measured (arrivals spanning MIN_SPAN_S) the line runs at the nominal rate, so a board slower
            # than sensor.fs falls behind it: that is what the measurement is for, not a restart (reset, it never measured one:
            # the rate stayed nominal and no warning came; an outside audit)
            if not self._measured() or t_mono - self.estimate(end_index) <= self.reset_s:
                self._late_since = None
            else:
                self._late_since = t_mono if self._late_since is None else self._late_since
                if t_mono - self._late_since < self.persist_s:
                    return  # a stall so far: a late arrival says nothing new about the line
                self._reset()
        if self._bucket is None:
            self._bucket, self._bucket_t0 = (end_index, t_mono), t_mono
        elif self._delay(end_index, t_mono) < self._delay(*self._bucket):
            self._bucket = (end_index, t_mono)
        if t_mono - self._bucket_t0 >= BUCKET_S or not self._points:
            self._points.append(self._bucket)
            self._bucket, self._bucket_t0 = None, t_mono
            while len(self._points) > 2 and self._points[-1][1] - self._points[0][1] > self.span_s:
                self._points.popleft()
            self._fit()
        elif self._offset is not None:
            self._offset = min(self._offset, t_mono - end_index / self.fs)

    def _reset(self) -> None:
        self._points.clear()
        self._bucket = None
        self._offset = None
        self._late_since = None
        self.fs = self.fs_nominal
        self.resets += 1

    def _delay(self, index: int, t: float) -> float:
        return t - index / self.fs_nominal

    def _measured(self) -> bool:
        """Whether the envelope's points span :data:`MIN_SPAN_S`: the rate is measured (else it is the nominal one)."""
        return len(self._points) > 1 and self._points[-1][1] - self._points[0][1] >= MIN_SPAN_S

    def _fit(self) -> None:
        pts = list(self._points)
        if self._measured():
            half = len(pts) // 2
            a = min(pts[:half], key=lambda p: self._delay(*p))
            b = min(pts[half:], key=lambda p: self._delay(*p))
            if b[1] > a[1] and b[0] > a[0]:
                self.fs = (b[0] - a[0]) / (b[1] - a[1])
        self._offset = min(t - i / self.fs for i, t in pts)

    def _plan(self, end: int, wall: float) -> None:
        """Extend the map from its last knot to ``end`` towards the estimate (module docstring)."""
        desired = self.estimate(end)
        if not self._ki:
            self._ki.append(end)
            self._kt.append(desired)
            self._ku.append(wall)
            self._head = 1.0 / self.fs
            return
        p, tp, up = self._ki[-1], self._kt[-1], self._ku[-1]
        if end <= p:
            return
        span = (end - p) / self.fs  # host seconds the new samples take at the estimate's rate
        natural = tp + span
        ahead = natural - desired  # > 0: the map would lie after the estimate
        if ahead < -self.step_s:
            te = desired  # the estimate moved forward (restart): join it, a forward step
            self.steps += 1
        elif ahead > self.reset_s:
            te = max(desired, tp + 1e-6)  # an index jump: join the estimate at the new end, squeezing the skipped indices
            self.steps += 1
        else:
            c = min(abs(ahead) / self.tau_s, self.max_slew) * span
            te = min(max(desired, natural - c), natural + c)
        drift = wall - up
        if abs(drift) > self.wall_step_s:
            ue = wall
        elif abs(drift) <= WALL_BAND_S:
            ue = up
        else:
            ue = up + min(max(drift, -WALL_SLEW * (te - tp)), WALL_SLEW * (te - tp))
        if len(self._ki) >= 2:  # on the last segment's line (within 1 ns, 1 us): move its end instead of adding a knot
            q, tq, uq = self._ki[-2], self._kt[-2], self._ku[-2]
            w = (end - q) / (p - q)
            if abs(tq + w * (tp - tq) - te) <= 1e-9 and abs(uq + w * (up - uq) - ue) <= 1e-6:
                self._ki[-1], self._kt[-1], self._ku[-1] = end, te, ue
                return
        self._ki.append(end)
        self._kt.append(te)
        self._ku.append(ue)
        if len(self._ki) > MAX_KNOTS:
            cut = MAX_KNOTS // 4
            self._head = (self._kt[cut] - self._kt[cut - 1]) / (self._ki[cut] - self._ki[cut - 1])
            del self._ki[:cut], self._kt[:cut], self._ku[:cut]

    def _at(self, index: int) -> tuple[float, float]:
        """(mono, unix - mono) of the map at ``index``."""
        if not self._ki:
            raise ValueError("ClockMap: no samples observed yet")
        ki, kt, ku = self._ki, self._kt, self._ku
        k = bisect.bisect_right(ki, index) - 1
        if k < 0:  # before the first knot: at the rate then
            return kt[0] + (index - ki[0]) * self._head, ku[0]
        if k == len(ki) - 1:  # at or after the last knot: on at the estimate's rate
            return kt[-1] + (index - ki[-1]) / self.fs, ku[-1]
        w = (index - ki[k]) / (ki[k + 1] - ki[k])
        return kt[k] + w * (kt[k + 1] - kt[k]), ku[k] + w * (ku[k + 1] - ku[k])

    def mono(self, index: int) -> float:
        """Host monotonic time at which sample ``index`` was taken (the map: never decreasing in ``index``, frozen once received), s."""
        return self._at(index)[0]

    def host(self, index: int) -> tuple[float, float]:
        """(monotonic, unix) host time of sample ``index``, s."""
        mono, off = self._at(index)
        return mono, mono + off

    def rate(self, start: int, stop: int) -> float:
        """Samples per host second of the map from ``start`` to ``stop``: row ``k`` of a batch at ``start`` is at
        ``mono(start) + k / rate(start, stop)``, and ``stop`` (the next batch's first row) at ``mono(stop)``, Hz."""
        if stop <= start or not self._ki:
            return self.fs
        dt = self.mono(stop) - self.mono(start)
        return (stop - start) / dt if dt > 0 else self.fs
