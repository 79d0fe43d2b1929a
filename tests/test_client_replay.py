"""The client library records and replays sessions: same API as live, onto a socket, with the light client alone."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import msgpack
import numpy as np
import pytest
from tactiled_client import BlockingReplay, BlockingSubscriber, EndOfLog, LogError, NoData, Replay, Roughness, Slide, schema
from tactiled_client.log import HEADER, RECORD, LogReader, LogWriter

from tests.conftest import REPO, run_cli, tactiled_cmd


def _body(kind: str, seq: int, sensor: str = "s0", **fields: object) -> bytes:
    out: bytes = msgpack.packb({"v": schema.SCHEMA_VERSION, "seq": seq, "sensor": sensor, "type": kind, **fields}, use_bin_type=True)
    return out


def _session(path: Path) -> list[list[bytes]]:
    """A small log: slide start, two roughness labels, a slide end, a status, over 0.4 s of recorded time."""
    frames = [[b"slide/s0", _body("slide", 0, event="start", slide_id=0, start=100)],
              [b"roughness/s0", _body("roughness", 0, label="Ra1.00", confidence=0.6, final=False)],
              [b"slide/s0", _body("slide", 1, event="end", slide_id=0, start=100, stop=900)],
              [b"roughness/s0", _body("roughness", 1, label="Ra1.18", confidence=0.7, final=True)],
              [b"status/s1", _body("status", 0, "s1", state="idle")]]
    with LogWriter(path) as log:
        for i, f in enumerate(frames):
            log.write(f, 1000.0 + 0.1 * i, 1.7e9 + 0.1 * i)
    return frames


def test_blocking_replay_gives_every_message_exactly_and_in_order(tmp_path: Path) -> None:
    frames = _session(tmp_path / "s.tlog")
    with BlockingReplay(tmp_path / "s.tlog", speed=None) as rep:
        got = list(rep)
    assert [schema.topic(m.type, m.sensor) for m in got] == [f[0].decode() for f in frames]
    for m, f in zip(got, frames, strict=True):  # every field as sent
        sent = msgpack.unpackb(f[1])
        assert {k: m.extra[k] if k in m.extra else getattr(m, k) for k in sent} == sent
    with BlockingReplay(tmp_path / "s.tlog", topics=["roughness"], speed=None) as rep:
        assert [m.label for m in rep if isinstance(m, Roughness)] == ["Ra1.00", "Ra1.18"]
    with BlockingReplay(tmp_path / "s.tlog", sensor="s1", topics=["status"], speed=None) as rep:
        assert [m.type for m in rep] == ["status"]


def test_async_replay_paces_filters_and_ends(tmp_path: Path) -> None:
    _session(tmp_path / "s.tlog")

    async def run() -> None:
        async with Replay(tmp_path / "s.tlog", topics=["roughness", "slide"], speed=20.0) as sub:
            first = await sub.receive()
            assert isinstance(first, Slide) and first.event == "start"
            with pytest.raises(NoData):  # the next is 0.1 s of recorded time away: 5 ms at speed 20
                await sub.receive(timeout=0.001)
            labels = [m async for m in sub if isinstance(m, Roughness)]
            assert [m.label for m in labels] == ["Ra1.00", "Ra1.18"]
            assert sub.latest(max_age_s=1.0) is labels[-1]
            with pytest.raises(EndOfLog):
                await sub.receive()

    asyncio.run(run())


def test_replay_before_entering_is_a_client_error(tmp_path: Path) -> None:
    from tactiled_client import ClientError

    _session(tmp_path / "s.tlog")

    async def run() -> None:
        with pytest.raises(ClientError, match="before entering"):
            await Replay(tmp_path / "s.tlog").receive()

    asyncio.run(run())
    with pytest.raises(ClientError, match="unknown topic"):
        BlockingReplay(tmp_path / "s.tlog", topics=["nope"])


def test_a_killed_recorder_leaves_a_file_that_replays_to_its_last_complete_message(tmp_path: Path) -> None:
    _session(tmp_path / "s.tlog")
    data = (tmp_path / "s.tlog").read_bytes()
    (tmp_path / "cut.tlog").write_bytes(data[:-7])  # killed inside the last record
    reader = LogReader(tmp_path / "cut.tlog")
    assert len(list(reader)) == 4 and reader.truncated and "ends inside a record" in reader.truncated
    res = subprocess.run([sys.executable, "-m", "tactiled_client", "replay", str(tmp_path / "cut.tlog"), "--json"], capture_output=True,
                         text=True, timeout=60, cwd=REPO)
    assert res.returncode == 0 and len(res.stdout.splitlines()) == 4 and res.stderr.startswith("warning:") and "cut.tlog" in res.stderr


def _hostile(tmp_path: Path) -> dict[str, tuple[bytes, str]]:
    deep = b"\x91" * 100_000 + b"\xc0"  # 100 000 nested one-element arrays
    rec_deep = msgpack.packb([0.0, 0.0, "status/s", deep], use_bin_type=True)
    return {
        "huge.tlog": (HEADER + RECORD.pack(0xFFFFFFF0, 0), "declares 4294967280 bytes"),
        "crc.tlog": (HEADER + RECORD.pack(3, 0) + b"abc", "fails its CRC-32"),
        "deep.tlog": (HEADER + RECORD.pack(len(rec_deep), zlib.crc32(rec_deep)) + rec_deep, "not msgpack"),
        "version.tlog": (HEADER[:12] + struct.pack("<H", 9) + b"\x00\x00", "session log version 9"),
        "other.tlog": (b"PK\x03\x04 a zip, not a log", "not a session log, an MCAP file or tactiled replay --json output"),
        "deep.jsonl": (b"{\"a\": " + b"[" * 100_000 + b"]" * 100_000 + b"}\n", "line 1: not JSON"),
    }


@pytest.mark.parametrize("name", ["huge.tlog", "crc.tlog", "deep.tlog", "version.tlog", "other.tlog", "deep.jsonl"])  # a newer schema: read (test_audit_client)
def test_bad_files_get_one_line_naming_file_and_fault(name: str, tmp_path: Path) -> None:
    data, what = _hostile(tmp_path)[name]
    (tmp_path / name).write_bytes(data)
    with pytest.raises(LogError, match=what.replace("(", r"\(").replace(")", r"\)")) as info:
        list(BlockingReplay(tmp_path / name, speed=None))
    assert str(tmp_path / name) in str(info.value) and "\n" not in str(info.value)
    res = subprocess.run([sys.executable, "-m", "tactiled_client", "replay", str(tmp_path / name), "--json"], capture_output=True, text=True,
                         timeout=60, cwd=REPO)
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1 and name in res.stderr


def test_replay_onto_a_socket_renumbers_seq_per_topic(tmp_path: Path) -> None:
    frames = _session(tmp_path / "s.tlog")
    endpoint = f"ipc://{tmp_path}/pub"
    with BlockingSubscriber(endpoint, timeout=30) as sub:
        proc = subprocess.Popen([sys.executable, "-m", "tactiled_client", "replay", str(tmp_path / "s.tlog"), "--publish", endpoint,
                                 "--speed", "10", "--wait-subscriber", "30"], cwd=REPO, stderr=subprocess.PIPE, text=True)
        got = [sub.receive() for _ in frames]
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0 and "published 5 messages" in err
    assert [(schema.topic(m.type, m.sensor), m.seq) for m in got] == [("slide/s0", 0), ("roughness/s0", 0), ("slide/s0", 1),
                                                                      ("roughness/s0", 1), ("status/s1", 0)]
    assert all(m.missed == 0 for m in got)


def _simulated(tmp_path: Path) -> Path:
    from tactiled.files.recording import Recording, save_recording
    from tactiled.sim.physics import SimParams, pick_surfaces, simulate_file

    params = SimParams()
    sim = simulate_file(params, pick_surfaces("Ra2.29")[0], 3, 4)
    path = tmp_path / "r.npz"
    save_recording(path, Recording(sim.samples, params.fs, params.volts_per_count, first_index=1000,
                                   slide_start=np.array([t.start for t in sim.truth]), slide_stop=np.array([t.stop for t in sim.truth]),
                                   surface=np.array([t.surface.name for t in sim.truth])))
    return path


def test_tactiled_mcap_and_replay_json_replay_as_roughness_messages(tmp_path: Path) -> None:
    path = _simulated(tmp_path)
    res = run_cli("replay", "--json", str(path))
    assert res.returncode == 0, res.stderr
    printed = [json.loads(line) for line in res.stdout.splitlines()]
    (tmp_path / "r.jsonl").write_text(res.stdout)
    with BlockingReplay(tmp_path / "r.jsonl", speed=None) as rep:
        got = [m for m in rep if isinstance(m, Roughness)]
    finals = [m for m in got if m.final]
    assert [(m.start, m.stop, m.label, m.confidence) for m in finals] == [(p["start"], p["stop"], p["label"], p["confidence"]) for p in printed]
    assert len(got) - len(finals) == sum(len(p["provisional"]) for p in printed)
    assert run_cli("export", str(path), "-o", str(tmp_path / "r.mcap")).returncode == 0
    with BlockingReplay(tmp_path / "r.mcap", speed=None) as rep:
        from_mcap = [m for m in rep if isinstance(m, Roughness)]
    from tactiled.files.recording import load_recording

    base = load_recording(path).first_index  # MCAP: sensor indices, as on the wire; replay --json: positions in the file
    assert [(m.start, m.label) for m in from_mcap if m.final] == [(p["start"] + base, p["label"]) for p in printed]
    # stamped as the daemon stamps what it sends: seq per topic from 0 (no gap counted), time_unix the message's log time
    assert [m.seq for m in from_mcap] == list(range(len(from_mcap))) and rep.missed == {"roughness/fingertip0": 0}
    assert all(m.time_unix > 1e9 for m in from_mcap)
    # a provisional label replayed from the --json lines ends where its windows did, as the daemon published it (the MCAP
    # holds the messages as published): it carried the final label's stop, window and quality, then 1.5 s in its future
    early_json = [m for m in got if not m.final]
    early_mcap = [m for m in from_mcap if not m.final]
    assert early_json and len(early_json) == len(early_mcap)
    for j, m in zip(early_json, early_mcap, strict=True):
        assert (j.start + base, j.stop + base, [w + base for w in j.window], j.label, j.used_s) == (m.start, m.stop, m.window, m.label, m.used_s)
        assert j.t_stop == pytest.approx(j.t_start + j.used_s)
        assert {k: v for k, v in j.quality.items() if k != "compute_ms"} == {k: v for k, v in m.quality.items() if k != "compute_ms"}


@pytest.fixture(scope="module")
def client_only(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh virtual environment holding only the client package (and its pyzmq and msgpack)."""
    venv = tmp_path_factory.mktemp("client-only") / "venv"
    # no pip of its own (bootstrapping one is half the time): this environment's pip installs into it
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    subprocess.run([sys.executable, "-m", "pip", "--python", str(venv / "bin" / "python"), "install", "-q", str(REPO / "clients")], check=True,
                   timeout=600, capture_output=True)
    return venv / "bin" / "python"


def test_the_light_client_alone_records_a_session_and_replays_it(client_only: Path, tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    probe = subprocess.run([str(client_only), "-c", "import tactiled_client, importlib.util as u; print(u.find_spec('tactiled') is None, "
                            "u.find_spec('numpy') is None)"], capture_output=True, text=True, cwd=tmp_path, env=env, timeout=60)
    assert probe.stdout.split() == ["True", "True"], probe.stdout + probe.stderr
    path = _simulated(tmp_path)
    endpoint = f"ipc://{tmp_path}/pub"
    log = tmp_path / "session.tlog"
    recorder = subprocess.Popen([str(client_only), "-m", "tactiled_client", "record", endpoint, str(log), "--seconds", "120"], cwd=tmp_path,
                                env=env, stderr=subprocess.PIPE, text=True)
    replay = subprocess.run(tactiled_cmd("replay", "--json", "--speed", "8", "--publish", endpoint, "--wait-subscriber", "30", str(path)),
                            capture_output=True, text=True, timeout=120, cwd=REPO)
    assert replay.returncode == 0, replay.stderr
    recorder.send_signal(signal.SIGTERM)  # the publisher has sent everything: what is in flight is still recorded
    _, err = recorder.communicate(timeout=60)
    assert recorder.returncode == 0, err
    printed = [json.loads(line) for line in replay.stdout.splitlines()]
    recorded = list(LogReader(log))
    rough = [msgpack.unpackb(e.body) for e in recorded if e.topic.startswith("roughness/")]
    assert [(r["start"] - 1000, r["label"]) for r in rough if r["final"]] == [(p["start"], p["label"]) for p in printed]
    assert [r["seq"] for r in rough] == list(range(len(rough)))  # nothing lost on the way
    back = subprocess.run([str(client_only), "-m", "tactiled_client", "replay", str(log), "--json"], capture_output=True, text=True, cwd=tmp_path,
                          env=env, timeout=60)
    assert back.returncode == 0, back.stderr
    lines = [json.loads(line) for line in back.stdout.splitlines()]
    assert [(x["topic"], x["seq"]) for x in lines] == [(e.topic, msgpack.unpackb(e.body)["seq"]) for e in recorded]
    assert all({k: v for k, v in x.items() if k != "topic"} == msgpack.unpackb(e.body) for x, e in zip(lines, recorded, strict=True)
               if not e.topic.startswith("samples/"))


def test_example_controller_runs_against_a_recorded_session(tmp_path: Path) -> None:
    _session(tmp_path / "s.tlog")
    res = subprocess.run([sys.executable, str(REPO / "clients" / "example_controller.py"), "--replay", str(tmp_path / "s.tlog")],
                         capture_output=True, text=True, timeout=60, cwd=REPO)
    assert res.returncode == 0, res.stderr
    assert "slide 0: final Ra1.18 p=0.70" in res.stdout and res.stdout.strip().endswith("end of the recorded session")


def test_a_fifo_given_as_a_session_is_refused_without_opening_it(tmp_path: Path) -> None:
    os.mkfifo(tmp_path / "s.tlog")  # opening it would block until a writer came
    with pytest.raises(LogError, match="not a regular file"):
        BlockingReplay(tmp_path / "s.tlog", speed=None)


def test_recording_from_an_endpoint_nobody_publishes_on_says_so(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A mistyped endpoint is not an error (a daemon may come later), but an empty session says where nothing came from."""
    from tactiled_client.__main__ import main

    endpoint = f"ipc://{tmp_path}/nobody"
    assert main(["record", endpoint, str(tmp_path / "s.tlog"), "--seconds", "0.3"]) == 0
    assert capsys.readouterr().err.strip() == f"{tmp_path / 's.tlog'}: 0 messages (nothing came from {endpoint}: is a daemon publishing there?)"
