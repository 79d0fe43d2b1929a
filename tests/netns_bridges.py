"""Run inside a private network namespace by tests/test_bridges.py: a real PUB socket → bridge → LSL inlet / ROS 2 subscriber.

``python -m tests.netns_bridges lsl|ros2 DIR`` prints one JSON object: what the consumer received
and what was published, for the test to compare. It refuses to run if any interface but
loopback exists (no discovery traffic may leave the machine).
"""

from __future__ import annotations

import json
import socket
import sys
import threading
import time
from typing import Any

import numpy as np
from tactiled_client import schema

from tactiled.apps.bridges import run_bridge
from tactiled.config import PublishConfig
from tactiled.core.pipeline import SlideResult
from tactiled.service.publish import Publisher

FS, N, BATCHES, SENSOR = 20_000.0, 400, 6, "tip7"
VPC = 5.0 / 32768


class Counting:
    """A sink wrapper counting what reached it (to know the bridge is subscribed)."""

    def __init__(self, sink: Any) -> None:
        self.sink, self.seen = sink, 0

    def __getattr__(self, name: str) -> Any:
        method = getattr(self.sink, name)

        def call(*a: Any) -> Any:
            self.seen += 1
            return method(*a)
        return call


def feed(endpoint: str, sink: Any, consume: Any) -> dict[str, Any]:
    pub = Publisher(PublishConfig(endpoint=endpoint))
    counting = Counting(sink)
    stop = threading.Event()
    thread = threading.Thread(target=run_bridge, args=(endpoint, counting, stop), daemon=True)
    thread.start()
    base = time.monotonic() + 0.5

    def host(i: int) -> tuple[float, float]:
        return base + i / FS, 1.7e9 + i / FS

    rng = np.random.default_rng(1)
    counts = rng.integers(-3000, 3000, (BATCHES * N, 2)).astype(np.int16)
    lost = [[100, 20]]  # in batch 2
    deadline = time.monotonic() + 30
    while counting.seen == 0 and time.monotonic() < deadline:  # slow joiner: until the bridge has a message
        pub.publish(schema.status(SENSOR, state=schema.STATE_IDLE))
        stop.wait(0.05)  # publishing period while waiting for the subscription, not synchronisation

    def send(k: int) -> None:
        rows = counts[k * N:(k + 1) * N].copy()
        gone = lost if k == 2 else []
        for p, c in gone:
            rows[p:p + c] = 0
        pub.publish(schema.samples(SENSOR, k * N, rows.astype("<i2").tobytes(), N, 2, fs=FS, volts_per_count=VPC, lost=gone,
                                   to_host=host, fs_clock=FS))

    def status() -> None:
        pub.publish(schema.status(SENSOR, state=schema.STATE_IDLE, clock_index=0, clock_mono=base, clock_unix=1.7e9, fs_clock=FS))

    send(0)  # the raw outlet / publishers exist from the first batch on
    state = consume.start()
    while not consume.ready(state) and time.monotonic() < deadline + 30:  # the consumer hears the bridge: status until it does
        status()
    for k in range(1, BATCHES):
        send(k)
    for final, label in ((False, "Ra1.00"), (True, "Ra1.18"), (True, None)):
        r = SlideResult(4, 500, 2000, (1000, 1800), label, None if label else "low_confidence", 0.8, [("Ra1.18", 0.8)], {"samples": 800},
                        final=final, used_s=0.05)
        pub.publish(schema.roughness(SENSOR, r, fs=FS, model="m", version="t", to_host=host))
    got = consume.collect(state)
    stop.set()
    thread.join(10)
    pub.close()
    return {"got": got, "counts": counts[N:].tolist(), "lost": [[2 * N - N + p, c] for p, c in lost], "base": base, "fs": FS, "n": N,
            "first": N, "vpc": VPC}


class LslConsumer:
    def start(self) -> Any:
        import pylsl

        raw = pylsl.resolve_byprop("name", f"tactiled-{SENSOR}", timeout=20)
        marks = pylsl.resolve_byprop("name", f"tactiled-{SENSOR}-labels", timeout=20)
        inlets = pylsl.StreamInlet(raw[0]), pylsl.StreamInlet(marks[0])
        for inlet in inlets:
            inlet.open_stream(timeout=20)
        info = inlets[0].info(timeout=20)
        ch = info.desc().child("channels").child("channel")
        labels = []
        while not ch.empty():
            labels.append((ch.child_value("label"), ch.child_value("unit")))
            ch = ch.next_sibling()
        return inlets, {"channels": info.channel_count(), "nominal": info.nominal_srate(), "labels": labels, "type": info.type()}

    def ready(self, state: Any) -> bool:
        return True  # open_stream returned: the inlets are connected

    def collect(self, state: Any) -> dict[str, Any]:
        (raw, marks), meta = state
        values: list[list[float]] = []
        stamps: list[float] = []
        markers: list[tuple[str, float]] = []
        deadline = time.monotonic() + 30
        want = (BATCHES - 1) * N - 20
        while (len(values) < want or len(markers) < 3) and time.monotonic() < deadline:
            chunk, ts = raw.pull_chunk(timeout=0.2)
            values += chunk
            stamps += ts
            m, mts = marks.pull_chunk(timeout=0.0)
            markers += [(x[0], t) for x, t in zip(m, mts, strict=True)]
        return {**meta, "values": values, "stamps": stamps, "markers": markers}


class Ros2Consumer:
    def start(self) -> Any:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
        from std_msgs.msg import Float32MultiArray, Header, String

        self.rclpy = rclpy
        node = rclpy.create_node("tactiled_test_consumer")
        got: dict[str, list[Any]] = {"samples": [], "stamp": [], "label": [], "detail": [], "diag": []}
        base = f"/tactiled/{SENSOR}"
        node.create_subscription(Float32MultiArray, f"{base}/samples", lambda m: got["samples"].append(
            ([(d.label, d.size, d.stride) for d in m.layout.dim], list(m.data))), 100)
        node.create_subscription(Header, f"{base}/samples/stamp", lambda m: got["stamp"].append(
            (m.frame_id, m.stamp.sec + m.stamp.nanosec * 1e-9)), 100)
        node.create_subscription(String, f"{base}/roughness", lambda m: got["label"].append(m.data), 10)
        node.create_subscription(DiagnosticStatus, f"{base}/roughness/detail", lambda m: got["detail"].append(
            (m.level[0] if isinstance(m.level, bytes) else m.level, m.message, {kv.key: kv.value for kv in m.values})), 10)
        node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: got["diag"].append(
            [(s.name, s.message, {kv.key: kv.value for kv in s.values}) for s in m.status]), 10)
        # wait until the bridge's publishers are matched (discovery on loopback)
        deadline = time.monotonic() + 30
        while node.count_publishers(f"{base}/samples") == 0 and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
        return node, got

    def ready(self, state: Any) -> bool:
        node, got = state
        self.rclpy.spin_once(node, timeout_sec=0.1)
        return bool(got["diag"])

    def collect(self, state: Any) -> dict[str, Any]:
        node, got = state
        deadline = time.monotonic() + 30
        def done() -> bool:  # the last batch (array and stamp, in pairs) and the three roughness messages are in
            last = bool(got["stamp"]) and got["stamp"][-1][0] == str((BATCHES - 1) * N)
            return last and len(got["samples"]) == len(got["stamp"]) and len(got["detail"]) >= 3

        while not done() and time.monotonic() < deadline:
            self.rclpy.spin_once(node, timeout_sec=0.05)
        node.destroy_node()
        return got


def main() -> None:
    kind, folder = sys.argv[1], sys.argv[2]
    interfaces = [name for _, name in socket.if_nameindex()]
    if interfaces != ["lo"]:
        raise SystemExit(f"refusing to run discovery outside a private network namespace: interfaces {interfaces}")
    endpoint = f"ipc://{folder}/pub"
    if kind == "lsl":
        from tactiled.apps.bridges.lsl import LslSink

        out = feed(endpoint, LslSink(SENSOR), LslConsumer())
    else:
        import rclpy

        from tactiled.apps.bridges.ros2 import Ros2Sink

        rclpy.init()
        out = feed(endpoint, Ros2Sink(SENSOR), Ros2Consumer())
        rclpy.shutdown()
    out["interfaces"] = interfaces
    print(json.dumps(out))


if __name__ == "__main__":
    main()
