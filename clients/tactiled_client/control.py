"""Ask a running daemon, through its control socket, to load a model, start or stop a shadow model, or for its status.

``control("ipc:///run/tactiled/fingertip0.control", "load", "new_model.npz")`` returns the daemon's reply map:
``{"ok": True, "model": "<fingerprint>"}``, or ``{"ok": False, "error": "<one line>"}`` (the old model stays).
"""

from __future__ import annotations

from typing import Any

import msgpack

from tactiled_client.endpoints import connect
from tactiled_client.errors import NoData, UsageError
from tactiled_client.subscriber import _secure

COMMANDS = ("load", "shadow", "status")


def control(endpoint: str, cmd: str, path: str | None = None, *, curve: tuple[str, str] | None = None, timeout: float = 30.0) -> dict[str, Any]:
    """Send one request and return the reply; :class:`NoData` if none comes within ``timeout`` s.

    ``cmd``: ``load`` (``path``: a model file, checked as at start-up), ``shadow`` (``path``: a candidate model;
    None stops the shadow) or ``status``. ``curve``: as for a subscriber (daemon's public, this client's secret file).
    """
    import zmq

    if cmd not in COMMANDS:
        raise UsageError(f"cmd must be one of {', '.join(COMMANDS)}, got {cmd!r}")
    sock: zmq.Socket[bytes] = zmq.Context.instance().socket(zmq.REQ)
    try:
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.RCVTIMEO, round(timeout * 1000))
        # a REQ socket's send waits for a peer; a daemon that refuses this client's CURVE key drops the connection, so a send
        # after that would wait for ever (seen once in CI under load: the command outlived its 2 s timeout by a minute)
        sock.setsockopt(zmq.SNDTIMEO, round(timeout * 1000))
        _secure(sock, curve)
        connect(sock, endpoint)
        try:
            sock.send(msgpack.packb({"cmd": cmd, "path": path}, use_bin_type=True))
            body = msgpack.unpackb(sock.recv(), raw=False)
        except zmq.Again:
            raise NoData(f"no reply from {endpoint} within {timeout:g} s") from None
    finally:
        sock.close()
    if not isinstance(body, dict):
        raise NoData(f"{endpoint}: the reply is not a map")
    return body
