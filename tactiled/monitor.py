"""``tactiled monitor``: a terminal view of a running daemon (curses).

State, both films' live level, the slide in progress, the last labels with confidence,
rates and loss counters. ``q`` quits.
"""

from __future__ import annotations

import curses
import time
from collections import deque
from typing import Any

from tactiled_client import BlockingSubscriber, NoData, Roughness, Slide, Status


class MonitorModel:
    """What the screen shows, updated from messages (kept apart from drawing, for tests)."""

    def __init__(self) -> None:
        self.status: Status | None = None
        self.slide: Slide | None = None
        self.labels: deque[Roughness] = deque(maxlen=12)
        self.missed = 0
        self.last_message = 0.0

    def update(self, msg: Any) -> None:
        self.last_message = time.monotonic()
        self.missed += msg.missed
        if isinstance(msg, Status):
            self.status = msg
        elif isinstance(msg, Slide):
            self.slide = msg if msg.event == "start" else None
        elif isinstance(msg, Roughness):
            self.labels.appendleft(msg)

    def lines(self, endpoint: str, width: int = 80) -> list[str]:
        s = self.status
        out = [f"tactiled monitor  {endpoint}  (q quits)"]
        if s is None:
            out.append("waiting for the daemon's status ...")
            return out
        out.append(f"sensor {s.sensor}  state {s.state.upper():12s} uptime {s.uptime_s:8.1f} s  model {s.model or '-'}")
        out.append(f"rate {s.fs_measured:9.1f} Hz (nominal {s.fs_nominal:g})  samples {s.samples}  index {s.index}")
        out.append(f"lost {s.samples_lost} samples  crc errors {s.crc_errors}  bytes discarded {s.bytes_discarded}  "
                   f"reconnects {s.reconnects}  missed msgs {self.missed}")
        out.append(f"slides {s.slides}  labels {s.labels}")
        for k, v in enumerate(s.level):
            bar = "#" * min(40, int(40 * min(v, 1.0) ** 0.5))
            out.append(f"film{k + 1} {v * 1e3:8.1f} mV rms |{bar:<40s}|")
        if self.slide is not None:
            out.append(f"SLIDING: slide {self.slide.slide_id} since sample {self.slide.start}")
        else:
            out.append("")
        out.append("last labels:")
        for r in self.labels:
            label = r.label if r.label is not None else f"- ({r.reason})"
            conf = "" if r.confidence is None else f"{r.confidence:5.2f}"
            out.append(f"  slide {r.slide_id:4d}  {label:24s} {conf:5s}  {(r.stop - r.start) / max(s.fs_nominal, 1):5.2f} s  "
                       f"latency {r.latency_ms:6.2f} ms")
        return [line[: width - 1] for line in out]


def run_monitor(endpoint: str) -> int:
    model = MonitorModel()
    with BlockingSubscriber(endpoint, timeout=0.2) as sub:

        def loop(screen: Any) -> None:
            curses.curs_set(0)
            screen.nodelay(True)
            while True:
                try:
                    while True:
                        model.update(sub.receive(timeout=0.0 if model.last_message else 0.2))
                except NoData:
                    pass
                if model.last_message and time.monotonic() - model.last_message > 3 and model.status is not None:
                    model.status.state = "no data"
                height, width = screen.getmaxyx()
                screen.erase()
                for y, line in enumerate(model.lines(endpoint, width)[: height - 1]):
                    screen.addstr(y, 0, line)
                screen.refresh()
                if screen.getch() in (ord("q"), ord("Q")):
                    return
                curses.napms(100)  # redraw period

        curses.wrapper(loop)
    return 0
