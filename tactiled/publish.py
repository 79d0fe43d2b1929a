"""The ZeroMQ PUB side: builds schema messages and sends them without ever blocking.

A PUB socket drops messages for a subscriber whose queue is full (high-water mark), so a
slow or absent subscriber never stalls the daemon; ``seq`` (per topic, consecutive) lets
every subscriber count what it missed.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import zmq
from tactiled_client import schema

from tactiled import __version__
from tactiled.config import PublishConfig
from tactiled.errors import ConfigError
from tactiled.pipeline import PipelineEvent, SlideEnded, SlideResult, SlideStarted
from tactiled.recording import Recording


class Publisher:
    """Binds ``config.endpoint``; :meth:`send` stamps v, seq, sensor, type and time_unix."""

    def __init__(self, config: PublishConfig, context: zmq.Context[Any] | None = None) -> None:
        self.context = context or zmq.Context.instance()
        self.socket = self.context.socket(zmq.PUB)
        self.socket.setsockopt(zmq.LINGER, 0)
        self.socket.setsockopt(zmq.SNDHWM, 10_000)
        self.authenticator: Any = None
        if config.curve_secret_key_file:
            self._curve(config)
        try:
            self.socket.bind(config.endpoint)
        except zmq.ZMQError as exc:
            self.socket.close()
            raise ConfigError(f"publish.endpoint: cannot bind {config.endpoint}: {exc}") from None
        self.endpoint = self.socket.getsockopt_string(zmq.LAST_ENDPOINT)
        self._seq: dict[str, int] = {}
        self.sent = 0
        self.dropped = 0

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

    def send(self, kind: str, sensor: str, body: dict[str, Any]) -> dict[str, Any]:
        key = schema.topic(kind, sensor)
        seq = self._seq.get(key, 0)
        self._seq[key] = seq + 1
        full = {"v": schema.SCHEMA_VERSION, "seq": seq, "sensor": sensor, "type": kind, "time_unix": time.time(), **body}
        try:
            self.socket.send_multipart(schema.encode(kind, sensor, full), flags=zmq.NOBLOCK)
            self.sent += 1
        except zmq.Again:
            self.dropped += 1
        return full

    def close(self) -> None:
        self.socket.close(linger=0)
        if self.authenticator is not None:
            self.authenticator.stop()

    def publish_event(self, sensor: str, ev: PipelineEvent, fs: float, model: str, detected_at: float | None = None) -> None:
        """Publish one pipeline event; ``detected_at`` (perf_counter) is when its block was handed in."""
        if isinstance(ev, SlideStarted):
            self.send(schema.SLIDE, sensor, {"event": "start", "slide_id": ev.slide_id, "start": ev.start, "t_start": ev.start / fs})
        elif isinstance(ev, SlideEnded):
            self.send(schema.SLIDE, sensor, {"event": "end" if ev.reason != "too_short" else "cancelled", "slide_id": ev.slide_id,
                                             "start": ev.start, "stop": ev.stop, "t_start": ev.start / fs, "t_stop": ev.stop / fs,
                                             "reason": ev.reason})
        elif isinstance(ev, SlideResult):
            latency = 0.0 if detected_at is None else (time.perf_counter() - detected_at) * 1e3
            self.send(schema.ROUGHNESS, sensor, roughness_body(ev, fs, model, latency))

    def replay_handler(self, sensor: str, rec: Recording, model: str) -> Callable[[PipelineEvent], None]:
        """An ``on_event`` callback for replay (events carry sensor indices, as live)."""

        def handle(ev: PipelineEvent) -> None:
            self.publish_event(sensor, ev, rec.fs, model, time.perf_counter())

        return handle


def roughness_body(r: SlideResult, fs: float, model: str, latency_ms: float) -> dict[str, Any]:
    """The fields of a roughness message (see docs/messages.md)."""
    return {"label": r.label, "reason": r.reason, "confidence": r.confidence, "top": [[c, p] for c, p in r.top], "slide_id": r.slide_id,
            "start": r.start, "stop": r.stop, "window": [r.window[0], r.window[1]], "t_start": r.start / fs, "t_stop": r.stop / fs,
            "latency_ms": round(latency_ms, 3), "model": model, "quality": {**r.quality, "compute_ms": round(r.compute_ms, 3)},
            "version": __version__, "final": r.final, "used_s": round(r.used_s, 4)}
