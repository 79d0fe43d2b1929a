"""``tactiled lsl`` and ``tactiled ros2``: make the sink, then bridge until SIGTERM or SIGINT."""

from __future__ import annotations

import threading
from typing import Any

from tactiled.apps.bridges import StreamMeta, _say, first_status, run_bridge
from tactiled.config import subscribe_endpoint


def serve(kind: str, config: Any, connect: str | None = None, sensor_id: str | None = None, *, nan_lost: bool = False,
          ros_args: list[str] | None = None, status_wait_s: float = 2.0, curve: tuple[str, str] | None = None) -> int:
    """``tactiled lsl`` / ``tactiled ros2``: make the sink at once, then bridge until SIGTERM or SIGINT; returns the exit code (0).

    ``config``: a :class:`tactiled.config.Config` (endpoint, sensor id, channels, rate and scale
    before the daemon says otherwise); ``curve``: the daemon's CURVE certificates, as a subscriber takes them. LSL waits
    up to ``status_wait_s`` for the daemon's first
    status, for the model fingerprint in the stream description.
    """
    import signal

    endpoint = connect or subscribe_endpoint(config, sensor_id)
    sensor = sensor_id or config.sensor.id
    sink: Any
    if kind == "lsl":
        from tactiled.apps.bridges.lsl import LslSink

        s = config.sensor
        first = first_status(endpoint, sensor, status_wait_s, curve)
        meta = StreamMeta(sensor, s.channels, first.fs_nominal if first and first.fs_nominal else s.fs, s.volts_per_count,
                          first.model if first else "", first.version if first else "")
        sink = LslSink(meta, nan_lost=nan_lost)
        raw_name = f"outlet tactiled-{sensor} (raw samples)"
    else:
        from tactiled.apps.bridges.ros2 import Ros2Sink

        sink = Ros2Sink(sensor, endpoint, ros_args)
        endpoint, sensor = sink.endpoint or endpoint, sink.sensor  # the node's parameters may say otherwise
        raw_name = f"topic tactiled/{sensor}/samples"
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    _say(f"{kind} bridge for sensor {sensor} from {endpoint}")
    run_bridge(endpoint, sink, stop, sensor, raw_name=raw_name, curve=curve)
    return 0
