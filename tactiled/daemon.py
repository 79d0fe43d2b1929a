"""``tactiled run``: one asyncio daemon per sensor.

Tasks in one TaskGroup: ``ingest`` (serial bytes → decoder → pipeline → publisher; blocks
that complete an analysis window run in a worker thread so feature extraction never
stalls the loop, detection-only blocks run inline, cheaper than a thread hop), ``status`` (at
least once a second, and the systemd watchdog), ``stop`` (SIGTERM, SIGINT, SIGHUP). The serial
source is a reader thread (tactiled.serialsource) that survives unplugs.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import socket
import time
from dataclasses import dataclass, field

import numpy as np
from tactiled_client import schema

from tactiled import __version__
from tactiled.clockmap import ClockMap
from tactiled.config import Config
from tactiled.frames import FrameDecoder
from tactiled.model import Model
from tactiled.pipeline import Pipeline, PipelineEvent
from tactiled.publish import Publisher
from tactiled.rawbatch import raw_batches
from tactiled.record import RecordingSink
from tactiled.serialsource import CONNECTED, SerialSource

log = logging.getLogger(__name__)


def sd_notify(message: str) -> None:
    """Send ``message`` to systemd's notify socket if there is one (Type=notify, watchdog)."""
    path = os.environ.get("NOTIFY_SOCKET")
    if not path:
        return
    if path.startswith("@"):
        path = "\0" + path[1:]
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        try:
            sock.connect(path)
            sock.sendall(message.encode())
        except OSError as exc:
            log.warning("sd_notify failed: %s", exc)


PROCESS_S = 0.04  # the pipeline runs on batches of at least this much sensor time, s


def group_blocks(items: list[tuple[int, np.ndarray]]) -> list[tuple[int, np.ndarray]]:
    """Consecutive (index, (n, C) samples) items joined into as few blocks as possible."""
    blocks: list[tuple[int, list[np.ndarray]]] = []
    end = None
    for index, samples in items:
        if blocks and index == end and samples.shape[1] == blocks[-1][1][0].shape[1]:
            blocks[-1][1].append(samples)
        else:
            blocks.append((index, [samples]))
        end = index + samples.shape[0]
    return [(i, np.concatenate(parts) if len(parts) > 1 else parts[0]) for i, parts in blocks]



@dataclass
class DaemonState:
    started: float = field(default_factory=time.monotonic)
    connected: bool = False
    samples_window: int = 0
    sumsq: np.ndarray | None = None
    last_index: int = 0
    channel_errors: int = 0


class Daemon:
    """The daemon's state and tasks; :meth:`run` until stopped."""

    def __init__(self, config: Config, model: Model | None, record_to: str | None = None) -> None:
        self.config = config
        self.model = model
        s = config.sensor
        self.fingerprint = model.fingerprint if model else ""
        self.decoder = FrameDecoder()
        self.pipeline = Pipeline(config, s.fs, s.channels, s.volts_per_count, True, model)
        self.publisher = Publisher(config.publish)
        self.state = DaemonState()
        self.stop_event = asyncio.Event()
        self.source: SerialSource | None = None
        self.record_to = record_to
        self._backlog: list[tuple[int, np.ndarray]] = []
        self._backlog_n = 0
        self._process_n = round(PROCESS_S * s.fs)
        self.recorder = RecordingSink(record_to, fs=s.fs, channels=s.channels, volts_per_count=s.volts_per_count, force=True,
                                      meta={"sensor": s.id, "port": s.port, "source": "tactiled run --record"}, counters=self._record_counters,
                                      on_error=log.error) if record_to else None  # streams to record_to's journal (tactiled/journal.py)
        self.clock = ClockMap(s.fs)  # sample index -> host time
        self._arrival = 0.0  # host monotonic time of the newest bytes read (reader thread)
        self._raw_next: int | None = None  # next index of the samples topic

    @property
    def endpoint(self) -> str:
        return self.publisher.endpoint

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        queue: asyncio.Queue[bytes | tuple[str, str]] = asyncio.Queue()
        s = self.config.sensor

        def on_bytes(data: bytes) -> None:
            self._arrival = time.monotonic()  # every sample queued so far had arrived by then
            loop.call_soon_threadsafe(queue.put_nowait, data)

        def on_state(state: str, detail: str) -> None:
            loop.call_soon_threadsafe(queue.put_nowait, (state, detail))

        self.source = SerialSource(s.port, on_bytes, on_state, baudrate=s.baudrate,
                                   retry_initial_s=self.config.serial.retry_initial_s, retry_max_s=self.config.serial.retry_max_s,
                                   read_interval_s=self.config.serial.read_interval_s)
        for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
            loop.add_signal_handler(sig, self.stop_event.set)
        self.source.start()
        log.info("tactiled %s: sensor %s on %s, publishing on %s, model %s", __version__, s.id, s.port, self.endpoint, self.fingerprint or "none")
        sd_notify("READY=1")
        try:
            async with asyncio.TaskGroup() as tg:
                ingest = tg.create_task(self._ingest(queue), name="ingest")
                status = tg.create_task(self._status(), name="status")
                await self.stop_event.wait()
                ingest.cancel()
                status.cancel()
        finally:
            sd_notify("STOPPING=1")
            self.source.stop()
            self.publisher.publish(self._status_message(stopping=True))
            self.publisher.close()
            if self.recorder is not None:
                self._save_recording()
            for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
                loop.remove_signal_handler(sig)

    async def _ingest(self, queue: asyncio.Queue[bytes | tuple[str, str]]) -> None:
        sensor = self.config.sensor
        while True:
            item = await queue.get()
            chunks = [item]
            while not queue.empty():
                chunks.append(queue.get_nowait())
            data = bytearray()
            arrival = self._arrival
            for chunk in chunks:
                if isinstance(chunk, tuple):
                    self.state.connected = chunk[0] == CONNECTED
                    log.log(logging.INFO if self.state.connected else logging.WARNING, "%s: %s (%s)", sensor.port, chunk[0], chunk[1])
                else:
                    data += chunk
            if not data:
                continue
            frames = self.decoder.feed(bytes(data))
            if frames:
                self.clock.observe(frames[-1].index + frames[-1].samples.shape[0], arrival)
            if self.recorder is not None:
                for frame in frames:
                    self.recorder.add(frame)
            for frame in frames:
                if frame.samples.shape[1] != sensor.channels:
                    self.state.channel_errors += 1
                    continue
                self._backlog.append((frame.index, frame.samples))
                self._backlog_n += frame.samples.shape[0]
            # the port is read every serial.read_interval_s (the tty buffer is small); the pipeline
            # runs on batches of at least PROCESS_S of samples: half the CPU of per-read processing
            if self._backlog_n >= self._process_n:
                blocks, self._backlog, self._backlog_n = group_blocks(self._backlog), [], 0
                for index, samples in blocks:
                    sq = np.einsum("ij,ij->j", samples, samples, dtype=np.float64)
                    self.state.sumsq = sq if self.state.sumsq is None else self.state.sumsq + sq
                    self.state.samples_window += samples.shape[0]
                    self.state.last_index = index + samples.shape[0]
                detected_at = time.perf_counter()
                if self.config.publish.samples:
                    self._publish_samples(blocks)
                end = blocks[-1][0] + blocks[-1][1].shape[0]
                if self.pipeline.will_analyse(end):  # feature extraction: off the event loop
                    events = await asyncio.to_thread(self._feed_blocks, blocks)
                else:  # detection only: cheaper than a thread hop
                    events = self._feed_blocks(blocks)
                to_host = self.clock.host if self.clock.ready else None
                for ev in events:
                    self.publisher.publish_event(sensor.id, ev, sensor.fs, self.fingerprint, detected_at, to_host)

    def _publish_samples(self, blocks: list[tuple[int, np.ndarray]]) -> None:
        """The batch's raw samples on ``samples/<id>``: every index from the last batch's end on, lost ones as zero rows."""
        s = self.config.sensor
        to_host = self.clock.host if self.clock.ready else None
        for b in raw_batches(blocks, self._raw_next, max_fill=round(s.fs)):
            n = b.samples.shape[0]
            self.publisher.publish(schema.samples(s.id, b.index, b.samples.astype("<i2", copy=False).tobytes(), n, s.channels, fs=s.fs,
                                                  volts_per_count=s.volts_per_count, lost=b.lost, lost_before=b.lost_before,
                                                  to_host=to_host, fs_clock=round(self.clock.fs, 3)))
            self._raw_next = b.index + n

    def _record_counters(self) -> dict[str, int]:
        st = self.decoder.stats
        return {"crc_errors": st.crc_errors, "bytes_discarded": st.bytes_discarded, "reconnects": self.source.reconnects if self.source else 0}

    def _save_recording(self) -> None:
        assert self.recorder is not None
        result = self.recorder.finish(self._record_counters())
        if result.error is None:
            log.info("%s: saved %d samples (%d lost)", self.recorder.out, result.samples, result.samples_lost)
        elif not self.recorder.error:  # a failure while capturing was logged when it happened
            log.error("%s", result.error)

    def _feed_blocks(self, blocks: list[tuple[int, np.ndarray]]) -> list[PipelineEvent]:
        events: list[PipelineEvent] = []
        for index, samples in blocks:
            events += self.pipeline.feed(index, samples)
        return events

    def _status_message(self, interval: float = 0.0, stopping: bool = False) -> schema.Status:
        st, stats = self.state, self.decoder.stats
        if stopping:
            state = schema.STATE_STOPPING
        elif not (self.source and self.source.connected):
            state = schema.STATE_DISCONNECTED
        elif self.pipeline.sliding:
            state = schema.STATE_SLIDING
        elif st.samples_window == 0:
            state = schema.STATE_CONNECTED
        else:
            state = schema.STATE_IDLE
        level = []
        if st.sumsq is not None and st.samples_window:
            level = [round(float(np.sqrt(v / st.samples_window)) * self.config.sensor.volts_per_count, 6) for v in st.sumsq]
        clock_index = clock_mono = clock_unix = None
        if self.clock.ready and st.last_index:
            clock_index = st.last_index
            clock_mono, clock_unix = (round(t, 6) for t in self.clock.host(clock_index))
        return schema.status(self.config.sensor.id, state=state, samples=stats.samples, samples_lost=stats.samples_lost, crc_errors=stats.crc_errors,
                             bytes_discarded=stats.bytes_discarded, bad_headers=stats.bad_headers,
                             reconnects=self.source.reconnects if self.source else 0, restarts=stats.restarts,
                             slides=self.pipeline.slides, labels=self.pipeline.labels, fs_nominal=self.config.sensor.fs,
                             fs_measured=round(st.samples_window / interval, 1) if interval > 0 else 0.0, model=self.fingerprint,
                             uptime_s=round(time.monotonic() - st.started, 3), index=st.last_index, level=level, version=__version__,
                             dropped_messages=self.publisher.dropped, channel_errors=st.channel_errors, clock_index=clock_index,
                             clock_mono=clock_mono, clock_unix=clock_unix, fs_clock=round(self.clock.fs, 3))

    async def _status(self) -> None:
        interval = self.config.publish.status_interval_s
        last = time.monotonic()
        watchdog = "WATCHDOG_USEC" in os.environ
        while True:
            await asyncio.sleep(interval)  # the status period itself, not synchronisation
            now = time.monotonic()
            self.publisher.publish(self._status_message(now - last))
            self.state.samples_window = 0
            self.state.sumsq = None
            last = now
            if watchdog:
                sd_notify("WATCHDOG=1")
