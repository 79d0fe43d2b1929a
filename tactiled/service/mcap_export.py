"""Recordings as MCAP files (JSON message encoding with JSON schemas) for Foxglove and PlotJuggler.

Channels, for sensor ``<id>``:

- ``/tactiled/<id>/samples``: the raw samples in batches of ``batch`` rows: ``index``, ``n``,
  ``fs``, ``volts_per_count``, ``lost`` ([[position, count], ...] as on the samples topic),
  and ``film1`` … ``filmC`` (volts, lost samples 0.0);
- ``/tactiled/<id>/slides``: the recording's ground-truth slides (``start``, ``stop`` as file
  positions, ``t_start``, ``t_stop``, ``surface``, ``ra_um``);
- ``/tactiled/<id>/roughness``: the pipeline's results, one roughness message per slide (and
  provisional ones), built by :func:`tactiled_client.schema.roughness`.

``log_time`` and ``publish_time`` are the sensor clock: sample position / fs, in ns (the file
holds no host time); for samples the time of the batch's first row, for slides and labels
the slide's onset.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tactiled_client import schema

from tactiled import __version__
from tactiled.core.pipeline import SlideResult
from tactiled.errors import TactiledError
from tactiled.extras import need
from tactiled.files.recording import Recording

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


def export_mcap(rec: Recording, out: str | Path, *, sensor: str = "fingertip0", results: Sequence[SlideResult] = (), model: str = "",
                batch: int = BATCH) -> dict[str, int]:
    """Write ``rec`` (and the pipeline's ``results``, positions in the file) to ``out``; returns messages per channel."""
    writer_mod = need("mcap.writer", "mcap")
    if batch < 1:
        raise TactiledError(f"--batch: must be >= 1, got {batch}")
    volts = rec.volts()
    valid = rec.valid_mask()
    volts[~valid] = 0.0
    n, channels = volts.shape
    lost = np.asarray(rec.lost, dtype=np.int64).reshape(-1, 2)
    counts = {"samples": 0, "slides": 0, "roughness": 0}

    def ns(position: int) -> int:
        return round((rec.first_index + position) / rec.fs * 1e9)

    with open(out, "wb") as fh:
        writer = writer_mod.Writer(fh, compression=writer_mod.CompressionType.ZSTD)
        writer.start(profile="", library=f"tactiled {__version__}")
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

        def put(kind: str, position: int, body: dict[str, Any]) -> None:
            t = ns(position)
            writer.add_message(chan[kind], log_time=t, publish_time=t, data=json.dumps(body).encode(), sequence=counts[kind])
            counts[kind] += 1

        lost = lost[np.argsort(lost[:, 0], kind="stable")] if len(lost) else lost
        first = 0  # the first lost range that may still reach the current batch: one sweep, linear in batches + ranges
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
            body: dict[str, Any] = {"index": rec.first_index + lo, "n": hi - lo, "fs": rec.fs, "volts_per_count": rec.volts_per_count,
                                    "lost": inside}
            for k, name in enumerate(film):
                body[name] = volts[lo:hi, k].tolist()
            put("samples", lo, body)
        ra = rec.ra_um.tolist() if rec.ra_um is not None else None
        for k, (start, stop, surface) in enumerate(rec.slides()):
            put("slides", start, {"start": start, "stop": stop, "t_start": start / rec.fs, "t_stop": stop / rec.fs, "surface": surface,
                                  "ra_um": None if ra is None else ra[k]})
        for r in results:
            put("roughness", r.start, schema.roughness(sensor, r, fs=rec.fs, model=model, version=__version__).to_map())
        writer.finish()
    return counts


def read_mcap_samples(path: str | Path) -> tuple[np.ndarray, np.ndarray, int, float]:
    """(volts (n, C), valid (n,), first index, fs) from the samples channel of an MCAP file written by :func:`export_mcap`."""
    make_reader = need("mcap.reader", "mcap").make_reader
    rows: list[np.ndarray] = []
    valid: list[np.ndarray] = []
    first, fs = 0, 0.0
    with open(path, "rb") as fh:
        for _schema, channel, message in make_reader(fh).iter_messages():
            if not channel.topic.endswith("/samples"):
                continue
            body = json.loads(message.data)
            if not rows:
                first, fs = body["index"], body["fs"]
            films = sorted((k for k in body if k.startswith("film")), key=lambda k: int(k[4:]))
            rows.append(np.column_stack([body[k] for k in films]))
            ok = np.ones(body["n"], dtype=bool)
            for p, c in body["lost"]:
                ok[p:p + c] = False
            valid.append(ok)
    if not rows:
        raise TactiledError(f"{path}: no samples channel")
    return np.concatenate(rows), np.concatenate(valid), first, fs
