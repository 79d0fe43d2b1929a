"""Client library for tactiled: subscribe to roughness, slide, status, raw samples and shadow messages, record them, replay them.

Depends on pyzmq and msgpack only. See docs/messages.md for every field and the session log format. The
subscribers and replays (pyzmq, asyncio) are imported when first used, so that importing the schema alone
stays light. Every error the library raises on purpose is a :class:`ClientError`.
"""

from typing import TYPE_CHECKING, Any

from tactiled_client.endpoints import local_endpoint
from tactiled_client.errors import ClientError, EndOfLog, LogError, NoData, UsageError
from tactiled_client.schema import SCHEMA_VERSION, Message, Roughness, Samples, Shadow, Slide, Status

if TYPE_CHECKING:
    from tactiled_client.record import record
    from tactiled_client.replay import BlockingReplay, Replay
    from tactiled_client.subscriber import BlockingSubscriber, Subscriber

__all__ = ["SCHEMA_VERSION", "BlockingReplay", "BlockingSubscriber", "ClientError", "EndOfLog", "LogError", "Message", "NoData", "Replay",
           "Roughness", "Samples", "Shadow", "Slide", "Status", "Subscriber", "UsageError", "local_endpoint", "record"]

_LAZY = {"BlockingSubscriber": "subscriber", "Subscriber": "subscriber", "BlockingReplay": "replay", "Replay": "replay", "record": "record"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"tactiled_client.{_LAZY[name]}"), name)
    raise AttributeError(f"module 'tactiled_client' has no attribute {name!r}")
