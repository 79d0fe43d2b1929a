"""Client library for tactiled: subscribe to roughness, slide, status and raw samples messages.

Depends on pyzmq and msgpack only. See docs/messages.md for every field.
"""

from tactiled_client.schema import SCHEMA_VERSION, Message, Roughness, Samples, Slide, Status
from tactiled_client.subscriber import BlockingSubscriber, NoData, Subscriber

__all__ = ["SCHEMA_VERSION", "BlockingSubscriber", "Message", "NoData", "Roughness", "Samples", "Slide", "Status", "Subscriber"]
