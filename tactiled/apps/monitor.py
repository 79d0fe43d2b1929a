"""``tactiled monitor``: a live terminal view of a running daemon (rich).

Up front the device and connection state; then both films' levels as moving traces, a live
spectrum of the raw samples (the daemon must publish them: ``publish.samples`` or ``run
--samples``), and the label history: provisional and final labels with their confidence,
abstentions highlighted with their reason, and the true surface when a virtual board's log
is given (``--truth``: the simulator knows it, a real board does not). ``q`` or Ctrl-C quits.

rich rather than Textual: the screen is redrawn from one model at a fixed rate, which rich's
``Live`` does with no application framework or event loop of its own to combine with the
ZeroMQ subscriber, and the same renderable prints to a string for headless tests.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import select
import sys
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from tactiled_client import BlockingSubscriber, NoData, Roughness, Samples, Slide, Status, schema
from tactiled_client.truth import overlapping

TRACE_LEN = 120  # points per film trace (one per 10 ms of signal)
LABEL_HISTORY = 40  # labels kept; as many as fit are shown
FULL_SIZE = (100, 40)  # (columns, lines) from which the screen also shows the spectrum and every label column
SPECTRUM_N = 4096  # samples per spectrum
SPARK = "▁▂▃▄▅▆▇█"
STALE_AFTER_S = 3.0  # no message for this long: the daemon's state is shown as "no data" and its live figures blanked
NO_DATA = "no data"


def sparkline(values: np.ndarray, top: float) -> str:
    """One character per value, 8 levels from 0 to ``top``."""
    if values.size == 0 or top <= 0:
        return ""
    idx = np.clip((values / top * (len(SPARK) - 1)).round().astype(int), 0, len(SPARK) - 1)
    return "".join(SPARK[i] for i in idx)


def read_truth(path: str | Path) -> list[tuple[int, int, str]]:
    """(start, stop, surface) of the slides in a virtual board's log (``simulate serial --log``)."""
    out = []
    try:
        with open(path, encoding="utf-8") as fh:
            for line in fh:
                ev = json.loads(line) if line.strip() else {}
                if ev.get("event") == "slide":
                    out.append((int(ev["start"]), int(ev["stop"]), str(ev["surface"])))
    except FileNotFoundError:
        pass
    return out


class MonitorState:
    """What the screen shows, updated from messages (kept apart from drawing, for tests)."""

    def __init__(self, truth_log: str | None = None) -> None:
        self.status: Status | None = None
        self.slide: Slide | None = None
        self.labels: deque[Roughness] = deque(maxlen=LABEL_HISTORY)
        self.missed = 0
        self.last_message = 0.0
        self.traces: list[deque[float]] = []
        self.raw: deque[np.ndarray] = deque()
        self.raw_n = 0
        self.fs = 0.0
        self.truth_log = truth_log
        self._truth: list[tuple[int, int, str]] = []
        self.stale_s = 0.0  # seconds since the last message, once over STALE_AFTER_S (0: the figures are live)

    def update(self, msg: Any) -> None:
        """Fold one message (status, slide, roughness or samples) into the state, adding the messages it says were missed."""
        self.last_message = time.monotonic()
        self.stale_s = 0.0
        self.missed += msg.missed
        if isinstance(msg, Status):
            self.status = msg
            if msg.state in (schema.STATE_DISCONNECTED, schema.STATE_STOPPING):  # no slide goes on without samples
                self.slide = None
        elif isinstance(msg, Slide) and msg.event == schema.SLIDE_RESUMED:  # its final label is withdrawn: the slide goes on
            self.labels = deque((r for r in self.labels if not (r.final and r.slide_id == msg.slide_id)), maxlen=LABEL_HISTORY)
            self.slide = msg
        elif isinstance(msg, Slide):
            self.slide = msg if msg.event == schema.SLIDE_START else None
        elif isinstance(msg, Roughness):
            self.labels.appendleft(msg)
        elif isinstance(msg, Samples):
            self._samples(msg)

    def check_stale(self, now: float | None = None) -> bool:
        """After :data:`STALE_AFTER_S` without a message: the state becomes "no data", the slide in progress is forgotten and
        :attr:`stale_s` says for how long nothing came (the rate and film levels are then shown blank). True if stale."""
        now = time.monotonic() if now is None else now
        if not self.last_message or now - self.last_message <= STALE_AFTER_S or self.status is None:
            return False
        self.status.state = NO_DATA
        self.slide = None
        self.stale_s = now - self.last_message
        return True

    def _samples(self, msg: Samples) -> None:
        volts = msg.counts().astype(np.float64) * msg.volts_per_count
        self.fs = msg.fs
        if len(self.traces) != msg.channels:
            self.traces = [deque(maxlen=TRACE_LEN) for _ in range(msg.channels)]
        step = max(1, round(msg.fs / 100))
        for lo in range(0, msg.n - step + 1, step):
            rms = np.sqrt(np.mean(volts[lo:lo + step] ** 2, axis=0))
            for k, trace in enumerate(self.traces):
                trace.append(float(rms[k]))
        self.raw.append(volts)
        self.raw_n += msg.n
        while self.raw_n - self.raw[0].shape[0] >= SPECTRUM_N:
            self.raw_n -= self.raw.popleft().shape[0]

    def spectrum(self, bars: int = 48, max_hz: float = 5000.0) -> tuple[np.ndarray, float]:
        """(dB per band (bars,) of film 1 + 2 summed power, Hz per band) of the newest SPECTRUM_N samples."""
        if self.raw_n < SPECTRUM_N or not self.fs:
            return np.zeros(0), 0.0
        x = np.concatenate(list(self.raw))[-SPECTRUM_N:]
        x = x - x.mean(axis=0)
        power = (np.abs(np.fft.rfft(x * np.hanning(SPECTRUM_N)[:, None], axis=0)) ** 2).sum(axis=1)
        freqs = np.fft.rfftfreq(SPECTRUM_N, 1 / self.fs)
        hi = min(max_hz, self.fs / 2)
        edges = np.linspace(0, hi, bars + 1)
        band = np.array([power[(freqs >= a) & (freqs < b)].sum() for a, b in itertools.pairwise(edges)])
        return 10 * np.log10(band + 1e-20), hi / bars

    def truth_for(self, start: int, stop: int) -> str | None:
        """The true surface of the logged slide that overlaps [start, stop) (sensor sample indices) most; None without a log or a match.

        The log is read again when it does not reach ``stop`` yet.
        """
        if self.truth_log is None:
            return None
        if not self._truth or self._truth[-1][1] < stop:
            self._truth = read_truth(self.truth_log)
        return overlapping(self._truth, start, stop)


def at_start(s: Status) -> str:
    """The bytes the daemon dropped when it first opened the port, in one line for either screen (shown when not 0)."""
    return f"discarded at start {s.discarded_at_start} bytes (stale: sent before the port was opened)"


def foreign_frames(s: Status) -> str:
    """The frames the daemon skipped for their channel count, in one line for either screen (shown when not 0: the board
    is not the one configured, and none of its samples is used)."""
    return f"{s.channel_errors} frames of another channel count skipped: check [sensor] channels"


def losses(s: Status, missed: int) -> str:
    """The loss counters that are always shown, in one line."""
    return f"lost {s.samples_lost} samples  crc errors {s.crc_errors}  bytes discarded {s.bytes_discarded}  reconnects {s.reconnects}  missed msgs {missed}"


def other_losses(s: Status) -> str:
    """The counters of rarer losses and faults, those not 0, in one line ("" when all are 0): board restarts, repeated
    frames dropped, messages the daemon's socket refused (a subscriber's own losses are its missed messages), samples not
    analysed (load shed), input dropped undecoded, bad headers."""
    parts = [f"{label} {value}" for label, value in (
        ("restarts", s.restarts), ("duplicate frames", s.duplicate_frames), ("dropped msgs", s.dropped_messages),
        ("overloaded", s.overloaded), ("input shed bytes", s.input_shed_bytes), ("bad headers", s.bad_headers)) if value]
    return "  ".join(parts)


def rate(model: MonitorState, s: Status, full: bool) -> str:
    """The board's rate as the daemon's clock map measures it (steady; until the map is ready, the samples counted over the
    last status interval, which swing with the hand-overs at rest), or a dash and how long nothing has come once the
    figures are stale."""
    if model.stale_s:
        return f"rate - (no data for {model.stale_s:.0f} s)" if full else "- Hz"
    steady = s.fs_clock if s.fs_clock > 0 else s.fs_measured
    return (f"rate {steady:.1f} Hz (last interval {s.fs_measured:.0f} Hz, nominal {s.fs_nominal:g} Hz)" if full
            else f"{steady:.0f} Hz")


def render(model: MonitorState, endpoint: str, width: int = 140, height: int = 50) -> Any:
    """The whole screen, for a terminal of ``width`` columns and ``height`` lines, as one rich renderable.

    From :data:`FULL_SIZE` up: state, counters, film traces, the spectrum and the labels with every column.
    Smaller (down to 80×24): state, loss counters, film levels and the last labels, each on one line.
    """
    if width < FULL_SIZE[0] or height < FULL_SIZE[1]:
        return render_compact(model, endpoint, width, height)
    from rich.console import Group
    from rich.panel import Panel
    from rich.table import Table
    from rich.text import Text

    s = model.status
    head = Text()
    head.append("tactiled monitor  ", style="bold")
    head.append(f"{endpoint}   (q quits)\n")
    if s is None:
        head.append("waiting for the daemon's status ...", style="yellow")
        return Panel(head)
    colour = {schema.STATE_DISCONNECTED: "bold red", schema.STATE_SLIDING: "bold green", NO_DATA: "bold red"}.get(s.state, "bold cyan")
    head.append(f"sensor {s.sensor}  ")
    head.append(f" {s.state.upper()} ", style=f"reverse {colour}")
    head.append(f"  uptime {s.uptime_s:.1f} s  model {s.model or '-'}  v{s.version}\n")
    head.append(f"{rate(model, s, True)}  samples {s.samples}  index {s.index}\n")
    head.append(losses(s, model.missed))
    if other_losses(s):
        head.append(f"\n{other_losses(s)}", style="yellow")
    if s.discarded_at_start:
        head.append(f"\n{at_start(s)}")
    if s.channel_errors:
        head.append(f"\n{foreign_frames(s)}", style="bold red")
    if model.slide is not None:
        head.append(f"\nSLIDING: slide {model.slide.slide_id} since sample {model.slide.start}", style="bold green")
    levels = Table(title="film levels (RMS per 10 ms, mV)", expand=True, title_justify="left")
    levels.add_column("film")
    levels.add_column("now, mV", justify="right")
    levels.add_column("max, mV", justify="right")
    levels.add_column("trace (newest right)", ratio=1)
    if model.traces:
        for k, trace in enumerate(model.traces):
            values = np.array(trace)
            top = max(float(values.max()), 1e-6)
            levels.add_row(f"film{k + 1}", "-" if model.stale_s else f"{values[-1] * 1e3:.2f}", f"{top * 1e3:.2f}", sparkline(values, top))
    else:
        for k, v in enumerate(s.level):
            levels.add_row(f"film{k + 1}", "-" if model.stale_s else f"{v * 1e3:.2f}", "", "(no samples topic: run the daemon with --samples)")
    db, hz = model.spectrum()
    spec = Text()
    if db.size:
        floor = float(db.max()) - 60
        rows = 6
        level = np.clip((db - floor) / 60 * rows * 8, 0, rows * 8)
        for row in range(rows - 1, -1, -1):
            spec.append("".join(" " if h <= row * 8 else SPARK[min(int(h - row * 8), 8) - 1] for h in level) + "\n", style="magenta")
        spec.append(f"0 Hz{'':{max(len(db) - 12, 1)}}{hz * len(db):.0f} Hz   ({hz:.0f} Hz per column, top {db.max():.0f} dB, 60 dB span)")
    else:
        spec.append("(waiting for raw samples)")
    labels = Table(title="last labels (newest first)", expand=True, title_justify="left")
    for col, just in (("slide", "right"), ("kind", "left"), ("label", "left"), ("confidence", "right"), ("used, s", "right"),
                      ("duration, s", "right"), ("latency, ms", "right"), ("truth", "left"),
                      ("abstained: reason", "left")):
        labels.add_column(col, justify=just)  # type: ignore[arg-type]
    fs = s.fs_nominal or 1.0
    for r in itertools.islice(model.labels, max(height - 35 - bool(s.discarded_at_start), 5)):
        truth = model.truth_for(r.start, r.stop)
        style = "bold red" if r.label is None else ("dim" if not r.final else ("green" if truth in (None, r.label) else "yellow"))
        labels.add_row(str(r.slide_id), "final" if r.final else "provisional", r.label or "-",
                       "" if r.confidence is None else f"{r.confidence:.2f}", f"{r.used_s:.2f}", f"{(r.stop - r.start) / fs:.2f}",
                       f"{r.latency_ms:.1f}", truth or "", r.reason or "", style=style)
    return Group(Panel(head), levels, Panel(spec, title="spectrum of the raw samples (films summed)", title_align="left"), labels)


def render_compact(model: MonitorState, endpoint: str, width: int, height: int) -> Any:
    """The screen for a small terminal (80×24 and up): nothing wraps, the labels take the lines left."""
    from rich import box
    from rich.console import Group
    from rich.table import Table
    from rich.text import Text

    def line(text: Text) -> Text:
        text.no_wrap, text.overflow = True, "ellipsis"
        return text

    s = model.status
    title = line(Text.assemble(("tactiled monitor ", "bold"), f"{endpoint} (q quits)"))
    if s is None:
        return Group(title, line(Text("waiting for the daemon's status ...", style="yellow")))
    colour = {schema.STATE_DISCONNECTED: "bold red", schema.STATE_SLIDING: "bold green", NO_DATA: "bold red"}.get(s.state, "bold cyan")
    sliding = f"  slide {model.slide.slide_id} since {model.slide.start}" if model.slide is not None else ""
    state = line(Text.assemble(f"{s.sensor} ", (f" {s.state.upper()} ", f"reverse {colour}"),
                               f"{sliding}  up {s.uptime_s:.0f} s  {rate(model, s, False)}  model {s.model or '-'}"))
    counters = [line(Text(f"lost {s.samples_lost}  crc {s.crc_errors}  discarded {s.bytes_discarded}  reconnects {s.reconnects}  "
                          f"missed msgs {model.missed}  samples {s.samples}"))]
    if other_losses(s):
        counters.append(line(Text(other_losses(s), style="yellow")))
    if s.discarded_at_start:
        counters.append(line(Text(at_start(s))))
    if s.channel_errors:
        counters.append(line(Text(foreign_frames(s), style="bold red")))
    levels = [line(Text("film levels, mV RMS per 10 ms (now, max, trace)", style="bold"))]
    if model.traces:
        for k, trace in enumerate(model.traces):
            values = np.array(trace)
            top = max(float(values.max()), 1e-6)
            head = f"film{k + 1} {'-' if model.stale_s else format(values[-1] * 1e3, '7.2f'):>7} {top * 1e3:7.2f} "
            levels.append(line(Text(head + sparkline(values[-max(width - len(head) - 1, 0):], top))))
    else:
        levels.append(line(Text("  ".join(f"film{k + 1} {'-' if model.stale_s else format(v * 1e3, '.2f')}" for k, v in enumerate(s.level))
                                + "  (traces: run the daemon with --samples)")))
    labels = Table(box=box.SIMPLE_HEAD, expand=True, show_edge=False, pad_edge=False, title="last labels (newest first)",
                   title_justify="left", title_style="bold")
    for col, just in (("slide", "right"), ("kind", "left"), ("label", "left"), ("conf", "right"), ("truth", "left"), ("reason", "left")):
        labels.add_column(col, justify=just, no_wrap=True, overflow="ellipsis")  # type: ignore[arg-type]
    rows = max(height - 3 - len(counters) - len(levels) - 4, 1)  # title, state, counters, levels, the table's title, header, rule, a spare line
    for r in itertools.islice(model.labels, rows):
        truth = model.truth_for(r.start, r.stop)
        style = "bold red" if r.label is None else ("dim" if not r.final else ("green" if truth in (None, r.label) else "yellow"))
        labels.add_row(str(r.slide_id), "final" if r.final else "prov.", r.label or "-", "" if r.confidence is None else f"{r.confidence:.2f}",
                       truth or "", r.reason or "", style=style)
    return Group(title, state, *counters, *levels, labels)


def run_monitor(endpoint: str, truth_log: str | None = None, running: Callable[[], bool] = lambda: True,
                curve: tuple[str, str] | None = None) -> int:
    """Show the live view of the daemon at ``endpoint`` (redrawn every 0.1 s; ``curve``: its CURVE certificates, as a
    subscriber takes them) until ``q`` or Ctrl-C (exit code 0) or ``running()`` False (the demo's own daemon stopped: 1)."""
    from rich.live import Live

    model = MonitorState(truth_log)
    sub = BlockingSubscriber(endpoint, curve=curve)  # an endpoint no subscriber can connect to is refused before (tactiled.cli.cmd_live)
    tty = sys.stdin.isatty()
    old = None
    if tty:
        import termios
        import tty as ttymod

        old = termios.tcgetattr(sys.stdin)
        ttymod.setcbreak(sys.stdin.fileno())
    try:
        with sub, Live(render(model, endpoint), auto_refresh=False, screen=True) as live:
            while True:
                deadline = time.monotonic() + 0.1  # redraw period
                try:
                    while time.monotonic() < deadline:
                        model.update(sub.receive(timeout=max(deadline - time.monotonic(), 0.0)))
                except NoData:
                    pass
                model.check_stale()
                size = live.console.size
                live.update(render(model, endpoint, size.width, size.height), refresh=True)
                if tty and select.select([sys.stdin], [], [], 0)[0] and os.read(sys.stdin.fileno(), 1) in (b"q", b"Q"):
                    return 0
                if not running():
                    return 1
    except KeyboardInterrupt:
        return 0
    finally:
        if old is not None:
            import termios

            with contextlib.suppress(termios.error, OSError):  # the terminal may be gone (closed: SIGHUP)
                termios.tcsetattr(sys.stdin, termios.TCSADRAIN, old)
