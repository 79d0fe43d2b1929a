"""An example robot controller: slow down on rough surfaces, using the latest fresh label.

Run a daemon (``tactiled run``, or ``tactiled demo``), then:
    python clients/example_controller.py tcp://127.0.0.1:7350

Or against a recorded session, without any daemon (``python -m tactiled_client record ENDPOINT session.tlog``):
    python clients/example_controller.py --replay session.tlog
"""

from __future__ import annotations

import asyncio
import sys

from tactiled_client import EndOfLog, NoData, Replay, Roughness, Status, Subscriber


async def main(endpoint: str, replay: str | None = None) -> None:
    source = Replay(replay, topics=["roughness", "status"], timeout=3.0) if replay else Subscriber(endpoint, topics=["roughness", "status"], timeout=3.0)
    async with source as sub:
        while True:
            try:
                msg = await sub.receive()
            except EndOfLog:
                print("end of the recorded session")
                return
            except NoData:
                print("no data from the daemon for 3 s: stopping the arm")
                continue
            if msg.missed:
                print(f"missed {msg.missed} {msg.type} messages")
            if isinstance(msg, Roughness):
                if msg.label is None:
                    print(f"slide {msg.slide_id}: no label ({msg.reason})")
                else:
                    print(f"slide {msg.slide_id}: {msg.label} p={msg.confidence:.2f}, {msg.latency_ms:.1f} ms after the slide ended")
            elif isinstance(msg, Status) and msg.state == "disconnected":
                print("sensor disconnected")
            fresh = sub.latest(max_age_s=2.0)
            speed = 0.05 if fresh and fresh.label and float(fresh.label.removeprefix("Ra")) > 2.0 else 0.09
            print(f"  -> sliding speed {speed} m/s")


if __name__ == "__main__":
    args = sys.argv[1:]
    if args[:1] == ["--replay"] and len(args) == 2:
        asyncio.run(main("", replay=args[1]))
    else:
        asyncio.run(main(args[0] if args else "tcp://127.0.0.1:7350"))
