"""A virtual sensor board: the simulator's samples as frames on a pseudo-terminal.

It opens a pty, keeps an optional symlink pointing at it, and streams frames per
docs/sensor-frames.md in real time (or ``speed`` times faster). It can corrupt,
drop and garble frames, unplug (remove the symlink and close the pty, keep sampling, then open a new pty
and point the symlink at it: the index goes on, so the samples of the unplug are a gap) and reset (the
index starts again at ``reset_to``, as a board that restarted). With a log it writes one JSON
line per event (slides scheduled, frames dropped or corrupted, garbage, unplugs with the bytes
the reader had not taken yet, resets) so tests can check what arrived; frames the pty would not take
(nothing reading the port) are summed up in one ``overrun`` line per second at most, so the log stays bounded
(:func:`read_log` gives them back one event per frame).
"""

from __future__ import annotations

import json
import os
import threading
import time
import tty
from collections import deque
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from tactiled.board.frames import encode_frame
from tactiled.sim.physics import SensorSimulator, Surface

_TAKEN_KEPT = 1 << 18  # bytes of what the pty took kept to find the bytes stranded at an unplug among them


class VirtualBoard:
    """Streams ``model`` over a pty; :meth:`run` until ``stop`` is set or ``seconds`` of sensor time."""

    def __init__(self, model: SensorSimulator, surfaces: Sequence[Surface], *, link: str | None = None,
                 speed: float = 1.0, corrupt: float = 0.0, drop: float = 0.0, garbage: float = 0.0,
                 unplug_at: Sequence[float] = (), unplug_s: float = 0.3, frame_count: int = 20,
                 seed: int = 0, log: TextIO | None = None, first_index: int = 0, reset_at: Sequence[float] = (),
                 reset_to: int = 0) -> None:
        if speed <= 0:
            raise ValueError("speed must be > 0")
        for name, value in (("corrupt", corrupt), ("drop", drop), ("garbage", garbage)):
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be a probability in [0, 1], got {value}")
        self.model = model
        self.surfaces = list(surfaces)
        self.link = link
        self.speed = speed
        self.corrupt, self.drop, self.garbage = corrupt, drop, garbage
        self.unplug_at = sorted(unplug_at)
        self.unplug_s = unplug_s
        self.frame_count = frame_count
        self.first_index = first_index
        self.reset_at = sorted(reset_at)  # sensor times (s of samples sent) at which the board's index starts again at reset_to
        self.reset_to = reset_to
        self._shift = 0  # what resets moved the index by: the next frame's index is first_index + sent_samples + _shift
        self.rng = np.random.default_rng(seed + 0x5EED)
        self.log = log
        self.path = ""
        self.sent_samples = 0
        self._master = -1
        self._slave = -1
        self._logged_slides = 0
        self._overruns: list[list[int]] = []  # [first frame index, frames] not taken by the pty since _overrun_t0
        self._overrun_bytes = 0
        self._overrun_t0 = 0.0
        self._taken = bytearray()  # the last bytes this pty took (at most ~2 _TAKEN_KEPT), to find the stranded ones among them
        self._taken_at = 0  # the offset in the pty's stream of _taken[0]
        self._whole: deque[tuple[int, int]] = deque()  # (start, end) in that stream of the whole frames it took
        self.ready = threading.Event()
        self._progress = threading.Condition()

    def wait_sent(self, samples: int, timeout: float) -> bool:
        """Block until at least ``samples`` have been sent (True) or ``timeout`` s pass (False)."""
        with self._progress:
            return self._progress.wait_for(lambda: self.sent_samples >= samples, timeout)

    def _event(self, event: str, **fields: Any) -> None:
        if self.log is not None:
            self.log.write(json.dumps({"event": event, **fields}) + "\n")
            self.log.flush()

    def _overrun(self, index: int, lost: int) -> None:
        """Note a frame at ``index`` the pty would not take (``lost`` bytes): one log line per second sums them up."""
        if not self._overruns:
            self._overrun_t0 = time.monotonic()
        last = self._overruns[-1] if self._overruns else None
        if last is not None and last[0] + last[1] * self.frame_count == index:
            last[1] += 1
        else:
            self._overruns.append([index, 1])
        self._overrun_bytes += lost

    def _flush_overruns(self, force: bool = False) -> None:
        """Write the overruns noted so far as one line, once a second has passed since the first (or ``force``)."""
        if self._overruns and (force or time.monotonic() - self._overrun_t0 >= 1.0):
            self._event("overrun", index=self._overruns[0][0], ranges=self._overruns, frame_samples=self.frame_count,
                        bytes=self._overrun_bytes)
            self._overruns, self._overrun_bytes = [], 0

    def open(self) -> str:
        """Open a new pty (raw, non-blocking master), point the link at it; returns its path."""
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self._taken, self._taken_at, self._whole = bytearray(), 0, deque()
        self.path = os.ttyname(slave)
        if self.link:
            tmp = f"{self.link}.tmp{os.getpid()}"
            if os.path.lexists(tmp):
                os.unlink(tmp)
            os.symlink(self.path, tmp)
            os.replace(tmp, self.link)
        self._event("open", path=self.path, index=self.first_index + self.sent_samples + self._shift)
        return self.path

    def _strand(self) -> tuple[int, int]:
        """At an unplug: the bytes written to the pty that its reader has not taken, read off the board's own end of it so that
        they are gone, as a hung-up tty's are; returns how many, and how many whole frames the pty took lose bytes to them
        ((0, 0) if the pty is closed).

        Reading counts them exactly: FIONREAD sees only the line discipline's buffer, not what still waits in the tty's flip
        buffers (up to 64 kB), while a read that finds nothing waits for those to be flushed first.
        """
        if self._slave < 0:
            return 0, 0
        os.set_blocking(self._slave, False)  # the board's own open file: the reader's is another
        chunks: list[bytes] = []
        while True:
            try:
                chunk = os.read(self._slave, 1 << 16)
            except OSError:  # EAGAIN: nothing left
                break
            if not chunk:
                break
            chunks.append(chunk)
        return sum(map(len, chunks)), self._frames_hit(chunks)

    def _frames_hit(self, chunks: list[bytes]) -> int:
        """The whole frames the pty took that lose a byte to ``chunks`` (read off it in this order): those its reader cannot decode.

        Not the bytes over the frame size: the reader goes on reading between two of these reads (a tty hands out at most its
        4 kB line buffer per read), so it may take a piece out of the middle, and a piece that holds no whole frame leaves two
        frames cut, one more than the bytes say (seen under load: the daemon counted one frame more lost than that). So each
        read is found in the bytes the pty took, the last one last: only what the reader took after a read lies between it and
        where it is found.
        """
        hit: set[int] = set()
        at = len(self._taken)  # in _taken: where the read after this one was found
        for chunk in reversed(chunks):
            at = self._taken.rfind(chunk, 0, at)
            if at < 0:
                raise RuntimeError(f"bytes read off the pty at an unplug are not among those it took ({len(chunk)} bytes)")
            start = self._taken_at + at
            end = start + len(chunk)
            hit.update(k for k, (a, b) in enumerate(self._whole) if a < end and b > start)
        return len(hit)

    def _took(self, data: bytes, frame_bytes: int) -> None:
        """Keep the bytes the pty took (``data``) for :meth:`_frames_hit`; they end with an intact frame ``frame_bytes`` long
        (after any garbage), unless that is 0: a frame the pty took only part of (an overrun) or corrupted, logged as such."""
        end = self._taken_at + len(self._taken) + len(data)
        if frame_bytes:
            self._whole.append((end - frame_bytes, end))
        self._taken += data
        if len(self._taken) > 2 * _TAKEN_KEPT:  # far more than a pty holds (its 4 kB line buffer and 64 kB of flip buffers)
            drop = len(self._taken) - _TAKEN_KEPT
            del self._taken[:drop]
            self._taken_at += drop
            while self._whole and self._whole[0][0] < self._taken_at:
                self._whole.popleft()

    def close(self) -> None:
        """Close the pty (the link stays; an unplug removes it first, :meth:`run`)."""
        for fd in (self._master, self._slave):
            if fd >= 0:
                os.close(fd)
        self._master = self._slave = -1

    def remove_link(self) -> None:
        """Remove the symlink if it still points at this board's pty (so it never names a pty another program gets next)."""
        if self.link and os.path.islink(self.link) and os.readlink(self.link) == self.path:
            os.unlink(self.link)

    def _log_slides(self) -> None:
        for truth in self.model.truth[self._logged_slides:]:
            self._event("slide", start=self.first_index + truth.start, stop=self.first_index + truth.stop,
                        surface=truth.surface.name, ra_um=truth.surface.ra_um)
        self._logged_slides = len(self.model.truth)

    def _write(self, data: bytes, index: int, frame_bytes: int) -> None:
        try:
            written = os.write(self._master, data)
        except BlockingIOError:
            written = 0
        except OSError:
            written = 0
        if written:
            self._took(data[:written], frame_bytes if written == len(data) else 0)
        if written < len(data):
            self._overrun(index, len(data) - written)
        self._flush_overruns()

    def run(self, stop: threading.Event, seconds: float | None = None) -> None:
        """Stream until ``stop`` is set (or ``seconds`` of sensor time have been sent)."""
        fs = self.model.p.fs
        n = self.frame_count
        total = None if seconds is None else round(seconds * fs)
        unplugs = [round(t * fs) for t in self.unplug_at]
        resets = [round(t * fs) for t in self.reset_at]
        if self._master < 0:
            self.open()
        self.ready.set()
        t0 = time.monotonic()
        down_until = -1
        while not stop.is_set() and (total is None or self.sent_samples < total):
            due = int((time.monotonic() - t0) * fs * self.speed)
            if total is not None:
                due = min(due, total)
            if due - self.sent_samples < n:
                time.sleep(min(0.005, n / fs / self.speed))  # pacing the stream, not synchronisation
                continue
            while self.sent_samples + n <= due and not stop.is_set():
                self.model.schedule_random(self.surfaces, self.model.position + 10 * n)
                self._log_slides()
                block = self.model.read(n)
                if resets and self.sent_samples >= resets[0]:
                    resets.pop(0)
                    self._flush_overruns(force=True)  # the overruns logged before a reset are of the old indices, those after of the new
                    self._event("reset", index=self.first_index + self.sent_samples + self._shift, to=self.reset_to)
                    self._shift = self.reset_to - self.first_index - self.sent_samples
                index = self.first_index + self.sent_samples + self._shift
                self.sent_samples += n
                if unplugs and self.sent_samples >= unplugs[0]:
                    unplugs.pop(0)
                    self._flush_overruns(force=True)
                    unread, unread_frames = self._strand()  # the frames still queued are lost with the pty
                    self._event("unplug", index=index, unread=unread, unread_frames=unread_frames)
                    # the link goes first, as udev removes /dev/serial/by-id/ links: once the pty is closed its number is free, and a
                    # link left pointing at it names the next pty anyone opens (another board's), which the reader would then read
                    self.remove_link()
                    self.close()
                    down_until = self.sent_samples + round(self.unplug_s * fs)
                if down_until >= 0:
                    if self.sent_samples < down_until:
                        continue
                    down_until = -1
                    self.open()
                    continue
                if self.rng.random() < self.drop:
                    self._event("drop", index=index, count=n)
                    continue
                frame = bytearray(encode_frame(index, block))
                frame_bytes = len(frame)
                if self.rng.random() < self.corrupt:
                    at = int(self.rng.integers(2, len(frame)))
                    frame[at] ^= int(self.rng.integers(1, 256))
                    frame_bytes = 0  # not a frame any reader decodes: logged as corrupt, not as stranded
                    self._event("corrupt", index=index, count=n)
                if self.rng.random() < self.garbage:
                    junk = self.rng.integers(0, 256, int(self.rng.integers(1, 40)), dtype=np.uint8).tobytes()
                    self._event("garbage", index=index, bytes=len(junk))
                    frame = bytearray(junk) + frame
                self._write(bytes(frame), index, frame_bytes)
                with self._progress:
                    self._progress.notify_all()
        self._flush_overruns(force=True)
        self._event("end", index=self.first_index + self.sent_samples + self._shift)


def read_log(path: str | Path) -> list[dict[str, Any]]:
    """The events of a virtual board's log file; an overrun line (up to a second of frames the pty would not take,
    as ``ranges`` of [first frame index, frames]) becomes one ``overrun`` event per frame (``index``, ``count``)."""
    out: list[dict[str, Any]] = []
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            if not line.strip():
                continue
            event = json.loads(line)
            if event.get("event") == "overrun" and "ranges" in event:
                n = int(event["frame_samples"])
                out += [{"event": "overrun", "index": first + k * n, "count": n} for first, frames in event["ranges"] for k in range(frames)]
            else:
                out.append(event)
    return out
