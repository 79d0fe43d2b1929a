"""Client library for tactiled: subscribe to roughness, slide, status and raw samples messages.

Depends on pyzmq and msgpack only. See docs/messages.md for every field. The subscribers (pyzmq,
asyncio) are imported when first used, so that importing the schema alone stays light.
"""

from typing import TYPE_CHECKING, Any

from tactiled_client.schema import SCHEMA_VERSION, Message, Roughness, Samples, Slide, Status

if TYPE_CHECKING:
    from tactiled_client.subscriber import BlockingSubscriber, NoData, Subscriber

__all__ = ["SCHEMA_VERSION", "BlockingSubscriber", "Message", "NoData", "Roughness", "Samples", "Slide", "Status", "Subscriber"]


def __getattr__(name: str) -> Any:
    if name in ("BlockingSubscriber", "NoData", "Subscriber"):
        from tactiled_client import subscriber

        return getattr(subscriber, name)
    raise AttributeError(f"module 'tactiled_client' has no attribute {name!r}")
