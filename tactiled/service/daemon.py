"""``tactiled run``: one asyncio daemon per sensor.

Tasks in one TaskGroup: ``reader`` (tactiled.board.serialsource: a thread reads the port once per
``serial.read_interval_s`` and hands the loop its bytes once per ``serial.batch_s``, or once per
``serial.rest_batch_s`` while no slide can be in progress: no slide under way in the live or shadow
pipeline, their detectors past the stream's undecided start, and no load being shed; it
survives unplugs and any exception: a slide in progress when the port goes ends there, reason ``disconnected``, with its final
label from the samples read), whose bytes go through the ingest core (tactiled.run.ingest: decoder, channel and gap policies,
batches of ``serial.batch_s``) into the pipeline and the publisher: batches that complete an
analysis window run inline while the model's analysis is cheap (the last one took at most
:data:`INLINE_ANALYSIS_S`; a thread hop costs two wake-ups), in a worker thread otherwise (the first
one, and after a slow one), so a costly model's feature extraction never stalls the loop;
detection-only batches run inline; ``status`` (at least once a
second, and the systemd watchdog, fed only while the reader is alive and the daemon keeps up); ``stop`` (SIGTERM,
SIGINT). A finite source (tests) ends the stream explicitly and the daemon stops. SIGHUP
(``systemctl reload``) loads the model file again (``model.path`` or ``run --model``, even after a control request
loaded another: that one runs until the next reload or restart): validated as at start-up (a bad file, or one whose
windows the running ring cannot hold, is refused in one line and the running model stays), it takes over at the next
slide, so a slide in progress ends with the model it began with and no sample is lost. Of loads that overlap (SIGHUP or
control), the last requested wins: one still being checked when another is requested is not swapped in.

The loop always turns, whatever the input costs: the source yields after every item it hands over, and
the bytes of one item are decoded in slices of :data:`SLICE_BYTES` and their batches processed one at a
time, with a turn of the loop whenever :data:`TURN_S` of work has passed, so status, the watchdog and
SIGTERM are served within a fraction of a second. When input waits longer than :data:`SHED_AFTER_S`
(the pipeline cannot keep up), the daemon sheds load in a counted way: slides in progress end where
analysis stopped (their label says ``overloaded``), and the samples that follow are still decoded,
recorded and published in order but not analysed (``status.overloaded`` counts them) until the
backlog has drained below :data:`RESUME_BELOW_S`. The watchdog is fed only while the reader is alive
and the daemon keeps up: nothing waits longer than :data:`SHED_AFTER_S`, or samples are being handled
at no less than :data:`KEEPING_UP` of real time.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field

import numpy as np
from tactiled_client import schema
from tactiled_client.endpoints import remove_socket_file

from tactiled import __version__
from tactiled.board.clockmap import ClockMap, rate_mismatch
from tactiled.board.serialsource import CONNECTED, DISCONNECTED, ByteSource, SerialSource
from tactiled.config import Config
from tactiled.core.events import PipelineEvent, SlideResult, SlideResumed
from tactiled.core.features import film_levels
from tactiled.core.shadow import ShadowStats
from tactiled.errors import ConfigError, TactiledError, WindowError
from tactiled.files.capture import CaptureWriter
from tactiled.learn.cost import check_speed
from tactiled.learn.model import Model, load_model
from tactiled.run.ingest import Batch
from tactiled.run.stream import Stream
from tactiled.service.control import control_socket, parse_request, reply
from tactiled.service.publish import Publisher
from tactiled.service.recorder import RecordingSink, link_counters
from tactiled.service.samples_topic import samples_chunks
from tactiled.signals import STOP_SIGNALS, sd_notify

log = logging.getLogger(__name__)

SLICE_BYTES = 4096  # bytes decoded per step (a flood of headers claiming 16 kB frames costs ~12 ms per slice, measured)
TURN_S = 0.02  # the most work, s, done between two turns of the event loop (beyond one slice or one batch)
SHED_AFTER_S = 0.5  # input waiting longer than this: analysis is skipped (load shed) ...
RESUME_BELOW_S = 0.1  # ... until the oldest input waiting is younger than this
RATE_INTERVALS = 10  # a rate off sensor.fs (rate_mismatch) is said after this many status intervals running (5 s at the default)
KEEPING_UP = 0.5  # the watchdog is fed only while samples are handled at no less than this fraction of real time
INLINE_ANALYSIS_S = 0.005  # a batch that completes a window is analysed on the loop if the last such batch took at most this, s
STOP_READER_S = 1.5  # on SIGTERM, the longest wait for what the source has read to be analysed and recorded before it is cancelled
# (a batch or two in normal running: milliseconds; a backlog of costly input takes longer, and a stop must take at most 2 s)


@dataclass
class DaemonState:
    """What status messages report: start (host monotonic, s), samples since the last status and their per-channel
    sums of squares (C,) in counts², and the sensor index one past the newest sample."""

    started: float = field(default_factory=time.monotonic)
    samples_window: int = 0
    sumsq: np.ndarray | None = None
    sums: np.ndarray | None = None  # their sums (C,): the level is about the mean
    last_index: int = 0
    overloaded: int = 0  # samples decoded whose analysis was skipped (load shed)
    shedding: bool = False


class Daemon:
    """The daemon's state and tasks; :meth:`run` until stopped (or, for a finite ``source``, until its end).

    ``source_factory(on_bytes, on_state)``: the byte source (default: the serial port of the config);
    ``record_to``: also stream every sample to ``record_to``'s journal and write the recording on exit
    (tactiled/service/recorder.py); ``raw_to``: write every byte read.
    """

    def __init__(self, config: Config, model: Model | None, record_to: str | None = None, *, raw_to: str | None = None,
                 source_factory: Callable[[Callable[[bytes], Awaitable[None]], Callable[[str, str], None]], ByteSource] | None = None,
                 model_path: str | None = None, force: bool = False, shadow: Model | None = None) -> None:
        self.config = config
        self.model = model
        self.model_path = model_path  # what SIGHUP loads again: the config's model.path (or run --model), whatever a control request loaded
        self._loads = 0  # model loads requested so far (SIGHUP or control): the last one wins (load)
        self._last_load = ""  # ... and the last one, for the line that says an earlier one was overtaken
        self._reloads: set[asyncio.Task[bool]] = set()  # SIGHUP reloads under way
        self.force = force  # run a model even if its analysis cannot keep up with the sensor (tactiled/learn/cost.py)
        if model is not None and not force:
            check_speed(model, model_path or "model")
        if shadow is not None and not force:
            check_speed(shadow, f"shadow model {shadow.fingerprint}")
        s = config.sensor
        self.fingerprint = model.fingerprint if model else ""
        # the ingest core and the pipeline; a candidate model in the shadow of the live one (the same samples through its own
        # pipeline), compared with it and never published as it
        self.stream = Stream(config, model, min_batch=round(config.serial.batch_s * s.fs))
        self.decoder = self.stream.ingest.decoder
        self._channel_errors_seen, self._channel_errors_said = 0, False  # for _say_channel_errors
        self._rate_off = 0  # status intervals running with the measured rate off sensor.fs (_say_rate)
        self.pipeline = self.stream.live
        self.shadow_stats: ShadowStats | None = None
        self.set_shadow(shadow)
        self.publisher = Publisher(config.publish, sensor=config.sensor.id)
        self.state = DaemonState()
        self.stop_event = asyncio.Event()
        self.last_status: schema.Status | None = None  # the stopping status, once run() has ended
        self.source: ByteSource | None = None
        self.raw_to = raw_to
        self._source_factory = source_factory
        self.recorder = RecordingSink(record_to, fs=s.fs, channels=s.channels, volts_per_count=s.volts_per_count, force=force,
                                      meta={"sensor": s.id, "port": s.port, "source": "tactiled run --record"},
                                      counters=lambda: link_counters(self.stream.stats, self.source),
                                      on_error=log.error) if record_to else None  # streams to record_to's journal (tactiled/files/journal.py)
        self._recording_error: str | None = None
        self._tee: CaptureWriter | None = None  # run --raw
        self.clock = ClockMap(s.fs)  # sample index -> host time
        self._raw_next: int | None = None  # next index of the samples topic
        self._reader: asyncio.Task[None] | None = None
        self._turned = time.monotonic()  # when the loop last turned (work is bounded between turns)
        self._analysis_s = float("inf")  # how long the last batch that completed a window took to process (inf: none yet), s
        self._status_at = self.state.started  # when the last periodic status was made (host monotonic, s): the next one's interval began then
        self._periodic: schema.Status | None = None  # that status
        try:
            self.control = control_socket(config, self.publisher.context) if config.control.endpoint else None
        except ConfigError:
            self.publisher.close()
            raise

    @property
    def endpoint(self) -> str:
        """The endpoint the publisher is bound to, as ZeroMQ resolved it (a ``tcp://...:*`` bind shows its port)."""
        return self.publisher.endpoint

    def _make_source(self, tee: CaptureWriter | None) -> ByteSource:
        if self._source_factory is not None:
            return self._source_factory(self._on_bytes, self._on_state)
        s, c = self.config.sensor, self.config.serial
        return SerialSource(s.port, self._on_bytes, self._on_state, baudrate=s.baudrate, retry_initial_s=c.retry_initial_s,
                            retry_max_s=c.retry_max_s, read_interval_s=c.read_interval_s, tee=tee, hand_over_s=c.batch_s)

    async def run(self) -> None:
        """Read, publish and serve control until SIGTERM or SIGINT (or a finite source's end); SIGHUP reloads the model.

        On the way out: a slide under way ends at the last sample read with its final label (reason ``end_of_stream``), then a
        stopping status, sockets and the raw file closed, the recording written.
        """
        loop = asyncio.get_running_loop()
        s = self.config.sensor
        tee = self._tee = CaptureWriter(self.raw_to, lambda line: log.error("run --raw: %s", line)) if self.raw_to else None
        self.source = self._make_source(tee)
        for sig in STOP_SIGNALS:
            if sig != signal.SIGHUP:
                loop.add_signal_handler(sig, self.stop_event.set)
        loop.add_signal_handler(signal.SIGHUP, self._on_sighup)
        log.info("tactiled %s: sensor %s, model %s", __version__, s.id, self.fingerprint or "none")  # the CLI said its port and endpoint
        sd_notify("READY=1")
        try:
            async with asyncio.TaskGroup() as tg:
                self._reader = tg.create_task(self._read(), name="reader")
                status = tg.create_task(self._status(), name="status")
                stopped = tg.create_task(self.stop_event.wait(), name="stop")
                limit = tg.create_task(self.publisher.limit_connections(), name="connections")
                tasks = [self._reader, status, stopped, limit]
                if self.control is not None:
                    tasks.append(tg.create_task(self._serve_control(), name="control"))
                await asyncio.wait([self._reader, stopped], return_when=asyncio.FIRST_COMPLETED)
                if not self._reader.done():  # stopped: what the source read is analysed and recorded first (bounded wait)
                    self.source.request_stop()
                    await asyncio.wait([self._reader], timeout=STOP_READER_S)
                    if not self._reader.done():  # input that costs more than it takes to arrive: a stop takes at most 2 s
                        log.warning("stopping before all that was read could be processed (%g s): the samples after index %s "
                                    "are neither analysed nor recorded", STOP_READER_S, self.state.last_index)
                for t in tasks:
                    t.cancel()
        finally:
            sd_notify("STOPPING=1")
            self._keep(self.stream.held())  # decoded (and counted) but not yet handed over: recorded and published all the same
            self.last_status = self._status_message(stopping=True)  # the CLI's one-line summary on the way out
            self.publisher.publish(self.last_status)
            if self.control is not None:
                remove_socket_file(self.config.control.endpoint)
                self.control.close()
            self.publisher.close()
            if tee is not None:
                tee.close()
            if self.recorder is not None:
                self._save_recording()
            for sig in STOP_SIGNALS:  # SIGHUP (reload) among them
                loop.remove_signal_handler(sig)

    def _on_sighup(self) -> None:
        """SIGHUP: :meth:`reload` in a task of its own; whatever it raises is said in one line (the old model stays)."""
        task = asyncio.get_running_loop().create_task(self.reload(), name="reload")
        self._reloads.add(task)
        task.add_done_callback(self._reloaded)

    def _reloaded(self, task: asyncio.Task[bool]) -> None:
        """A SIGHUP reload's task has ended: forgotten, and an exception it raised said in one line."""
        self._reloads.discard(task)
        exc = None if task.cancelled() else task.exception()
        if exc is not None:  # a failure the checks did not foresee: one line, as a control request's, and the daemon runs on
            log.error("reload of %s refused, model %s stays: %s: %s", self.model_path, self.fingerprint or "none", type(exc).__name__, exc)

    async def reload(self) -> bool:
        """Load :attr:`model_path` (the config's ``model.path``, or ``run --model``) again and swap it in at the next slide; a
        bad file is refused in one line (the old model stays). A model loaded by a control request is replaced by it."""
        if not self.model_path:
            log.error("reload: no model file to load (the daemon runs without a model)")
            return False
        return await self.load(self.model_path, by="SIGHUP") is None

    async def load(self, path: str, by: str = "control") -> str | None:
        """Load ``path``, check it as at start-up (stream, probe, speed) and against the running ring, and swap it in at the next
        slide (a slide in progress finishes with the model it started with). None, or why it was refused (logged; the old
        model stays). ``by``: who asked (SIGHUP, control), for the lines.

        The last request wins: a load still being checked when another is requested is not swapped in (its reply and a line
        say so), whether the later one is then swapped in or refused. A model loaded from another file than :attr:`model_path` (a
        control request) runs until the next reload (SIGHUP, which loads :attr:`model_path`) or restart."""
        self._loads += 1
        ticket, self._last_load = self._loads, f"{by} load of {path}"
        try:
            model = await self._checked(path)
        except TactiledError as exc:
            return self._refused(str(exc))
        if ticket != self._loads:
            log.warning("reload: model %s from %s (%s) not swapped in: a later request (%s) came while it was checked; model %s runs",
                        model.fingerprint, path, by, self._last_load, self.fingerprint or "none")
            return f"{path}: not swapped in: a later request ({self._last_load}) came while it was checked (the last request wins)"
        try:
            self.stream.swap_model(model)
        except WindowError as exc:  # windows longer than the running ring holds: only a start sizes the ring for its model
            return self._refused(f"{path}: {exc}, or restart the daemon with it (a start sizes the ring for its model; "
                                 "a running one's does not grow)")
        log.info("reload: model %s from %s takes over at the next slide (was %s)", model.fingerprint, path, self.fingerprint or "none")
        self.model, self.fingerprint = model, model.fingerprint
        return None

    def _refused(self, error: str) -> str:
        """A load refused: ``error`` logged in one line (the old model stays) and returned."""
        log.error("reload refused, model %s stays: %s", self.fingerprint or "none", error)
        return error

    async def _checked(self, path: str) -> Model:
        """A model file loaded and checked for this stream, as at start-up (off the event loop)."""
        s = self.config.sensor
        model = await asyncio.to_thread(load_model, path)
        model.check_stream(s.fs, s.channels, f"sensor {s.id}", path)
        await asyncio.to_thread(check_speed, model, path, self.force)
        return model

    def set_shadow(self, model: Model | None) -> None:
        """Run ``model`` in the shadow of the live one from the next live slide on, under the live slides' ids (None: stop the
        shadow; a shadow running stops at once)."""
        self.stream.set_shadow(model)
        self.shadow_stats = ShadowStats(model=model.fingerprint) if model is not None else None

    async def _serve_control(self) -> None:
        """Answer control requests (tactiled/service/control.py) until cancelled: one reply per request."""
        assert self.control is not None
        while True:
            frames = await self.control.recv_multipart()
            try:
                cmd, path = parse_request(frames)
            except ValueError as exc:
                await self.control.send(reply(False, error=str(exc)))
                continue
            try:
                answer = await self._answer(cmd, path)
            except Exception as exc:  # a request the checks missed is refused in one line; the daemon runs on
                log.error("control: %s %s refused: %s: %s", cmd, path, type(exc).__name__, exc)
                answer = reply(False, error=f"{type(exc).__name__}: {exc}")
            await self.control.send(answer)

    async def _answer(self, cmd: str, path: str | None) -> bytes:
        """The packed reply to one parsed control request."""
        if cmd == "status":
            return reply(True, status=self._status_now().to_map())
        if cmd == "load":
            assert path is not None
            error = await self.load(path)
            return reply(error is None, **({"error": error} if error else {"model": self.fingerprint}))
        try:
            candidate = await self._checked(path) if path else None
        except TactiledError as exc:
            return reply(False, error=str(exc))
        self.set_shadow(candidate)
        log.info("shadow: %s", f"model {candidate.fingerprint} from {path}, from the next slide on" if candidate else "stopped")
        return reply(True, shadow=candidate.fingerprint if candidate else None)

    def _status_now(self) -> schema.Status:
        """A status for a control request: every figure as of now, but ``fs_measured`` and ``level`` those of the last status
        published (over its whole interval: the one under way may have only begun) and its ``seq``; ``time_unix`` now.
        Before the first status, the rate and levels since the start."""
        msg = self._status_message(time.monotonic() - self._status_at)
        last = self._periodic
        if last is not None:
            msg.seq, msg.fs_measured, msg.level = last.seq, last.fs_measured, last.level
        msg.time_unix = time.time()
        return msg

    async def _read(self) -> None:
        """The source until it ends (a finite source: then the explicit end of stream), or until cancelled."""
        assert self.source is not None
        await self.source.run()
        # the end of a finite source, or a stop: a slide under way ends at the last sample read (reason end_of_stream, as the
        # replay of its recording ends it at the file's end) and gets its final label; slides cut short by load shedding had
        # ended already
        if self.stop_event.is_set() and self.state.shedding:
            return
        step = self.stream.finish()
        self._keep(step.batches)
        self._publish(step.events, time.perf_counter())
        self._publish_shadow(step.shadow, time.perf_counter())

    def _on_state(self, state: str, detail: str) -> None:
        log.log(logging.INFO if state == CONNECTED else logging.WARNING, "%s: %s (%s)", self.config.sensor.port, state, detail)
        if state == DISCONNECTED:
            self._port_lost()

    def _port_lost(self) -> None:
        """The serial port is gone (unplugged, or a reader error): a slide in progress ends at the last sample read, its end
        published with reason ``schema.END_DISCONNECTED``, and gets its final label from the samples read (the live and shadow
        pipelines alike), as a gap longer than the ring ends one; the detector goes on with the samples after the
        reconnection. Nothing changes if no slide is in progress, nor on a stop (the stream's end ends it, in :meth:`_read`), for a
        finite source (its end is the end of the stream), or while shedding load (slides already ended). A recording
        (``--record``) marks the disconnection after the rows read (its ``disconnected`` key): its replay ends the slide there too."""
        if self.stop_event.is_set() or self.state.shedding or not isinstance(self.source, SerialSource) or self.stream.pipeline is None:
            return
        held = self.stream.held()  # decoded and counted, not yet handed over: recorded, published and analysed first
        self._keep(held)
        if self.recorder is not None:  # the recording marks it after those rows: its replay ends the slide there too
            self.recorder.mark_disconnected()
        now = time.perf_counter()
        step = self.stream.process(held)
        step += self.stream.disconnected()
        self._publish(step.events, now)
        self._publish_shadow(step.shadow, now)

    async def _on_bytes(self, data: bytes) -> None:
        """Bytes read from the port: decode them a slice at a time, and run the pipeline on each batch they complete,
        turning the loop whenever :data:`TURN_S` of work has passed.

        After each slice the clock map is told that the samples decoded so far had arrived by the time of the read that
        returned the slice's last byte (``source.read_at``): their arrival, however long they then waited to be decoded. Not
        the newest read's time (``source.arrival``): while analysis lags, the bytes decoded now were read long before it,
        every pair would look late, and held late over the map's ``reset_s`` for ``persist_s`` they would measure its line
        again, hundreds of ms off."""
        self._turned = time.monotonic()  # the source yields before each item
        view = memoryview(data)
        for lo in range(0, len(view), SLICE_BYTES):
            hi = min(lo + SLICE_BYTES, len(view))
            batches = self.stream.decode(view[lo:hi])
            end = self.decoder.next_index
            if end is not None and self.source is not None:
                self.clock.observe(end, self.source.read_at(hi - 1))  # every sample decoded so far had arrived by then
            if batches:
                await self._process(batches)
            await self._turn()
        if self.source is not None:
            self.source.hand_over_s = self._hand_over_s()

    def _hand_over_s(self) -> float:
        """How often the source should hand bytes over now: ``serial.rest_batch_s`` (at least ``batch_s``) while no slide can be
        in progress (live and shadow detectors decided and at rest, no load shed), else ``serial.batch_s``."""
        c = self.config.serial
        if self.state.shedding:
            return c.batch_s
        for p in (self.stream.pipeline, self.stream.shadow):
            if p is not None and (p.sliding or p.detector.undecided):
                return c.batch_s
        return max(c.batch_s, c.rest_batch_s)

    async def _turn(self) -> None:
        """Let the loop turn (status, watchdog, signals) if :data:`TURN_S` of work has passed since it last did."""
        if time.monotonic() - self._turned >= TURN_S:
            await asyncio.sleep(0)  # a turn of the loop, not synchronisation
            self._turned = time.monotonic()

    def _shed_now(self) -> bool:
        """Whether to skip analysis now: starts when input has waited over :data:`SHED_AFTER_S` (slides in progress end
        there, their labels marked overloaded), stops once it waits less than :data:`RESUME_BELOW_S`."""
        behind = self.source.behind if self.source is not None else 0.0
        st = self.state
        if st.shedding and behind < RESUME_BELOW_S:
            st.shedding = False
            log.warning("caught up (input %.2f s behind): analysing again from sample %d; %d samples not analysed so far",
                        behind, st.last_index, st.overloaded)
        elif not st.shedding and behind > SHED_AFTER_S:
            st.shedding = True
            log.warning("overloaded: input %.2f s behind; skipping analysis until the backlog drains (samples are still decoded, "
                        "recorded and published)", behind)
            step = self.stream.shed()
            now = time.perf_counter()
            self._publish(step.events, now, overloaded=True)
            self._publish_shadow(step.shadow, now, overloaded=True)
        return st.shedding

    async def _process(self, batches: list[Batch]) -> None:
        """Decoded batches: recorded, published on the samples topic, then through the pipeline one at a time (a costly
        analysis off the loop) unless the daemon is shedding load."""
        if not batches:
            return
        self._take(batches)
        detected_at = time.perf_counter()
        if self.config.publish.samples:
            self._publish_samples(batches)
        for b in batches:
            if self._shed_now():
                self.state.overloaded += b.samples.shape[0]
                continue
            if self.stream.will_analyse(b.end) or b.restart:
                t0 = time.perf_counter()
                if self._analysis_s <= INLINE_ANALYSIS_S:  # cheap: a thread hop would cost more than it spares the loop
                    step = self.stream.process([b])
                else:  # feature extraction that may be costly: off the event loop
                    step = await asyncio.to_thread(self.stream.process, [b])
                    self._turned = time.monotonic()
                self._analysis_s = time.perf_counter() - t0
            else:  # detection only: cheaper than a thread hop
                step = self.stream.process([b])
            self._publish(step.events, detected_at)
            self._publish_shadow(step.shadow, detected_at)
            await self._turn()

    def _keep(self, batches: list[Batch]) -> None:
        """Decoded batches outside the pipeline's own path (a stop, the end of a source, a lost port): recorded (:meth:`_take`)
        and, with ``publish.samples``, on the samples topic, as :meth:`_process` does before it analyses."""
        self._take(batches)
        if self.config.publish.samples:
            self._publish_samples(batches)

    def _take(self, batches: list[Batch]) -> None:
        """Decoded batches into the recorder and the status's film levels."""
        st = self.state
        for b in batches:
            if self.recorder is not None:
                self.recorder.add(b)
            x = b.samples.astype(np.float64)
            sq = np.einsum("ij,ij->j", x, x)  # a third of the time of einsum's own cast (dtype=), same sums (exact below 2**53)
            total = x.sum(axis=0)
            st.sumsq = sq if st.sumsq is None else st.sumsq + sq
            st.sums = total if st.sums is None else st.sums + total
            st.samples_window += b.samples.shape[0]
            st.last_index = b.end

    def _publish(self, events: list[PipelineEvent], detected_at: float, overloaded: bool = False) -> None:
        sensor = self.config.sensor
        to_host = self.clock.host if self.clock.ready else None
        for ev in events:  # a result names the model that made it (a reloaded one takes over between slides)
            model = ev.model if isinstance(ev, SlideResult) and ev.model else self.fingerprint
            self.publisher.publish_event(sensor.id, ev, sensor.fs, model, detected_at, to_host, overloaded=overloaded)
            if self.shadow_stats is not None and isinstance(ev, SlideResult):
                self.shadow_stats.add_live(ev)
            elif self.shadow_stats is not None and isinstance(ev, SlideResumed):
                self.shadow_stats.withdraw(shadow=False)

    def _publish_shadow(self, events: list[PipelineEvent], detected_at: float, overloaded: bool = False) -> None:
        """The shadow model's results on ``shadow/<id>`` (its slide events are the live ones': not sent again)."""
        if self.shadow_stats is None:
            return
        sensor = self.config.sensor
        to_host = self.clock.host if self.clock.ready else None
        for ev in events:
            if isinstance(ev, SlideResumed):
                self.shadow_stats.withdraw(shadow=True)
            if isinstance(ev, SlideResult):
                self.shadow_stats.add_shadow(ev)
                self.publisher.publish(schema.shadow(sensor.id, ev, fs=sensor.fs, model=ev.model or self.shadow_stats.model, version=__version__,
                                                     latency_ms=(time.perf_counter() - detected_at) * 1e3, to_host=to_host,
                                                     overloaded=overloaded))

    def _publish_samples(self, batches: list[Batch]) -> None:
        """The batch's raw samples on ``samples/<id>``: every index from the last batch's end on, lost ones as zero rows."""
        s = self.config.sensor
        to_host = self.clock.host if self.clock.ready else None
        for b in samples_chunks([(x.index, x.samples) for x in batches], self._raw_next, max_fill=round(s.fs)):
            n = b.samples.shape[0]
            self.publisher.publish(schema.samples(s.id, b.index, b.samples.astype("<i2", copy=False).tobytes(), n, s.channels, fs=s.fs,
                                                  volts_per_count=s.volts_per_count, lost=b.lost, lost_before=b.lost_before,
                                                  to_host=to_host, fs_clock=round(self.clock.rate(b.index, b.index + n), 3)))
            self._raw_next = b.index + n

    @property
    def recording_error(self) -> str | None:
        """The recording's failure in one line (a full disk while capturing, or the ``.npz`` not written at exit), or the raw
        capture's (``--raw``), or None: ``tactiled run`` then exits 1."""
        return self._recording_error or (self.recorder.error if self.recorder is not None else None) or (self._tee.error if self._tee else None)

    def _save_recording(self) -> None:
        """The recording written from its journal (the journal removed); one of no sample is not written (as ``tactiled
        record``): its journal is removed, a file already at its path stays as it was, and one line says so."""
        assert self.recorder is not None
        if self.recorder.first_index is None and self.recorder.error is None:  # not one sample: an empty recording is no recording
            self.recorder.discard()
            log.warning("nothing was recorded (no sample received), so %s was not written", self.recorder.out)
            return
        result = self.recorder.finish()
        if result.error is None:
            log.info("%s: saved %d samples (%d lost)", self.recorder.out, result.samples, result.samples_lost)
        else:
            self._recording_error = result.error
            if not self.recorder.error:  # a failure while capturing was logged when it happened
                log.error("%s", result.error)

    def _status_message(self, interval: float = 0.0, stopping: bool = False) -> schema.Status:
        st, stats = self.state, self.stream.stats
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
        level: list[float] = []
        if st.sumsq is not None and st.sums is not None:
            level = film_levels(st.sums, st.sumsq, st.samples_window, self.config.sensor.volts_per_count)
        clock_index = clock_mono = clock_unix = None
        if self.clock.ready and st.last_index:
            clock_index = st.last_index
            clock_mono, clock_unix = (round(t, 6) for t in self.clock.host(clock_index))
        return schema.status(self.config.sensor.id, state=state, samples=stats.samples, samples_lost=stats.samples_lost, crc_errors=stats.crc_errors,
                             bytes_discarded=stats.bytes_discarded, bad_headers=stats.bad_headers,
                             reconnects=self.source.reconnects if self.source else 0, restarts=stats.restarts,
                             slides=self.pipeline.slides, labels=self.pipeline.labels, unknown=self.pipeline.unknown, fs_nominal=self.config.sensor.fs,
                             fs_measured=round(st.samples_window / interval, 1) if interval > 0 else 0.0, model=self.fingerprint,
                             uptime_s=round(time.monotonic() - st.started, 3), index=st.last_index, level=level, version=__version__,
                             dropped_messages=self.publisher.dropped, channel_errors=stats.channel_errors, duplicate_frames=stats.duplicates,
                             clock_index=clock_index,
                             clock_mono=clock_mono, clock_unix=clock_unix, fs_clock=round(self.clock.fs, 3),
                             shadow=self.shadow_stats.summary() if self.shadow_stats is not None else None,
                             overloaded=st.overloaded, behind_s=round(self.source.behind, 3) if self.source else 0.0,
                             input_shed_bytes=self.source.shed_bytes if self.source else 0,
                             discarded_at_start=self.source.discarded_at_start if self.source else 0)

    def reader_alive(self, now: float) -> bool:
        """The reader task runs and its loop ticked recently (reading, or waiting for the device)."""
        if self._reader is None or self._reader.done() or self.source is None:
            return False
        return now - self.source.alive_at <= max(5.0, 2 * self.config.serial.retry_max_s)

    def keeping_up(self, interval: float, handled: int) -> bool:
        """True if nothing has waited longer than :data:`SHED_AFTER_S`, or ``handled`` samples in ``interval`` s are at least
        :data:`KEEPING_UP` of real time (what the watchdog asks, besides a live reader)."""
        behind = self.source.behind if self.source is not None else 0.0
        return behind <= SHED_AFTER_S or handled >= KEEPING_UP * self.config.sensor.fs * interval

    def _say_rate(self) -> None:
        """Log once when the clock map's measured rate has been off ``sensor.fs`` (:func:`rate_mismatch`) for
        :data:`RATE_INTERVALS` status intervals running (a board at another rate than configured), and again after it
        has been back in tolerance."""
        line = rate_mismatch(self.config.sensor.id, self.clock.fs, self.config.sensor.fs) if self.clock.ready else None
        self._rate_off = self._rate_off + 1 if line else 0
        if self._rate_off == RATE_INTERVALS:
            log.warning("%s (status: fs_clock)", line)

    def _say_channel_errors(self) -> None:
        """Log once when intact frames of another channel count than ``sensor.channels`` begin to be skipped (the board is
        not the one configured: no sample of it is analysed), and once more each time they start again after a quiet spell."""
        errors = self.stream.stats.channel_errors
        if errors > self._channel_errors_seen and not self._channel_errors_said:
            log.warning("%s", self.decoder.channel_mismatch(self.config.sensor.id))
        self._channel_errors_said = errors > self._channel_errors_seen  # a quiet interval: the next ones are said again
        self._channel_errors_seen = errors

    async def _status(self) -> None:
        interval = self.config.publish.status_interval_s
        last = self._status_at = time.monotonic()
        handled = self.stream.stats.samples
        watchdog = "WATCHDOG_USEC" in os.environ
        while True:
            await asyncio.sleep(interval)  # the status period itself, not synchronisation
            now = time.monotonic()
            self._periodic = self.publisher.publish(self._status_message(now - last))
            self._status_at = now
            self._say_channel_errors()
            self._say_rate()
            self.state.samples_window = 0
            self.state.sumsq = self.state.sums = None
            # a dead reader, or input the daemon cannot keep up with, starves the watchdog: systemd restarts the daemon
            samples = self.stream.stats.samples
            if watchdog and self.reader_alive(now) and self.keeping_up(now - last, samples - handled):
                sd_notify("WATCHDOG=1")
            last, handled = now, samples
