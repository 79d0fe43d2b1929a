"""Run inside a private network namespace by tests/test_bridges.py: a real PUB socket → bridge → LSL inlet / ROS 2 subscriber.

``python -m tests.netns_bridges lsl|ros2 DIR`` prints one JSON object: what the consumer received
and what was published, for the test to compare. It refuses to run if any interface but
loopback exists (no discovery traffic may leave the machine).

The samples carry host times from a real :class:`~tactiled.board.clockmap.ClockMap` fed with
arrivals whose first read is 31.8 ms late (as the daemon would publish them), and lost ranges
inside a batch and before one (``lost_before``).
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

from tactiled.apps.bridges import StreamMeta, run_bridge
from tactiled.board.clockmap import ClockMap
from tactiled.config import PublishConfig
from tactiled.core.events import SlideResult
from tactiled.service.publish import Publisher

FS, N, BATCHES, SENSOR = 20_000.0, 400, 8, "tip7"
VPC = 5.0 / 32768
LOST = {2: [[100, 20]], 5: [[0, 30], [390, 10]]}  # batch -> lost rows inside it
GAP_BEFORE = {6: 2_000}  # batch -> samples lost before it (a gap longer than the daemon fills)


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


def plan() -> list[tuple[int, int, list[list[int]], int]]:
    """(first index, rows, lost, lost_before) of every batch."""
    out, index = [], 0
    for k in range(BATCHES):
        index += GAP_BEFORE.get(k, 0)
        out.append((index, N, LOST.get(k, []), GAP_BEFORE.get(k, 0)))
        index += N
    return out


def feed(endpoint: str, sink: Any, consume: Any) -> dict[str, Any]:
    pub = Publisher(PublishConfig(endpoint=endpoint))
    state = consume.start()  # the outlets / publishers exist before any samples: the consumer finds them now
    counting = Counting(sink)
    stop = threading.Event()
    thread = threading.Thread(target=run_bridge, args=(endpoint, counting, stop, SENSOR), daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while counting.seen == 0 and time.monotonic() < deadline:  # slow joiner: until the bridge has a message
        pub.publish(schema.status(SENSOR, state=schema.STATE_IDLE))
        stop.wait(0.05)  # publishing period while waiting for the subscription, not synchronisation
    while not consume.ready(state) and time.monotonic() < deadline + 30:  # the consumer hears the bridge: status until it does
        pub.publish(schema.status(SENSOR, state=schema.STATE_IDLE, level=[0.01, 0.02]))

    clock = ClockMap(FS)
    base = time.monotonic()
    rng = np.random.default_rng(1)
    batches = plan()
    total = batches[-1][0] + N
    counts = rng.integers(-3000, 3000, (total, 2)).astype(np.int16)
    sent = []
    for k, (index, n, lost, lost_before) in enumerate(batches):
        late = 0.0318 if k == 0 else float(rng.uniform(0, 0.003))  # the first read later than the rest
        clock.observe(index + n, base + (index + n) / FS + 0.002 + late)
        rows = counts[index:index + n].copy()
        for p, c in lost:
            rows[p:p + c] = 0
        msg = schema.samples(SENSOR, index, rows.astype("<i2").tobytes(), n, 2, fs=FS, volts_per_count=VPC, lost=lost,
                             lost_before=lost_before, to_host=clock.host, fs_clock=round(clock.rate(index, index + n), 3))
        pub.publish(msg)
        sent.append({"index": index, "n": n, "index_mono": msg.index_mono, "index_unix": msg.index_unix, "fs_clock": msg.fs_clock})
    for final, label in ((False, "Ra1.00"), (True, "Ra1.18"), (True, None)):
        r = SlideResult(4, 500, 2000, (1000, 1800), label, None if label else "low_confidence", 0.8, [("Ra1.18", 0.8)], {"samples": 800},
                        final=final, used_s=0.05, novelty=0.4)
        msg = schema.roughness(SENSOR, r, fs=FS, model="m", version="t", to_host=clock.host)
        msg.extra = {"grip_force_n": 1.5}  # a field of a newer daemon than the bridge knows: passed on all the same
        pub.publish(msg)
    got = consume.collect(state)
    stop.set()
    thread.join(10)
    pub.close()
    return {"got": got, "counts": counts.tolist(), "batches": batches, "sent": sent, "fs": FS, "vpc": VPC,
            "stop_mono": clock.mono(2000), "stop_unix": clock.host(2000)[1]}


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
            labels.append((ch.child_value("label"), ch.child_value("unit"), ch.child_value("scale")))
            ch = ch.next_sibling()
        acq = info.desc().child("acquisition")
        acquisition = {k: acq.child_value(k) for k in ("manufacturer", "sensor_id", "fs_firmware", "volts_per_count", "model_fingerprint")}
        return inlets, {"channels": info.channel_count(), "nominal": info.nominal_srate(), "labels": labels, "type": info.type(),
                        "acquisition": acquisition, "resolved_before_samples": True}

    def ready(self, state: Any) -> bool:
        return True  # open_stream returned: the inlets are connected

    def collect(self, state: Any) -> dict[str, Any]:
        (raw, marks), meta = state
        values: list[list[float]] = []
        stamps: list[float] = []
        markers: list[tuple[str, float]] = []
        deadline = time.monotonic() + 30
        want = BATCHES * N - sum(c for lost in LOST.values() for _, c in lost)
        while (len(values) < want or sum('"roughness"' in m for m, _ in markers) < 3) and time.monotonic() < deadline:
            chunk, ts = raw.pull_chunk(timeout=0.2)
            values += chunk
            stamps += ts
            m, mts = marks.pull_chunk(timeout=0.0)
            markers += [(x[0], t) for x, t in zip(m, mts, strict=True)]
        return {**meta, "values": values, "stamps": stamps, "markers": markers}


class Ros2Consumer:
    NS = "/robot1"  # the bridge runs with --ros-args -r __ns:=/robot1 -p sensor_id:=tip7 -p frame_id:=tip_link

    def start(self) -> Any:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2
        from std_msgs.msg import String

        from tactiled.apps.bridges.ros2 import table_dtype

        self.rclpy = rclpy
        node = rclpy.create_node("tactiled_test_consumer")
        got: dict[str, list[Any]] = {"samples": [], "label": [], "json": [], "status": [], "diag": []}
        base = f"{self.NS}/tactiled/{SENSOR}"

        def cloud(m: Any) -> None:
            rows = np.frombuffer(bytes(m.data), dtype=table_dtype(2))
            got["samples"].append({"stamp": m.header.stamp.sec + m.header.stamp.nanosec * 1e-9, "frame": m.header.frame_id,
                                   "fields": [(f.name, f.offset, f.datatype) for f in m.fields], "dense": m.is_dense,
                                   "width": m.width, "film1": rows["film1"].tolist(), "film2": rows["film2"].tolist(),
                                   "t": rows["t"].tolist(), "index": rows["index"].tolist()})

        # best effort, as the bridge offers; a deep history: this consumer spins only after the burst (the default 5 would drop 3)
        node.create_subscription(PointCloud2, f"{base}/samples", cloud, QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT))
        node.create_subscription(String, f"{base}/roughness", lambda m: got["label"].append(m.data), 10)
        node.create_subscription(String, f"{base}/roughness/json", lambda m: got["json"].append(json.loads(m.data)), 10)
        node.create_subscription(String, f"{base}/status", lambda m: got["status"].append(json.loads(m.data)), 10)
        node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: got["diag"].append(
            [(s.name, s.message, {kv.key: kv.value for kv in s.values}) for s in m.status]), 10)
        deadline = time.monotonic() + 30  # until the bridge's samples publisher is matched (discovery on loopback)
        while node.count_publishers(f"{base}/samples") == 0 and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
        got["publishers_before_samples"] = [node.count_publishers(f"{base}/samples")]
        return node, got

    def ready(self, state: Any) -> bool:
        node, got = state
        self.rclpy.spin_once(node, timeout_sec=0.1)
        return bool(got["diag"]) and bool(got["status"])

    def collect(self, state: Any) -> dict[str, Any]:
        node, got = state
        deadline = time.monotonic() + 30

        def done() -> bool:  # the last batch and the three roughness messages are in
            last = plan()[-1][0]
            return any(s["index"][0] == last for s in got["samples"]) and len(got["json"]) >= 3

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

        out = feed(endpoint, LslSink(StreamMeta(SENSOR, 2, FS, VPC, model="abc123", version="t")), LslConsumer())
    else:
        import rclpy

        from tactiled.apps.bridges.ros2 import Ros2Sink

        sink = Ros2Sink("ignored", endpoint, ["-r", f"__ns:={Ros2Consumer.NS}", "-p", f"sensor_id:={SENSOR}", "-p", "frame_id:=tip_link"])
        out = feed(endpoint, sink, Ros2Consumer())
        out["sink"] = {"sensor": sink.sensor, "endpoint": sink.endpoint, "frame_id": sink.frame_id}
        if rclpy.ok():
            rclpy.shutdown()
    out["interfaces"] = interfaces
    print(json.dumps(out))


if __name__ == "__main__":
    main()
