"""The client library's exceptions: one root, :class:`ClientError`, for everything it raises on purpose."""

from __future__ import annotations


class ClientError(Exception):
    """Root of every error the client library raises (misuse, silence, bad files)."""


class NoData(ClientError, TimeoutError):
    """Nothing arrived within the subscriber's timeout."""


class EndOfLog(NoData):
    """A replayed file has no message left (a replay's ``async for`` / ``for`` simply stops instead)."""


class LogError(ClientError, ValueError):
    """A file that cannot be replayed: one line naming the file and what is wrong."""


class UsageError(ClientError, ValueError):
    """The API used out of order, e.g. receiving before ``async with``."""


class RecordRefused(LogError):
    """A message a session log will not hold, because no reader could read it back (too large, not a msgpack map, a
    receive time that is no clock reading): nothing is written. ``reason`` is the fault without the file's name."""

    def __init__(self, path: object, reason: str) -> None:
        super().__init__(f"{path}: {reason}")
        self.reason = reason
