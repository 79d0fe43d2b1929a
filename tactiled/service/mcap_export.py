"""Recordings as MCAP files (JSON message encoding with JSON schemas) for Foxglove and PlotJuggler.

Channels, for sensor ``<id>``:

- ``/tactiled/<id>/samples``: the raw samples in batches of ``batch`` rows: ``index``, ``n``,
  ``fs``, ``volts_per_count``, ``lost`` ([[position, count], ...] as on the samples topic),
  and ``film1`` … ``filmC`` (volts, lost samples 0.0);
- ``/tactiled/<id>/slides``: the recording's ground-truth slides (``start``, ``stop``, ``t_start``,
  ``t_stop``, ``surface``, ``ra_um``);
- ``/tactiled/<id>/roughness``: the pipeline's results, one roughness message per slide (and
  provisional ones), built by :func:`tactiled_client.schema.roughness`;
- ``/tactiled/<id>/disconnected``: one message per mark of the recording's ``disconnected`` key (where the host
  lost the sensor's port; :func:`disconnections`): ``index``, ``t``. Only in the export of a recording that has one.

One frame of reference: every ``index``, ``start`` and ``stop`` is the sensor's absolute sample
index (as on the wire: the recording's ``first_index`` plus the position in the file), and
``t_start`` / ``t_stop`` are those indices / fs. ``log_time`` and ``publish_time`` are host wall
time (unix ns) of the message's first sample (samples), the slide's onset (slides, labels), the mark
(disconnections: the end of the rows read before the port went away): the
recording's start (``recorded_at`` in its meta, to the second; a file without it, such as a
simulated one: the time its last sample was written, the file's modification time less its
duration) plus position / fs. The metadata record ``tactiled.recording`` says which origin was
used and carries the recording's label, meta and scale.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Sequence
from dataclasses import replace
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
from tactiled_client import schema

from tactiled import __version__
from tactiled.config import Config
from tactiled.core.events import SlideResult
from tactiled.errors import OutputError, TactiledError
from tactiled.extras import need
from tactiled.files.outputs import check_output
from tactiled.files.recording import Recording, atomic_file, load_recording, merge_ranges
from tactiled.learn.choose import ModelChoice
from tactiled.rostable import field_names, table_dtype
from tactiled.run.replay import replay_recording

BATCH = 20  # rows per samples message: one board frame (1 ms at 20 kHz)


def _type(value: Any) -> dict[str, Any]:
    if isinstance(value, bool):
        return {"type": "boolean"}
    if isinstance(value, int):
        return {"type": "integer"}
    if isinstance(value, float):
        return {"type": "number"}
    if isinstance(value, str):
        return {"type": "string"}
    if isinstance(value, list):
        return {"type": "array"}
    if isinstance(value, dict):
        return {"type": "object"}
    return {}


def json_schema(title: str, example: dict[str, Any], nullable: Sequence[str] = ()) -> bytes:
    """A JSON schema whose properties are the keys of ``example`` (types from its values; ``nullable`` may also be null)."""
    props = {}
    for key, value in example.items():
        t = _type(value)
        if key in nullable or value is None:
            t = {"type": [t["type"], "null"]} if "type" in t else {}
        props[key] = t
    return json.dumps({"title": title, "type": "object", "properties": props}).encode()


def batches(n: int, lost: np.ndarray, batch: int) -> Iterator[tuple[int, int, list[list[int]]]]:
    """(lo, hi, lost ranges inside as [[position from lo, count], ...]) of every batch of ``batch`` rows out of ``n``.

    ``lost``: (k, 2) [[position, count], ...] in the file, in any order, overlapping or not: joined first
    (:func:`~tactiled.files.recording.merge_ranges`), so one sweep is linear in batches + ranges (overlapping ranges
    kept every batch scanning all of them: 1 000 of them took 37 s for 12 s of samples).
    """
    lost = merge_ranges(lost)
    first = 0  # the first lost range that may still reach the current batch
    for lo in range(0, n, batch):
        hi = min(lo + batch, n)
        while first < len(lost) and lost[first, 0] + lost[first, 1] <= lo:
            first += 1
        inside = []
        for p, c in lost[first:]:
            if p >= hi:
                break
            if p + c > lo:
                inside.append([int(max(p, lo) - lo), int(min(p + c, hi) - max(p, lo))])
        yield lo, hi, inside


def host_origin(rec: Recording, source: str | Path | None = None) -> tuple[float, str]:
    """(unix time of the recording's first sample, s; where it comes from): ``recorded_at``, else ``source``'s mtime less the duration, else 0."""
    stamp = rec.meta.get("recorded_at")
    if isinstance(stamp, str):
        try:
            return datetime.strptime(stamp, "%Y-%m-%dT%H:%M:%S%z").timestamp(), "recorded_at"
        except ValueError:
            pass  # not the recorder's format: the file's time instead
    if source is not None:
        try:
            return os.stat(source).st_mtime - rec.samples.shape[0] / rec.fs, "file_mtime"
        except OSError:
            pass
    return 0.0, "none"


def disconnections(rec: Recording) -> list[tuple[int, dict[str, Any]]]:
    """(position in the file, message body) of each mark of ``rec.disconnected`` (d,), in order.

    The body: ``index``, the sensor's absolute index of the mark (``first_index`` + position: every sample before it
    was read before the port went away, the first one after it came after; one past the last sample when the port
    went away at the end), and ``t``, that index / fs (s, sensor time). The host time of the loss is not recorded:
    the message's log time is the mark's sample time (:func:`host_origin` + position / fs), when the last sample
    before it was taken.
    """
    return [(p, {"index": rec.first_index + p, "t": (rec.first_index + p) / rec.fs}) for p in np.asarray(rec.disconnected).tolist()]


def export_mcap(rec: Recording, out: str | Path, *, sensor: str = "fingertip0", results: Sequence[SlideResult] = (), model: str = "",
                batch: int = BATCH, source: str | Path | None = None) -> dict[str, int]:
    """Write ``rec`` (and the pipeline's ``results``, positions in the file) to ``out``; returns messages per channel.

    ``source``: the recording's file (its modification time is the host-time origin when the
    recording has no ``recorded_at``).
    """
    writer_mod = need("mcap.writer", "mcap")
    if batch < 1:
        raise TactiledError(f"--batch: must be >= 1, got {batch}")
    volts = rec.volts()
    valid = rec.valid_mask()
    volts[~valid] = 0.0
    n, channels = volts.shape
    lost = np.asarray(rec.lost, dtype=np.int64).reshape(-1, 2)
    counts = {"samples": 0, "slides": 0, "roughness": 0, "disconnected": 0}
    marks = disconnections(rec)

    origin, origin_kind = host_origin(rec, source)

    def ns(position: int) -> int:
        return round(origin * 1e9) + round(position * 1e9 / rec.fs)  # in two parts: a float of unix ns has a 256 ns grain

    with atomic_file(out) as fh:  # an export cut short (Ctrl-C, a full disk) leaves no unreadable file under its name
        writer = writer_mod.Writer(fh, compression=writer_mod.CompressionType.ZSTD)
        writer.start(profile="", library=f"tactiled {__version__}")
        writer.add_metadata("tactiled.recording", {
            "sensor": sensor, "label": rec.label or "", "fs": repr(rec.fs), "channels": str(channels), "volts_per_count": repr(rec.volts_per_count),
            "first_index": str(rec.first_index), "samples_dtype": str(rec.samples.dtype), "model": model,
            "log_time_origin": origin_kind, "log_time_origin_unix": repr(origin),
            "meta": json.dumps(rec.meta, default=str)})
        film = [f"film{k + 1}" for k in range(channels)]
        example: dict[str, Any] = {"index": 0, "n": 0, "fs": 0.0, "volts_per_count": 0.0, "lost": [], **{f: [] for f in film}}
        chan = {
            "samples": writer.register_channel(f"/tactiled/{sensor}/samples", "json",
                                               writer.register_schema("tactiled.Samples", "jsonschema", json_schema("tactiled.Samples", example))),
            "slides": writer.register_channel(f"/tactiled/{sensor}/slides", "json",
                                              writer.register_schema("tactiled.TruthSlide", "jsonschema", json_schema(
                                                  "tactiled.TruthSlide", {"start": 0, "stop": 0, "t_start": 0.0, "t_stop": 0.0, "surface": "",
                                                                          "ra_um": 0.0}, nullable=("surface", "ra_um")))),
            "roughness": writer.register_channel(f"/tactiled/{sensor}/roughness", "json", writer.register_schema(
                "tactiled.Roughness", "jsonschema", json_schema("tactiled.Roughness", schema.Roughness(0, 0, "", "").to_map(),
                                                                nullable=("label", "reason", "confidence", "start_mono", "start_unix",
                                                                          "stop_mono", "stop_unix")))),
        }
        if marks:  # only when there is one, as the recording's key
            chan["disconnected"] = writer.register_channel(f"/tactiled/{sensor}/disconnected", "json", writer.register_schema(
                "tactiled.Disconnected", "jsonschema", json_schema("tactiled.Disconnected", marks[0][1])))

        def put(kind: str, position: int, body: dict[str, Any]) -> None:
            t = ns(position)
            writer.add_message(chan[kind], log_time=t, publish_time=t, data=json.dumps(body).encode(), sequence=counts[kind])
            counts[kind] += 1

        for lo, hi, inside in batches(n, lost, batch):
            body: dict[str, Any] = {"index": rec.first_index + lo, "n": hi - lo, "fs": rec.fs, "volts_per_count": rec.volts_per_count,
                                    "lost": inside}
            for k, name in enumerate(film):
                body[name] = volts[lo:hi, k].tolist()
            put("samples", lo, body)
        ra = rec.ra_um.tolist() if rec.ra_um is not None else None
        base = rec.first_index
        for k, (start, stop, surface) in enumerate(rec.slides()):
            put("slides", start, {"start": base + start, "stop": base + stop, "t_start": (base + start) / rec.fs, "t_stop": (base + stop) / rec.fs,
                                  "surface": surface, "ra_um": None if ra is None else ra[k]})
        for r in results:  # positions in the file -> sensor indices, as the daemon publishes them
            at = replace(r, start=base + r.start, stop=base + r.stop, window=(base + r.window[0], base + r.window[1]))
            # logged when it could first have been published: at the end of what it read (a provisional label's windows, a
            # final label's slide), as the ROS 2 profile and a replay's JSON place it; not at the slide's onset
            msg = schema.roughness(sensor, at, fs=rec.fs, model=r.model or model, version=__version__)
            put("roughness", r.stop, as_sent(msg, counts["roughness"], ns(r.stop)))
        for position, body in marks:
            put("disconnected", position, body)
        writer.finish()
    return counts


def read_mcap_samples(path: str | Path) -> tuple[np.ndarray, np.ndarray, int, float]:
    """(volts (n, C), valid (n,), first index, fs) of an MCAP file written by :func:`export_mcap` (lost rows zero)."""
    from tactiled.files.mcap_read import load_mcap_recording

    rec = load_mcap_recording(path)
    valid = rec.valid_mask()
    volts = rec.volts()
    volts[~valid] = 0.0
    return volts, valid, rec.first_index, rec.fs


ROS2_BATCH = 500  # rows per PointCloud2 with --profile ros2 (25 ms at 20 kHz; the live bridge sends about 800)


def export_ros2_mcap(rec: Recording, out: str | Path, *, sensor: str = "fingertip0", results: Sequence[SlideResult] = (), model: str = "",
                     batch: int = ROS2_BATCH, source: str | Path | None = None) -> dict[str, int]:
    """Write ``rec`` as a ROS 2 bag in one MCAP file (profile ``ros2``, ``ros2msg`` schemas, CDR), the topics of ``tactiled ros2``.

    ``/tactiled/<id>/samples`` sensor_msgs/PointCloud2 (the bridge's table: film volts, NaN when
    lost, ``t``, ``index``), ``/tactiled/<id>/roughness`` std_msgs/String (final labels),
    ``/tactiled/<id>/roughness/json``, ``/tactiled/<id>/slides`` and (a recording with a ``disconnected`` mark only)
    ``/tactiled/<id>/disconnected`` std_msgs/String (JSON: :func:`disconnections`).
    Stamps and log times are host time as in :func:`export_mcap`; indices absolute. Needs
    ``rosbags`` (extra ``tactiled[ros2bag]``) for the message definitions and CDR; no ROS install.
    Returns messages per topic kind.
    """
    writer_mod = need("mcap.writer", "ros2bag")
    typesys = need("rosbags.typesys", "ros2bag")
    if batch < 1:
        raise TactiledError(f"--batch: must be >= 1, got {batch}")
    ts = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    cloud_t, field_t = ts.types["sensor_msgs/msg/PointCloud2"], ts.types["sensor_msgs/msg/PointField"]
    header_t, time_t, string_t = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"], ts.types["std_msgs/msg/String"]
    volts = rec.volts()
    valid = rec.valid_mask()
    n, channels = volts.shape
    lost = np.asarray(rec.lost, dtype=np.int64).reshape(-1, 2)
    origin, origin_kind = host_origin(rec, source)
    base = rec.first_index
    fields = [field_t(name=x, offset=o, datatype=d, count=1) for x, o, d in field_names(channels)]
    counts = {"samples": 0, "slides": 0, "roughness": 0, "disconnected": 0}
    marks = disconnections(rec)

    def ns(position: int) -> int:
        return round(origin * 1e9) + round(position * 1e9 / rec.fs)  # in two parts: a float of unix ns has a 256 ns grain

    with atomic_file(out) as fh:  # an export cut short (Ctrl-C, a full disk) leaves no unreadable file under its name
        writer = writer_mod.Writer(fh, compression=writer_mod.CompressionType.ZSTD)
        writer.start(profile="ros2", library=f"tactiled {__version__}")
        writer.add_metadata("tactiled.recording", {
            "sensor": sensor, "label": rec.label or "", "fs": repr(rec.fs), "channels": str(channels), "volts_per_count": repr(rec.volts_per_count),
            "first_index": str(base), "model": model, "log_time_origin": origin_kind, "log_time_origin_unix": repr(origin),
            "meta": json.dumps(rec.meta, default=str)})
        schemas: dict[str, int] = {}
        seq: dict[str, int] = {}

        def channel(topic: str, typename: str) -> int:
            if typename not in schemas:
                text, _ = ts.generate_msgdef(typename, ros_version=2)
                schemas[typename] = writer.register_schema(typename, "ros2msg", text.encode())
            return int(writer.register_channel(topic, "cdr", schemas[typename]))

        topic = f"/tactiled/{sensor}"
        chan = {"samples": channel(f"{topic}/samples", "sensor_msgs/msg/PointCloud2"),
                "label": channel(f"{topic}/roughness", "std_msgs/msg/String"),
                "roughness": channel(f"{topic}/roughness/json", "std_msgs/msg/String"),
                "slides": channel(f"{topic}/slides", "std_msgs/msg/String")}
        if marks:  # only when there is one, as the recording's key
            chan["disconnected"] = channel(f"{topic}/disconnected", "std_msgs/msg/String")

        def put(kind: str, position: int, msg: Any, typename: str) -> None:
            t = ns(position)
            writer.add_message(chan[kind], log_time=t, publish_time=t, data=bytes(ts.serialize_cdr(msg, typename)), sequence=seq.get(kind, 0))
            seq[kind] = seq.get(kind, 0) + 1

        def stamp(position: int) -> Any:
            t = ns(position)
            return header_t(stamp=time_t(sec=t // 1_000_000_000, nanosec=t % 1_000_000_000), frame_id=sensor)

        step = table_dtype(channels).itemsize
        for lo, hi, inside in batches(n, lost, batch):
            rows = np.zeros(hi - lo, dtype=table_dtype(channels))
            ok = valid[lo:hi]
            for k in range(channels):
                rows[f"film{k + 1}"] = np.where(ok, volts[lo:hi, k], np.nan)
            rows["t"] = np.arange(hi - lo) / rec.fs
            rows["index"] = base + lo + np.arange(hi - lo, dtype=np.float64)
            cloud = cloud_t(header=stamp(lo), height=1, width=hi - lo, fields=fields, is_bigendian=False, point_step=step,
                            row_step=step * (hi - lo), data=np.frombuffer(rows.tobytes(), dtype=np.uint8), is_dense=not inside)
            put("samples", lo, cloud, "sensor_msgs/msg/PointCloud2")
            counts["samples"] += 1
        ra = rec.ra_um.tolist() if rec.ra_um is not None else None
        for k, (start, stop, surface) in enumerate(rec.slides()):
            body = {"start": base + start, "stop": base + stop, "t_start": (base + start) / rec.fs, "t_stop": (base + stop) / rec.fs,
                    "surface": surface, "ra_um": None if ra is None else ra[k]}
            put("slides", start, string_t(data=json.dumps(body)), "std_msgs/msg/String")
            counts["slides"] += 1
        for r in results:
            at = replace(r, start=base + r.start, stop=base + r.stop, window=(base + r.window[0], base + r.window[1]))
            msg = schema.roughness(sensor, at, fs=rec.fs, model=r.model or model, version=__version__)
            if msg.final:
                put("label", r.stop, string_t(data=msg.label or ""), "std_msgs/msg/String")
            put("roughness", r.stop, string_t(data=json.dumps(as_sent(msg, counts["roughness"], ns(r.stop)))), "std_msgs/msg/String")
            counts["roughness"] += 1
        for position, body in marks:
            put("disconnected", position, string_t(data=json.dumps(body)), "std_msgs/msg/String")
            counts["disconnected"] += 1
        writer.finish()
    return counts


def as_sent(msg: schema.Message, seq: int, t_ns: int) -> dict[str, Any]:
    """``msg``'s map stamped as the daemon stamps what it sends: the ``seq``-th of its topic (from 0), ``time_unix`` its log
    time ``t_ns`` (unix ns), so that a replay of the file counts no gap and ages a label as a subscriber would."""
    msg.seq, msg.time_unix = seq, t_ns / 1e9
    return msg.to_map()


def export_recording(path: str | Path, output: str | Path, config: Config, choice: ModelChoice, *, batch: int | None = None,
                     profile: str = "json", force: bool = False) -> dict[str, int]:
    """Recording ``path`` → MCAP ``output`` (``profile`` json: :func:`export_mcap`; ros2: :func:`export_ros2_mcap`), with the
    results of the daemon's pipeline under the model ``choice`` gives; returns the message counts. ``output`` is checked
    first (:func:`~tactiled.files.outputs.check_output`; an existing file is replaced only with ``force``) and is never
    ``path`` itself (:class:`~tactiled.errors.OutputError`)."""
    if Path(output).resolve() == Path(path).resolve():
        raise OutputError(f"{output}: is the recording being exported; write the MCAP file elsewhere")
    check_output(output, force, (".mcap",))
    if profile == "ros2":
        need("rosbags.typesys", "ros2bag")  # before the replay, not after it
    rec = load_recording(path)
    model = choice.for_stream(rec.fs, rec.channels, str(path))
    results = replay_recording(rec, config, model)
    write, default = (export_ros2_mcap, ROS2_BATCH) if profile == "ros2" else (export_mcap, BATCH)
    return write(rec, output, sensor=str(rec.meta.get("sensor", config.sensor.id)), results=results,
                 model=getattr(model, "fingerprint", ""), batch=batch or default, source=path)
