"""``tactiled record``: serial frames → a recording file, with every lost sample listed."""

from __future__ import annotations

import logging
import queue
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from tactiled.frames import Frame, FrameDecoder
from tactiled.recording import Recording, save_recording
from tactiled.serialsource import DISCONNECTED, SerialSource, check_port

log = logging.getLogger(__name__)


class FrameAssembler:
    """Collects decoded frames into one contiguous (n, C) int16 array with a ``lost`` list.

    Positions stay equal to sensor time: an index gap becomes zero rows listed in ``lost``.
    """

    def __init__(self, channels: int, limit: int | None = None) -> None:
        self.channels = channels
        self.limit = limit
        self.first_index: int | None = None
        self.restarts = 0
        self._chunks: list[npt.NDArray[np.int16]] = []
        self._lost: list[tuple[int, int]] = []
        self._n = 0

    @property
    def n(self) -> int:
        return self._n

    @property
    def done(self) -> bool:
        return self.limit is not None and self._n >= self.limit

    def add(self, frame: Frame) -> None:
        if self.done:
            return
        if frame.samples.shape[1] != self.channels:
            log.warning("frame at %d has %d channels, expected %d: skipped", frame.index, frame.samples.shape[1], self.channels)
            return
        if self.first_index is None:
            self.first_index = frame.index
        self.restarts += frame.restart
        gap = frame.index - (self.first_index + self._n)
        if gap > 0:
            self._append(np.zeros((gap, self.channels), dtype=np.int16), lost=True)
        self._append(frame.samples, lost=False)

    def _append(self, block: npt.NDArray[np.int16], lost: bool) -> None:
        if self.limit is not None:
            block = block[: self.limit - self._n]
        if not block.shape[0]:
            return
        if lost:
            self._lost.append((self._n, block.shape[0]))
        self._chunks.append(block)
        self._n += block.shape[0]

    def samples(self) -> npt.NDArray[np.int16]:
        if not self._chunks:
            return np.zeros((0, self.channels), dtype=np.int16)
        return np.concatenate(self._chunks).astype(np.int16, copy=False)

    def lost(self) -> npt.NDArray[np.int64]:
        return np.asarray(self._lost, dtype=np.int64).reshape(-1, 2)


@dataclass
class RecordSummary:
    seconds: float
    samples: int
    samples_lost: int
    crc_errors: int
    reconnects: int

    def line(self) -> str:
        return (f"recorded {self.seconds:.3f} s: {self.samples} samples, {self.samples_lost} lost, "
                f"{self.crc_errors} CRC failures, {self.reconnects} reconnects")


def record(port: str, seconds: float, out: str | Path, *, fs: float, channels: int, volts_per_count: float,
           label: str | None = None, baudrate: int = 1_000_000, retry_max_s: float = 2.0,
           meta: dict[str, Any] | None = None) -> RecordSummary:
    """Record ``seconds`` of sensor time from ``port`` into ``out``; Ctrl-C or SIGTERM stops early and saves."""
    check_port(port)
    chunks: queue.Queue[bytes | None] = queue.Queue()
    decoder = FrameDecoder()
    assembler = FrameAssembler(channels, limit=max(1, round(seconds * fs)))

    def on_state(state: str, detail: str) -> None:
        if state == DISCONNECTED:
            log.warning("%s: %s", port, detail)

    source = SerialSource(port, chunks.put, on_state, baudrate=baudrate, retry_max_s=retry_max_s)
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    source.start()
    log.info("recording %s -> %s (Ctrl-C stops and saves)", port, out)
    try:
        while not assembler.done:
            try:
                data = chunks.get(timeout=0.2)
            except queue.Empty:
                continue
            if data:
                for frame in decoder.feed(data):
                    assembler.add(frame)
    except KeyboardInterrupt:
        log.info("interrupted: saving what was captured")
    finally:
        source.stop()
        signal.signal(signal.SIGTERM, previous)
    while not chunks.empty():
        data = chunks.get_nowait()
        for frame in decoder.feed(data or b""):
            assembler.add(frame)
    for frame in decoder.flush():
        assembler.add(frame)
    lost = assembler.lost()
    info = dict(meta or {})
    info.update({"port": port, "recorded_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "restarts": assembler.restarts,
                 "crc_errors": decoder.stats.crc_errors, "bytes_discarded": decoder.stats.bytes_discarded,
                 "reconnects": source.reconnects})
    rec = Recording(samples=assembler.samples(), fs=fs, volts_per_count=volts_per_count, label=label, meta=info,
                    first_index=assembler.first_index or 0, lost=lost)
    save_recording(out, rec)
    return RecordSummary(assembler.n / fs, assembler.n, int(lost[:, 1].sum()), decoder.stats.crc_errors, source.reconnects)
