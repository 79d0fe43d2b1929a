"""Where a daemon on this machine publishes by default: an ``ipc://`` socket in a runtime folder, as gpsd keeps its
socket under ``/run``. Local subscribers find it by sensor id; TCP is opt-in (``publish.endpoint``).

The folder, first that applies: ``$TACTILED_RUNTIME_DIR``; ``$RUNTIME_DIRECTORY`` (what systemd sets for the unit's
``RuntimeDirectory=tactiled``: ``/run/tactiled``); ``$XDG_RUNTIME_DIR/tactiled`` (a user's own daemon);
``/tmp/tactiled-<uid>``. The socket is ``<folder>/<sensor id>.sock``.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Any

from tactiled_client.errors import UsageError

SYSTEM_DIR = Path("/run/tactiled")  # the systemd unit's RuntimeDirectory=tactiled
SYSTEM_CONFIG_DIR = Path("/etc/tactiled")  # the systemd unit's configs: tactiled@<name> reads /etc/tactiled/<name>.toml
AUTO = "auto"  # publish.endpoint's default: local_socket(sensor id)


def runtime_dir() -> Path:
    """The folder this process's daemon binds its socket in (see the module docstring)."""
    for var in ("TACTILED_RUNTIME_DIR", "RUNTIME_DIRECTORY"):
        value = os.environ.get(var, "").split(":")[0]
        if value:
            return Path(value)
    xdg = os.environ.get("XDG_RUNTIME_DIR")
    return Path(xdg) / "tactiled" if xdg else Path(f"/tmp/tactiled-{os.getuid()}")


def local_socket(sensor: str) -> Path:
    """The socket a daemon of ``sensor`` binds by default from this process's environment."""
    return runtime_dir() / f"{sensor}.sock"


def local_endpoint(sensor: str = "fingertip0") -> str:
    """The endpoint of the local daemon of ``sensor``: this environment's socket if it exists, else the system
    service's (``/run/tactiled/<sensor>.sock``) if that exists. If neither does (the daemon starts later), the system
    service's where this machine has one for ``sensor`` (``/etc/tactiled/<sensor>.toml``), else this environment's: a
    controller started at boot before the service must wait on the service's socket, not on one no daemon will bind.
    ``$TACTILED_RUNTIME_DIR`` always means this environment's. Decided once, when called: a subscriber stays connected to
    the endpoint it was given."""
    own = local_socket(sensor)
    system = SYSTEM_DIR / f"{sensor}.sock"
    if "TACTILED_RUNTIME_DIR" in os.environ or own.exists():
        return f"ipc://{own}"
    if system.exists() or (SYSTEM_CONFIG_DIR / f"{sensor}.toml").exists():  # (not /run/tactiled alone: another sensor's service)
        return f"ipc://{system}"
    return f"ipc://{own}"


def remove_socket_file(endpoint: str) -> None:
    """Remove the socket file of an ``ipc://`` endpoint this process bound, as it stops: ZeroMQ leaves it (a regular file
    there, or an abstract ``ipc://@name``, is left alone). Established connections are not affected, so what is still queued
    for them goes out."""
    if not endpoint.startswith("ipc://") or endpoint.startswith("ipc://@"):
        return
    path = Path(endpoint[len("ipc://"):])
    with contextlib.suppress(OSError):
        if path.is_socket():
            path.unlink()


def allow_ipv6(sock: Any, endpoint: str) -> None:
    """Turn IPv6 on for a ZeroMQ socket about to bind or connect ``endpoint`` when its host is an IPv6 address
    (``tcp://[::1]:7350``): ZeroMQ sockets are IPv4 only unless told, and fail there with "No such device" (a bind) or
    silence (a connect)."""
    if endpoint.startswith("tcp://["):
        import zmq

        sock.setsockopt(zmq.IPV6, 1)


def connect(sock: Any, endpoint: str) -> None:
    """``sock.connect(endpoint)`` (a ZeroMQ socket; IPv6 on for an IPv6 host, :func:`allow_ipv6`); :class:`UsageError`
    naming ``endpoint`` when ZeroMQ cannot parse it (``foo``, ``tcp://host`` without a port), where ZeroMQ raises a bare
    ``Invalid argument``."""
    import zmq

    allow_ipv6(sock, endpoint)
    try:
        sock.connect(endpoint)
    except zmq.ZMQError as exc:
        raise UsageError(f"{endpoint}: not an endpoint ZeroMQ can connect to ({exc.strerror})") from None
