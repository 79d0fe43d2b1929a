"""The wire schema: every field a writer can send is in the schema module and documented in docs/messages.md."""

from __future__ import annotations

import json
import re
import threading
from dataclasses import fields
from pathlib import Path

import pytest
from tactiled_client import schema

from tactiled.config import Config
from tactiled.core.events import SlideResult
from tactiled.files.recording import Recording, save_recording
from tactiled.learn.model import load_model
from tactiled.run.replay import by_slide, replay_recording, result_record
from tactiled.sim.physics import SimParams, pick_surfaces, simulate_file
from tests.conftest import REPO, run_cli


def documented_fields() -> set[str]:
    """Backquoted names in the first column of every table of docs/messages.md."""
    names: set[str] = set()
    for line in (REPO / "docs" / "messages.md").read_text().splitlines():
        if line.startswith("| `"):
            names.update(re.findall(r"`([a-z_]+)`", line.split("|")[1]))
    return names


def test_every_wire_field_is_documented() -> None:
    documented = documented_fields()
    for cls in (*schema.MESSAGE_TYPES.values(), schema.ReplaySlide, schema.ProvisionalLabel):
        names = {f.name for f in fields(cls)} - {"extra", "missed"}
        assert names <= documented, f"{cls.__name__}: undocumented {sorted(names - documented)}"


def test_builders_write_only_schema_fields() -> None:
    r = SlideResult(3, 1000, 9000, (7000, 9000), None, "low_confidence", 0.3, [("a", 0.3)], {"samples": 2000}, final=False, used_s=0.4)

    def host(i: int) -> tuple[float, float]:
        return i / 20_000, 1e9 + i / 20_000

    built = [schema.roughness("s", r, fs=20_000.0, model="m", version="0", to_host=host), schema.slide_start("s", 3, 1000, 20_000.0),
             schema.slide_end("s", 3, 1000, 9000, schema.END_QUIET, 20_000.0, host), schema.status("s", state=schema.STATE_IDLE),
             schema.samples("s", 5, b"\0" * 8, 2, 2, fs=20_000.0, volts_per_count=1.0, lost=[[1, 1]], to_host=host)]
    for msg in built:
        body = msg.to_map()
        assert set(body) <= msg.wire_fields() and msg.type in schema.TOPICS
        back = schema.parse(schema.topic(msg.type, "s"), body)
        assert back == msg and back.extra == {}
    newer = {**built[0].to_map(), "grip_force_n": 1.5, "tags": ["a"]}  # fields of a newer daemon: kept when passed on
    back = schema.parse(schema.topic(schema.ROUGHNESS, "s"), newer)
    assert back.extra == {"grip_force_n": 1.5, "tags": ["a"]} and back.to_map() == newer
    start = built[1].to_map()
    assert "stop" not in start and "reason" not in start  # absent on start, as documented
    rough = built[0]
    assert isinstance(rough, schema.Roughness) and rough.final is False and rough.used_s == 0.4 and rough.stop_mono == 9000 / 20_000


def test_encode_reuses_a_packer_per_thread_and_recovers_from_a_failed_message() -> None:
    body = schema.status("s", state=schema.STATE_IDLE).to_map()
    first = schema.encode(schema.STATUS, "s", body)
    with pytest.raises(TypeError):
        schema.encode(schema.STATUS, "s", {**body, "bad": object()})
    assert schema.encode(schema.STATUS, "s", body) == first  # nothing of the failed message left in the buffer
    results: dict[int, list[bytes]] = {}

    def encode_in_thread(n: int) -> None:
        results[n] = [schema.encode(schema.STATUS, "s", {**body, "seq": n})[1] for _ in range(200)]

    threads = [threading.Thread(target=encode_in_thread, args=(n,)) for n in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    assert sorted(results) == [0, 1, 2, 3]
    for n, payloads in results.items():
        assert {schema.decode([b"status/s", p])[1]["seq"] for p in payloads} == {n}


def test_replay_json_is_one_line_per_slide_with_its_provisional_labels(tmp_path: Path) -> None:
    params = SimParams()
    sim = simulate_file(params, pick_surfaces("Ra2.29")[0], 2, 4)
    rec = Recording(sim.samples, params.fs, params.volts_per_count)
    save_recording(tmp_path / "r.npz", rec)
    res = run_cli("replay", "--json", str(tmp_path / "r.npz"))
    assert res.returncode == 0, res.stderr
    lines = [json.loads(line) for line in res.stdout.splitlines()]
    assert len(lines) == 2
    for obj in lines:
        assert set(obj) <= schema.ReplaySlide.wire_fields() and obj["final"] is True and obj["file"].endswith("r.npz")
    # provisional results (the pipeline's, while a slide goes on) fold into their slide's line
    finals = [r for r in replay_recording(rec, Config(), load_model()) if r.final]
    early = [SlideResult(**{**f.__dict__, "final": False, "used_s": 0.25, "label": "x"}) for f in finals]
    grouped = by_slide([early[0], early[1], finals[0], finals[1]])
    assert [(r.slide_id, [p.used_s for p in ps]) for r, ps in grouped] == [(0, [0.25]), (1, [0.25])]
    line = result_record("r.npz", rec, grouped[0][0], grouped[0][1]).to_map()
    assert line["provisional"] == [{"label": "x", "confidence": early[0].confidence, "used_s": 0.25, "top": [list(t) for t in early[0].top],
                                    "reason": early[0].reason, "novelty": early[0].novelty, "stop": early[0].stop,
                                    "quality": {**early[0].quality, "compute_ms": round(early[0].compute_ms, 3)}}]
    assert json.loads(json.dumps(line))["provisional"][0]["label"] == "x"
