"""A tactiled MCAP file (``tactiled export``, ``record --format mcap``; JSON profile) read back as a :class:`Recording`.

The samples channel gives the rows (volts; lost rows marked in each message's ``lost``), the slides channel the ground
truth, the disconnected channel the positions where the port was lost (``Recording.disconnected``), the
``tactiled.recording`` metadata record the rate, scale, label, first index, meta and the samples' dtype (integer counts
come back as the same counts). The arrays then go through the same validation as an ``.npz`` recording, so ``tactiled
replay rec.mcap`` labels the slides exactly as ``tactiled replay rec.npz`` does. A ROS 2 bag (``export --profile
ros2``) is refused in one line: its samples are float32.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from tactiled_client.mcapbound import inflation_problem

from tactiled.errors import RecordingError
from tactiled.extras import need
from tactiled.files.recording import INT64_MAX, MAX_RECORDING_BYTES, Recording, validate_arrays, volts_per_count_problem
from tactiled.readable import file_problem


def load_mcap_recording(path: str | Path) -> Recording:
    """The recording an MCAP file written by tactiled's JSON export holds; :class:`RecordingError` names file and problem."""
    p = Path(path)
    problem = file_problem(p, MAX_RECORDING_BYTES)
    if problem is not None:
        raise RecordingError(f"{p}: {problem}")
    make_reader = need("mcap.reader", "mcap").make_reader
    try:
        with open(p, "rb") as fh:
            problem = inflation_problem(fh, MAX_RECORDING_BYTES)
            if problem is not None:
                raise RecordingError(f"{p}: {problem}")
            reader = make_reader(fh)
            header = reader.get_header()
            if header.profile == "ros2":
                raise RecordingError(f"{p}: a ROS 2 bag (export --profile ros2, float32 samples); replay reads the JSON export")
            info = next((m.metadata for m in reader.iter_metadata() if m.name == "tactiled.recording"), None)
            if info is None:
                raise RecordingError(f"{p}: not a tactiled MCAP file (no tactiled.recording metadata)")
            fs, vpc, dtype, first = _recording_info(p, info)
            fh.seek(0)
            rows, lost, slides, marks = _messages(p, make_reader(fh), first)
    except RecordingError:
        raise
    except Exception as exc:  # the mcap reader's own errors (bad magic, truncated records) and malformed JSON
        raise RecordingError(f"{p}: not a readable MCAP file ({type(exc).__name__}: {exc})") from None
    if not rows:  # a recording of no samples has no samples message: its channels are in the metadata
        try:
            rows = [np.zeros((0, int(info["channels"])))]
        except (KeyError, ValueError):
            raise RecordingError(f"{p}: samples: no samples messages, and no channel count in the metadata") from None
    volts = np.concatenate(rows)
    if dtype.kind == "i":
        info_i = np.iinfo(dtype)  # rint of a count within [min - 0.5, max + 0.5) is one the dtype holds: -32768 too (a clipped ADC)
        low, high = (float(volts.min()) / vpc, float(volts.max()) / vpc) if volts.size else (0.0, 0.0)
        if not (info_i.min - 0.5 <= low and high < info_i.max + 0.5):
            bad = low if low < info_i.min - 0.5 else high
            raise RecordingError(f"{p}: samples: {bad:.6g} counts at volts_per_count {vpc!r}, beyond the {dtype} of samples_dtype")
    samples = np.rint(volts / vpc).astype(dtype) if dtype.kind == "i" else volts
    arrays: dict[str, Any] = {"samples": samples, "fs": np.float64(fs), "volts_per_count": np.float64(vpc if dtype.kind == "i" else 1.0),
                              "first_index": np.int64(first),
                              "lost": np.asarray(lost, dtype=np.int64).reshape(-1, 2), "meta": np.str_(info.get("meta", "{}"))}
    if marks:
        arrays["disconnected"] = np.array(marks, dtype=np.int64)
    if info.get("label"):
        arrays["label"] = np.str_(info["label"])
    if slides:
        arrays["slide_start"] = np.array([s[0] for s in slides], dtype=np.int64)
        arrays["slide_stop"] = np.array([s[1] for s in slides], dtype=np.int64)
        if any(s[2] is not None for s in slides):
            arrays["surface"] = np.array([s[2] or "" for s in slides], dtype=np.str_)
        if all(s[3] is not None for s in slides):
            arrays["ra_um"] = np.array([s[3] for s in slides], dtype=np.float64)
    return validate_arrays(p, arrays)


def _recording_info(p: Path, info: dict[str, str]) -> tuple[float, float, np.dtype[Any], int]:
    """(fs in Hz, volts_per_count, the samples' dtype, first_index) of the ``tactiled.recording`` metadata ``info`` (string
    values); :class:`RecordingError` names the file ``p`` and the key that is missing or not what it must be. The ranges
    of fs and of first_index + rows are :func:`~tactiled.files.recording.validate_arrays`'s; these are what reading the
    messages needs first."""
    def number(key: str, default: str | None, kind: type[float] | type[int]) -> Any:
        text = info.get(key, default)
        if text is None:
            raise RecordingError(f"{p}: metadata tactiled.recording: {key}: missing (required)")
        try:
            return kind(text)
        except (TypeError, ValueError):
            raise RecordingError(f"{p}: metadata tactiled.recording: {key}: must be {'a number' if kind is float else 'an integer'}, "
                                 f"got {text!r:.80}") from None

    fs, vpc, first = number("fs", None, float), number("volts_per_count", "1.0", float), number("first_index", "0", int)
    if problem := volts_per_count_problem(vpc):
        raise RecordingError(f"{p}: metadata tactiled.recording: volts_per_count: {problem}")
    if not -INT64_MAX - 1 <= first <= INT64_MAX:
        raise RecordingError(f"{p}: metadata tactiled.recording: first_index: must be an int64, got {first}")
    name = info.get("samples_dtype", "float64")
    if name not in ("int16", "float32", "float64"):
        raise RecordingError(f"{p}: metadata tactiled.recording: samples_dtype: must be int16, float32 or float64, got {name!r:.80}")
    return fs, vpc, np.dtype(name), first


def _messages(p: Path, reader: Any, first: int) -> tuple[list[np.ndarray], list[list[int]], list[tuple[int, int, str | None, float | None]], list[int]]:
    """(sample blocks (n, C) in volts, lost [position, count] in the file, true slides (start, stop, surface, Ra), positions where
    the port was lost) of an MCAP reader."""
    rows: list[np.ndarray] = []
    lost: list[list[int]] = []
    slides: list[tuple[int, int, str | None, float | None]] = []
    marks: list[int] = []
    at = 0
    for _schema, channel, message in reader.iter_messages(log_time_order=False):
        body = json.loads(message.data)
        if channel.topic.endswith("/samples"):
            films = sorted((k for k in body if k.startswith("film")), key=lambda k: int(k[4:]))
            block = np.column_stack([np.asarray(body[k], dtype=np.float64) for k in films]).reshape(int(body["n"]), len(films))
            lo = int(body["index"]) - first
            if lo != at:
                raise RecordingError(f"{p}: samples: a message at row {lo} where row {at} was due")
            lost += [[lo + int(q), int(c)] for q, c in body["lost"]]
            rows.append(block)
            at += block.shape[0]
        elif channel.topic.endswith("/slides"):
            slides.append((int(body["start"]) - first, int(body["stop"]) - first, body.get("surface"), body.get("ra_um")))
        elif channel.topic.endswith("/disconnected"):
            marks.append(int(body["index"]) - first)
    return rows, lost, slides, marks
