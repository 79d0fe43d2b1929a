"""The ZeroMQ PUB side: builds schema messages and sends them without ever blocking.

A PUB socket drops messages for a subscriber whose queue is full (high-water mark), so a
slow or absent subscriber never stalls the daemon; ``seq`` (per topic, consecutive) lets
every subscriber count what it missed.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import functools
import logging
import os
import socket
import time
from pathlib import Path
from typing import Any, TypeVar

import zmq
import zmq.asyncio
from tactiled_client import schema
from tactiled_client.endpoints import AUTO, allow_ipv6, local_socket, remove_socket_file

from tactiled import __version__
from tactiled.config import PublishConfig, in_use, missing_ipc_folder
from tactiled.core.events import PipelineEvent, SlideEnded, SlideResult, SlideResumed, SlideStarted
from tactiled.errors import ConfigError, OutputError
from tactiled.files.outputs import check_folder, check_output

log = logging.getLogger(__name__)
M = TypeVar("M", bound=schema.Message)
# a subscription is one inbound message: a flag byte and a topic prefix (the longest topic: "roughness/" and a sensor
# id of at most 64 bytes, 75 bytes). Each distinct subscription costs the publisher memory, about 40 bytes per byte of
# it that no other subscription shares (libzmq's subscription trie), so a peer sending a message longer than this is
# disconnected. Measured (bench/bench_subscriptions.py, every subscription delivered): 10 000 distinct subscriptions
# from one peer add 32 MB at 80 bytes, 55 MB at 128, 166 MB at 370. The CURVE handshake needs longer commands (HELLO
# 200 bytes, INITIATE about 300 with its metadata), so with CURVE the cap is higher: those peers hold an authorised key.
MAX_INBOUND_BYTES = 128
MAX_INBOUND_CURVE_BYTES = 384


EVENTS_PER_TURN = 256  # connection events handled in one turn of the loop (a storm of peers yields between batches)
TRIM_AFTER_S = (1.0, 5.0)  # after a subscriber leaves, when to give what its subscriptions held back to the system


def release_freed_memory() -> None:
    """Return the heap's free pages to the system (glibc's ``malloc_trim``; nothing where the C library has none): after
    a peer with many subscriptions leaves, glibc would otherwise keep what libzmq freed (most of it, measured)."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


@functools.cache
def _malloc_trim() -> Any:
    try:
        return ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        return None


SOCKET_MODE = 0o660  # an ipc socket: the daemon's user and group may connect (add subscribers' users to the group)
FOLDER_MODE = 0o750  # the runtime folder made for it


def bind_address(endpoint: str, sensor: str) -> str:
    """The address to bind for ``publish.endpoint``: ``auto`` is ``ipc://`` + :func:`tactiled_client.endpoints.local_socket`
    (its folder made, mode 750); for an ipc:// path, a socket another process still listens on is refused (ConfigError:
    ZeroMQ would silently take it over), a stale one is replaced."""
    if endpoint == AUTO:
        path = local_socket(sensor)
        try:
            path.parent.mkdir(mode=FOLDER_MODE, parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(f"publish.endpoint: cannot make {path.parent} for the daemon's socket: {exc.strerror or exc}") from None
        endpoint = f"ipc://{path}"
    if in_use(endpoint):
        raise ConfigError(f"publish.endpoint: another process already publishes on {endpoint} (another daemon for sensor "
                          f"{sensor}?); stop it or give this one another endpoint")
    return endpoint


def bind_problem(endpoint: str, exc: zmq.ZMQError) -> str:
    """Why ZeroMQ could not bind ``endpoint``, in words: a missing ipc folder as ``check-config`` says it, else ZeroMQ's."""
    folder = missing_ipc_folder(endpoint)
    return f"cannot bind {endpoint}: " + (f"the folder {folder} does not exist (make it, or choose another path)" if folder else str(exc))


def share_socket(path: Path, group: str) -> None:
    """Mode 660 on the socket at ``path``, and group ``group`` when it exists and this process belongs to it (else the
    file keeps this process's group): the users of that group may subscribe, as gpsd's users do through its socket."""
    with contextlib.suppress(OSError):
        path.chmod(SOCKET_MODE)
        if group:
            import grp

            try:
                gid = grp.getgrnam(group).gr_gid
            except KeyError:
                return
            if gid in os.getgroups() or gid == os.getegid():
                os.chown(path, -1, gid)


# Messages queued for one subscriber before ZeroMQ drops that subscriber's newest. A live daemon sends a few a second
# (about 25 more with the raw samples topic), so a subscriber may stall for minutes (about 30 s with the raw topic) and
# lose nothing, and one that never reads holds at most this many messages of the daemon's memory. At 10 000, a subscriber
# that never read grew the daemon by about 0.12 MB a minute for the better part of an hour (docs/benchmarks.md).
SEND_HWM = 1_000
BURST_SEND_HWM = 10_000  # replay --publish sends as fast as it can: room for a subscriber to fall that far behind a file


class Publisher:
    """Binds ``config.endpoint`` (``auto``: :func:`bind_address`); :meth:`publish` stamps seq and time_unix on schema messages and sends them."""

    def __init__(self, config: PublishConfig, context: zmq.Context[Any] | None = None, see_subscribers: bool = False,
                 sensor: str = "fingertip0", send_hwm: int = SEND_HWM) -> None:
        """``see_subscribers``: an XPUB socket, so that :meth:`wait_subscriber` can tell when a subscription arrived; ``sensor``:
        the id that names the socket of ``auto``; ``send_hwm``: messages queued per subscriber before ZeroMQ drops that
        subscriber's newest (:data:`SEND_HWM`, :data:`BURST_SEND_HWM`)."""
        self.context = context or zmq.Context.instance()
        self.socket = self.context.socket(zmq.XPUB if see_subscribers else zmq.PUB)
        self.socket.setsockopt(zmq.LINGER, 0)
        self.socket.setsockopt(zmq.SNDHWM, send_hwm)
        # a peer that connects and never completes the greeting holds one of max_connections' places until libzmq drops it
        # (30 s by default): a subscriber greets within milliseconds, and one dropped for a slow greeting connects again
        self.socket.setsockopt(zmq.HANDSHAKE_IVL, round(config.handshake_s * 1000))
        # PUB and XPUB sockets receive their subscribers' SUBSCRIBE messages: a peer sending a longer one is disconnected,
        # so a 16 MB topic prefix can never grow the daemon (topics are "<type>/<sensor id>", under 100 bytes)
        self.socket.setsockopt(zmq.MAXMSGSIZE, MAX_INBOUND_CURVE_BYTES if config.curve_secret_key_file else MAX_INBOUND_BYTES)
        self.authenticator: Any = None
        if config.curve_secret_key_file:
            self._curve(config)
        # the connection events, watched from before the bind so that no peer is accepted unseen (limit_connections reads them)
        monitor = f"inproc://tactiled-publisher-monitor-{id(self)}"
        self.socket.monitor(monitor, zmq.EVENT_ACCEPTED | zmq.EVENT_DISCONNECTED | zmq.EVENT_CLOSED)
        self._events = zmq.asyncio.Context.shadow(self.context.underlying).socket(zmq.PAIR)
        self._events.setsockopt(zmq.LINGER, 0)
        self._events.connect(monitor)
        try:
            address = bind_address(config.endpoint, sensor)
            allow_ipv6(self.socket, address)
            self.socket.bind(address)
        except zmq.ZMQError as exc:
            self._close_sockets()
            raise ConfigError(f"publish.endpoint: {bind_problem(address, exc)}") from None
        except ConfigError:
            self._close_sockets()
            raise
        self.endpoint = self.socket.getsockopt_string(zmq.LAST_ENDPOINT)
        if self.endpoint.startswith("ipc://"):
            share_socket(Path(self.endpoint[6:]), config.socket_group)
        self._seq: dict[str, int] = {}
        self.sent = 0
        self.dropped = 0
        self.max_connections = config.max_connections
        self.connections: set[int] = set()  # the file descriptors of the subscriber connections accepted and not yet closed
        self.refused = 0  # connections over max_connections, disconnected at once
        self._trims_due: dict[float, asyncio.TimerHandle] = {}  # a pending heap trim per step of TRIM_AFTER_S
        self.departed = 0  # subscriber connections accepted that have since closed

    async def limit_connections(self) -> None:
        """Until cancelled: keep at most ``max_connections`` subscriber connections, shutting down each one accepted beyond
        that (ZeroMQ then drops it like any peer that went away), so silent peers cannot take every file descriptor."""
        waiting: zmq.Socket[bytes] = zmq.Socket.shadow(self._events.underlying)  # the events already queued, read without a loop turn each
        try:
            while True:
                frames = await self._events.recv_multipart()
                for _ in range(EVENTS_PER_TURN):  # a storm of peers: up to this many events per turn, each a few µs
                    self._on_event(frames[0])
                    try:
                        frames = waiting.recv_multipart(zmq.NOBLOCK)
                    except zmq.Again:
                        break
                else:
                    self._on_event(frames[0])
                    await asyncio.sleep(0)  # a turn of the loop between batches (the samples come first), not synchronisation
        finally:
            with contextlib.suppress(zmq.ZMQError):
                self.socket.disable_monitor()

    def _on_event(self, head: bytes) -> None:
        """One connection event of the monitor (``head``: its first frame, event number and file descriptor)."""
        event, fd = int.from_bytes(head[:2], "little"), int.from_bytes(head[2:6], "little")
        if event == zmq.EVENT_ACCEPTED:
            if len(self.connections) >= self.max_connections:
                self._refuse(fd)
            else:
                self.connections.add(fd)
        elif fd in self.connections:
            self.connections.discard(fd)
            self.departed += 1
            # what the peer's subscriptions held is freed as its pipe ends (on libzmq's I/O thread, soon after this event);
            # glibc keeps freed heap pages unless asked: housekeeping a moment later, not synchronisation
            self._trim_later()

    def _trim_later(self) -> None:
        """:func:`release_freed_memory` at each of :data:`TRIM_AFTER_S` from now, unless a trim is already due at that step: a storm
        of peers that connect and leave costs at most one trim a step, not two a peer (15 000 in a second put the analysis
        1.5 s behind)."""
        loop = asyncio.get_running_loop()
        for delay in TRIM_AFTER_S:
            if delay not in self._trims_due:
                self._trims_due[delay] = loop.call_later(delay, self._trim, delay)

    def _trim(self, delay: float) -> None:
        self._trims_due.pop(delay, None)
        release_freed_memory()

    def _refuse(self, fd: int) -> None:
        """Shut down the connection on ``fd`` (libzmq sees it end and closes it)."""
        self.refused += 1
        if self.refused in (1, 10, 100) or self.refused % 1000 == 0:
            log.warning("publish: %d connection(s) refused over publish.max_connections = %d", self.refused, self.max_connections)
        with contextlib.suppress(OSError), socket.socket(fileno=fd) as conn:
            try:
                conn.shutdown(socket.SHUT_RDWR)
            finally:
                conn.detach()  # the descriptor stays libzmq's: it closes it

    def _curve(self, config: PublishConfig) -> None:
        """CURVE: encrypt, and admit only subscribers whose public certificate is in the authorised folder."""
        import os

        import zmq.auth
        from zmq.auth.thread import ThreadAuthenticator

        try:
            public, secret = zmq.auth.load_certificate(config.curve_secret_key_file)
        except (OSError, ValueError) as exc:
            self.socket.close()
            raise ConfigError(f"publish.curve_secret_key_file: cannot read {config.curve_secret_key_file}: {exc}") from None
        if not secret:
            self.socket.close()
            raise ConfigError(f"publish.curve_secret_key_file: {config.curve_secret_key_file} holds no secret key")
        if not os.path.isdir(config.curve_authorized_dir):
            self.socket.close()
            raise ConfigError(f"publish.curve_authorized_dir: {config.curve_authorized_dir} is not a folder")
        self.authenticator = ThreadAuthenticator(self.context)
        self.authenticator.start()
        self.authenticator.configure_curve(domain="*", location=config.curve_authorized_dir)
        self.socket.curve_secretkey = secret
        self.socket.curve_publickey = public
        self.socket.curve_server = True

    def publish(self, msg: M) -> M:
        """Send ``msg`` (built by a :mod:`tactiled_client.schema` builder) with the next ``seq`` of its topic and ``time_unix`` now."""
        key = schema.topic(msg.type, msg.sensor)
        msg.seq = self._seq.get(key, 0)
        self._seq[key] = msg.seq + 1
        msg.time_unix = time.time()
        try:
            self.socket.send_multipart(schema.encode(msg.type, msg.sensor, msg.to_map()), flags=zmq.NOBLOCK)
            self.sent += 1
        except zmq.Again:
            self.dropped += 1
        return msg

    def wait_subscriber(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for a first subscription (XPUB only): a subscriber that connected before
        the bind otherwise misses what is sent while its subscription is in flight (ZeroMQ's slow joiner)."""
        if self.socket.type != zmq.XPUB or timeout_s <= 0:
            return False
        return bool(self.socket.poll(int(timeout_s * 1000), zmq.POLLIN))

    def close(self) -> None:
        """Close the socket at once (unsent messages dropped) and stop the CURVE authenticator, if any."""
        self._close_sockets()
        if self.authenticator is not None:
            self.authenticator.stop()

    def _close_sockets(self) -> None:
        """The monitor off, then the events socket and the publishing socket closed. limit_connections turns the monitor
        off when it ends; a monitor left on with its reader closed stalls the shared context: a subscriber made on it later
        in the process received nothing (a publisher closed without running, as tests/test_ingest.py's watchdog test does)."""
        with contextlib.suppress(zmq.ZMQError):
            self.socket.disable_monitor()
        self._events.close(0)
        remove_socket_file(getattr(self, "endpoint", ""))  # bound: ZeroMQ leaves the ipc socket's file behind
        self.socket.close(linger=0)

    def publish_event(self, sensor: str, ev: PipelineEvent, fs: float, model: str, detected_at: float | None = None,
                      to_host: schema.HostTime | None = None, overloaded: bool = False) -> None:
        """Publish one pipeline event; ``detected_at`` (perf_counter) is when its block was handed in; ``to_host`` maps indices to host
        times; ``overloaded``: a result of a slide whose analysis was cut short by load shedding."""
        if isinstance(ev, SlideStarted):
            self.publish(schema.slide_start(sensor, ev.slide_id, ev.start, fs, to_host))
        elif isinstance(ev, SlideEnded):
            self.publish(schema.slide_end(sensor, ev.slide_id, ev.start, ev.stop, ev.reason, fs, to_host))
        elif isinstance(ev, SlideResumed):
            self.publish(schema.slide_resumed(sensor, ev.slide_id, ev.start, ev.stop, fs, to_host))
        elif isinstance(ev, SlideResult):
            latency = 0.0 if detected_at is None else (time.perf_counter() - detected_at) * 1e3
            self.publish(schema.roughness(sensor, ev, fs=fs, model=model, version=__version__, latency_ms=latency, to_host=to_host,
                                             overloaded=overloaded))


def create_curve_pair(folder: str | Path, name: str, force: bool = False) -> tuple[Path, Path]:
    """A ZeroMQ CURVE certificate pair ``NAME.key`` (public) and ``NAME.key_secret`` in ``folder`` (made if missing): the
    daemon's, for ``publish.curve_secret_key_file``, or a subscriber's, whose public half goes in the daemon's authorised
    folder. A folder of keys takes more names; a pair of the same name is replaced only with ``force``. Returns the paths.

    The secret file is readable by its owner alone (0600) from the moment it exists: pyzmq writes both files with a plain
    ``open`` (0644 under the usual umask, and an existing file keeps its mode), so they are written into a fresh folder
    only the owner can enter (``mkdtemp``: 0700), the secret one set to 0600, and both then renamed into place."""
    import tempfile

    import zmq.auth

    out = Path(folder)
    check_folder(out, force=True)
    if out.is_dir():
        for file in (f"{name}.key", f"{name}.key_secret"):
            check_output(out / file, force)
    try:
        out.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{name}.", dir=out))
        try:
            made_public, made_secret = zmq.auth.create_certificates(str(staging), name)
            os.chmod(made_secret, 0o600)
            public, secret = out / f"{name}.key", out / f"{name}.key_secret"
            os.replace(made_secret, secret)  # a replaced file of that name goes, with its mode
            os.replace(made_public, public)
        finally:
            for left in staging.iterdir():
                left.unlink()
            staging.rmdir()
    except OSError as exc:
        raise OutputError(f"{out}: cannot write the certificates: {exc.strerror or exc}") from None
    return public, secret
