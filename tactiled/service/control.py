"""The daemon's control socket: a local request loads a model, starts or stops a shadow model, or asks for status.

A ZeroMQ REP socket on ``control.endpoint`` (ipc, or tcp on loopback only: checked in the config; an ipc socket another
process listens on is refused, and one bound is mode 660 with ``publish.socket_group``, as the publish socket). Requests and
replies are msgpack maps: ``{"cmd": "load" | "shadow" | "status", "path": str | nil}``; the reply is
``{"ok": true, ...}`` or ``{"ok": false, "error": "<one line>"}``. With CURVE configured for the subscriptions
(``publish.curve_secret_key_file``), the control socket uses the same certificate, and the same authorised folder
admits clients (the publisher's authenticator serves every socket of the context).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import msgpack
import zmq
import zmq.asyncio
import zmq.auth
from tactiled_client.endpoints import allow_ipv6

from tactiled.config import Config, in_use
from tactiled.errors import ConfigError
from tactiled.service.publish import bind_problem, share_socket

COMMANDS = ("load", "shadow", "status")
MAX_REQUEST_BYTES = 4096


def control_socket(config: Config, context: zmq.Context[Any]) -> zmq.asyncio.Socket:
    """A bound asyncio REP socket on ``config.control.endpoint`` sharing ``context`` (and its CURVE authenticator)."""
    sock = zmq.asyncio.Context.shadow(context.underlying).socket(zmq.REP)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.MAXMSGSIZE, MAX_REQUEST_BYTES)
    if config.publish.curve_secret_key_file:
        public, secret = zmq.auth.load_certificate(config.publish.curve_secret_key_file)  # read and checked by the publisher already
        sock.curve_secretkey, sock.curve_publickey, sock.curve_server = secret, public, True
    endpoint = config.control.endpoint
    if in_use(endpoint):
        sock.close()
        raise ConfigError(f"control.endpoint: another process already listens on {endpoint} (another daemon's control socket?); "
                          "stop it or give this one another endpoint")
    allow_ipv6(sock, endpoint)
    try:
        sock.bind(endpoint)
    except zmq.ZMQError as exc:
        sock.close()
        raise ConfigError(f"control.endpoint: {bind_problem(endpoint, exc)}") from None
    if endpoint.startswith("ipc://"):  # as the publish socket: mode 660, publish.socket_group's users may connect
        share_socket(Path(endpoint[6:]), config.publish.socket_group)
    return sock


def parse_request(frames: list[bytes]) -> tuple[str, str | None]:
    """(command, path) of a request; ValueError with one line for anything else."""
    try:
        body = msgpack.unpackb(frames[0], raw=False) if len(frames) == 1 else None
    except (ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError) as exc:
        raise ValueError(f"request: not a msgpack map ({exc})") from None
    if not isinstance(body, dict):
        raise ValueError("request: must be one msgpack map {cmd, path}")
    cmd, path = body.get("cmd"), body.get("path")
    if cmd not in COMMANDS:
        raise ValueError(f"request: cmd must be one of {', '.join(COMMANDS)}, got {cmd!r}")
    if path is not None and not isinstance(path, str):
        raise ValueError("request: path must be a string or nil")
    if path is not None and "\0" in path:
        raise ValueError("request: path holds a NUL character")
    if cmd == "load" and not path:
        raise ValueError("request: load needs a path")
    return cmd, path


def reply(ok: bool, **fields: Any) -> bytes:
    """A reply map, packed."""
    return msgpack.packb({"ok": ok, **fields}, use_bin_type=True)
