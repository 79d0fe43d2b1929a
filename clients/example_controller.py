"""An example robot controller: slide slower over rough surfaces, using the latest fresh label and how sure it is.

Start the demo daemon on an endpoint, then this controller on the same endpoint:

    tactiled demo --publish ipc:///tmp/tactiled-demo --headless --seconds 60 &
    python clients/example_controller.py ipc:///tmp/tactiled-demo

Against your own daemon: the endpoint of its ``publish.endpoint``. Against a recorded session, without any daemon
(``python -m tactiled_client record ENDPOINT session.tlog``):

    python clients/example_controller.py --replay session.tlog

Labels are whatever names the model was trained with. A label of the form ``Ra<µm>`` is rough above
``--rough-ra``; any other name is rough when it is listed in ``--rough`` (e.g. ``--rough P60,P120``). A label
that is missing (an unknown surface, a lost stretch) or less sure than ``--min-confidence`` slows the arm too.
"""

from __future__ import annotations

import argparse
import asyncio
import sys

from tactiled_client import ClientError, EndOfLog, NoData, Replay, Roughness, Slide, Status, Subscriber

FAST, SLOW = 0.09, 0.05  # m/s


def is_rough(label: str, rough_ra: float, rough: set[str]) -> bool:
    """Whether ``label`` names a rough surface: ``Ra<µm>`` above ``rough_ra``, or a name listed in ``rough``."""
    if label in rough:
        return True
    if label.startswith("Ra"):
        try:
            return float(label[2:]) > rough_ra
        except ValueError:
            return False
    return False


def speed_for(msg: Roughness | None, rough_ra: float, rough: set[str], min_confidence: float) -> float:
    """The sliding speed (m/s) after the latest label ``msg`` (None: no fresh one)."""
    if msg is None or msg.label is None or (msg.confidence or 0.0) < min_confidence:
        return SLOW  # not sure what is under the finger: careful
    return SLOW if is_rough(msg.label, rough_ra, rough) else FAST


async def main(args: argparse.Namespace) -> None:
    topics = ["roughness", "status", "slide"]  # slide: a "resumed" withdraws a final label (sub.latest forgets it)
    source = Replay(args.replay, topics=topics, timeout=3.0) if args.replay else Subscriber(args.endpoint, topics=topics, timeout=3.0)
    rough = {name for name in args.rough.split(",") if name}
    async with source as sub:
        print(f"controller: labels from {args.replay or args.endpoint} (Ctrl-C stops)", flush=True)
        while True:
            try:
                msg = await sub.receive()
            except EndOfLog:
                cut = source.truncated if isinstance(source, Replay) else None
                print(f"end of the recorded session{f' ({cut})' if cut else ''}")
                return
            except NoData:
                print("no data from the daemon for 3 s: stopping the arm", flush=True)
                continue
            if msg.missed:
                print(f"missed {msg.missed} {msg.type} messages")
            if isinstance(msg, Roughness):
                if msg.label is None:
                    print(f"slide {msg.slide_id}: no label ({msg.reason})", flush=True)
                else:
                    kind = "final" if msg.final else "provisional"
                    print(f"slide {msg.slide_id}: {kind} {msg.label} p={msg.confidence:.2f}, {msg.latency_ms:.1f} ms after its last sample",
                          flush=True)
                print(f"  -> sliding speed {speed_for(sub.latest(max_age_s=2.0), args.rough_ra, rough, args.min_confidence)} m/s", flush=True)
            elif isinstance(msg, Slide) and msg.event == "resumed":
                print(f"slide {msg.slide_id}: goes on, its label is withdrawn", flush=True)
                print(f"  -> sliding speed {speed_for(sub.latest(max_age_s=2.0), args.rough_ra, rough, args.min_confidence)} m/s", flush=True)
            elif isinstance(msg, Status) and msg.state == "disconnected":
                print("sensor disconnected: stopping the arm", flush=True)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description="an example robot controller on tactiled's labels")
    ap.add_argument("endpoint", nargs="?", help="the daemon's endpoint, e.g. ipc:///tmp/tactiled-demo (not needed with --replay)")
    ap.add_argument("--replay", metavar="LOG", help="a recorded session (.tlog, .mcap) instead of a daemon")
    ap.add_argument("--rough-ra", type=float, default=2.0, help="Ra labels above this many µm are rough (default: 2.0)")
    ap.add_argument("--rough", default="", help="other label names that are rough, joined by commas")
    ap.add_argument("--min-confidence", type=float, default=0.5, help="slower below this confidence (default: 0.5)")
    parsed = ap.parse_args()
    if not parsed.replay and not parsed.endpoint:
        ap.error("give the daemon's endpoint, or --replay LOG")
    try:
        asyncio.run(main(parsed))
    except KeyboardInterrupt:  # Ctrl-C: how it is stopped
        print("stopped", flush=True)
    except ClientError as exc:  # a log that cannot be replayed, a bad endpoint: one line
        print(f"example_controller: {exc}", file=sys.stderr)
        sys.exit(2)
