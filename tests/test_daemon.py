"""The daemon end to end: virtual board on a pty → tactiled run → client-library subscribers."""

from __future__ import annotations

import itertools
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import zmq
from tactiled_client import BlockingSubscriber, NoData, Roughness, Slide, Status

from tactiled.board.frames import frame_size
from tactiled.config import Config
from tactiled.files.recording import load_recording
from tactiled.learn.model import load_model
from tactiled.run.replay import replay_recording
from tactiled.sim.physics import SensorSimulator, SimParams, pick_surfaces
from tactiled.sim.virtualboard import VirtualBoard, read_log
from tests.conftest import board_and_daemon, daemon_process, running, standing_finals, tactiled_cmd, wait_for


def test_daemon_labels_every_slide_like_replay_through_faults(tmp_path: Path) -> None:
    config = tmp_path / "c.toml"
    config.write_text("[classifier]\nprovisional_confidence = 0.0\n")  # a provisional label after the first window of every slide
    lazy = zmq.Context.instance().socket(zmq.SUB)  # a subscriber that never reads
    lazy.setsockopt(zmq.SUBSCRIBE, b"")
    messages: list[object] = []
    try:
        with board_and_daemon(tmp_path, "--record", str(tmp_path / "got.npz"), "--config", str(config), surfaces=5, seed=5, corrupt=0.005,
                              drop=0.0025, garbage=0.005, unplug_at=[9.0], unplug_s=0.5) as live, \
                BlockingSubscriber(live.endpoint, timeout=20) as sub:
            lazy.connect(live.endpoint)

            def enough() -> bool:
                messages.append(sub.receive())
                unplugged = any(isinstance(m, Status) and m.reconnects >= 1 for m in messages)
                after = standing_finals(messages)  # a final label withdrawn by a "resumed" slide does not count
                return unplugged and len(after) >= 6 and isinstance(messages[-1], Roughness) and messages[-1].final and \
                    any(isinstance(m, Status) and m.reconnects >= 1 for m in messages[: messages.index(after[-1])])
            wait_for(enough, timeout=120, what="six labels and a reconnect")
            live.proc.terminate()
            live.proc.wait(30)
            try:
                while True:
                    messages.append(sub.receive(timeout=0.5))
            except NoData:
                pass
    finally:
        lazy.close(linger=0)
    proc, log_path = live.proc, live.log_path
    assert proc.returncode == 0, proc.stderr.read() if proc.stderr else ""
    every_label = [m for m in messages if isinstance(m, Roughness)]
    rough = standing_finals(messages)  # a final label withdrawn by a "resumed" slide message does not count
    statuses = [m for m in messages if isinstance(m, Status)]
    slides = [m for m in messages if isinstance(m, Slide)]
    # no message lost between daemon and subscriber; seq consecutive per topic
    assert all(m.missed == 0 for m in messages)  # type: ignore[attr-defined]
    assert all(m.extra == {} for m in messages)  # type: ignore[attr-defined]  # every key written is in the schema
    for kind in (every_label, statuses, slides):
        seqs = [m.seq for m in kind]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    # status at least once a second
    times = [m.time_unix for m in statuses]
    assert max(b - a for a, b in itertools.pairwise(times)) <= 1.0
    # every ended slide has exactly one final roughness message, after its end; provisional ones come before the end
    ended = {m.slide_id for m in slides if m.event == "end"}
    assert sorted(m.slide_id for m in rough) == sorted(ended)
    end_at = {m.slide_id: i for i, m in enumerate(messages) if isinstance(m, Slide) and m.event == "end"}
    early = [(i, m) for i, m in enumerate(messages) if isinstance(m, Roughness) and not m.final and m.slide_id in end_at]
    assert early and all(i < end_at[m.slide_id] and m.label and 0 < m.used_s <= (m.stop - m.start) / 20_000 + 1e-9 for i, m in early)
    assert all(messages.index(m) > end_at[m.slide_id] for m in rough)
    labelled = [m for m in rough if m.label is not None]
    assert len(labelled) >= 4, [(m.slide_id, m.label, m.reason, m.quality["lost"], m.final) for m in rough]
    assert all(m.model == load_model().fingerprint and m.latency_ms >= 0 for m in rough)
    # the labels replay gives on the very samples the daemon received
    got = load_recording(tmp_path / "got.npz")
    replayed = {r.start + got.first_index: r for r in replay_recording(got, Config(), load_model()) if r.final}
    for m in rough:
        r = replayed[m.start]
        assert (r.stop + got.first_index, r.label, r.reason) == (m.stop, m.label, m.reason)
    # counters match the faults injected while the daemon listened
    last = statuses[-1]
    events = [e for e in read_log(log_path) if e.get("index", -1) >= got.first_index and e.get("index", 0) < got.first_index + got.samples.shape[0]]
    overruns = {e["index"] for e in events if e["event"] == "overrun"}  # frames the pty would not take (the daemon starved): never received
    stranded = [(e["index"] - -(-e["unread"] // frame_size(2, 20)) * 20, e["index"]) for e in read_log(log_path) if e["event"] == "unplug"]
    corrupted = sum(e["event"] == "corrupt" and e["index"] not in overruns  # nor were the frames still in the pty at the unplug
                    and not any(lo <= e["index"] < hi for lo, hi in stranded) for e in events)
    dropped = sum(e["event"] == "drop" for e in events)
    assert last.crc_errors + last.bad_headers >= corrupted > 0
    assert last.samples_lost >= 20 * (corrupted + dropped) + round(0.5 * 20_000)
    assert last.samples_lost == int(got.lost[:, 1].sum())
    assert last.reconnects == 1


def test_daemon_refuses_public_bind_and_bad_model(tmp_path: Path) -> None:
    res = subprocess.run(tactiled_cmd("run", "--port", "/dev/null", "--publish", "tcp://0.0.0.0:0"), capture_output=True, text=True, timeout=60)
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == ["tactiled: error: publish.endpoint: binds a non-loopback address; set publish.allow_remote = true to allow it"]
    bad = tmp_path / "m.npz"
    bad.write_bytes(b"not a zip")
    res = subprocess.run(tactiled_cmd("run", "--port", "/dev/null", "--model", str(bad)), capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1 and str(bad) in res.stderr


def test_daemon_waits_for_a_missing_port_and_reports_it(tmp_path: Path) -> None:
    endpoint = f"ipc://{tmp_path}/pub"
    link = str(tmp_path / "later")
    with BlockingSubscriber(endpoint, topics=["status"], timeout=20) as sub, daemon_process(link, endpoint) as proc:
        first = sub.receive()
        assert isinstance(first, Status) and first.state == "disconnected"
        with running(VirtualBoard(SensorSimulator(SimParams(), seed=1), pick_surfaces(2), link=link, speed=1.0)):
            wait_for(lambda: (m := sub.receive()) and isinstance(m, Status) and m.samples > 0, timeout=30, what="samples after plug-in")
            proc.terminate()
            proc.wait(30)
    assert proc.returncode == 0


def test_replay_publishes_the_daemon_messages(tmp_path: Path) -> None:
    """A controller can be tested offline: replay --publish sends the same messages as the daemon."""
    import json

    from tactiled.files.recording import Recording, save_recording
    from tactiled.sim.physics import simulate_file

    params = SimParams()
    sim = simulate_file(params, pick_surfaces("Ra2.29")[0], 3, 4)
    path = tmp_path / "r.npz"
    save_recording(path, Recording(sim.samples, params.fs, params.volts_per_count, first_index=1000))
    endpoint = f"ipc://{tmp_path}/replay"
    with BlockingSubscriber(endpoint, topics=["roughness", "slide"], timeout=30) as sub:
        proc = subprocess.Popen(tactiled_cmd("replay", "--json", "--speed", "4", "--publish", endpoint, "--wait-subscriber", "30",
                                             str(path)),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        got = []
        while len([m for m in got if isinstance(m, Roughness) and m.final]) < 3:
            got.append(sub.receive())
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    printed = [json.loads(line) for line in out.splitlines()]
    rough = [m for m in got if isinstance(m, Roughness)]
    finals = [m for m in rough if m.final]  # provisional labels come before their slide's final one
    assert [(m.start - 1000, m.stop - 1000, m.label) for m in finals] == [(p["start"], p["stop"], p["label"]) for p in printed]
    assert sum(len(p["provisional"]) for p in printed) == len(rough) - len(finals)
    assert [m.seq for m in rough] == list(range(len(rough))) and all(m.model == load_model().fingerprint for m in rough)
    assert [m.event for m in got if isinstance(m, Slide)][:2] == ["start", "end"]


def test_curve_subscriber_without_the_key_receives_nothing(tmp_path: Path) -> None:
    import zmq.auth

    keys, allowed = tmp_path / "keys", tmp_path / "allowed"
    allowed.mkdir()
    for name in ("daemon", "robot", "stranger"):
        res = subprocess.run(tactiled_cmd("curve-keys", str(keys), name), capture_output=True, text=True, timeout=60)
        assert res.returncode == 0, res.stderr
    (allowed / "robot.key").write_bytes((keys / "robot.key").read_bytes())
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[publish]\nendpoint = "tcp://127.0.0.1:0"\ncurve_secret_key_file = "{keys / "daemon.key_secret"}"\n'
                   f'curve_authorized_dir = "{allowed}"\nstatus_interval_s = 0.05\n[control]\nendpoint = "ipc://{tmp_path}/control"\n')
    proc = subprocess.Popen(tactiled_cmd("run", "--config", str(cfg), "--port", str(tmp_path / "none"), "--no-model"),
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()
        endpoint = line.rsplit("publishing on ", 1)[1].strip()
        with BlockingSubscriber(endpoint, topics=["status"], timeout=10,
                                curve=(str(keys / "daemon.key"), str(keys / "robot.key_secret"))) as good:
            assert isinstance(good.receive(), Status)
        # both connected at once: after the stranger's 2 s of silence (40 status periods), the plain subscriber has been
        # connected as long, so anything it were sent would be waiting
        with BlockingSubscriber(endpoint, topics=["status"], curve=(str(keys / "daemon.key"), str(keys / "stranger.key_secret"))) as stranger, \
                BlockingSubscriber(endpoint, topics=["status"]) as plain:
            with pytest.raises(NoData):
                stranger.receive(timeout=2.0)
            with pytest.raises(NoData):
                plain.receive(timeout=0.2)
        assert zmq.auth.load_certificate(str(keys / "daemon.key"))[1] is None  # the public file holds no secret

        def control(*curve: str, timeout: str) -> subprocess.CompletedProcess[str]:
            return subprocess.run([sys.executable, "-m", "tactiled_client", "control", f"ipc://{tmp_path}/control", "status", *curve,
                                   "--timeout", timeout], capture_output=True, text=True, timeout=60)

        assert control("--curve", str(keys / "daemon.key"), str(keys / "robot.key_secret"), timeout="10").returncode == 0
        # the control socket admits the subscriptions' certificates, no one else (the two refused at once: 2 s of waiting each)
        with ThreadPoolExecutor(2) as pool:
            refused = list(pool.map(lambda curve: control(*curve, timeout="2"),
                                    [("--curve", str(keys / "daemon.key"), str(keys / "stranger.key_secret")), ()]))
        assert all(r.returncode != 0 for r in refused), [r.stderr for r in refused]
    finally:
        proc.terminate()
        proc.wait(10)
    assert proc.returncode == 0


def test_sighup_swaps_the_model_between_slides_and_refuses_a_bad_file(tmp_path: Path) -> None:
    """systemctl reload: the new model takes over at a slide boundary, no sample is lost, every slide gets its label; a bad file is refused."""
    import os
    import shutil
    import signal

    from tactiled.learn.model import default_model_path

    shipped = load_model()
    other = tmp_path / "other.npz"
    shipped.summary = {**shipped.summary, "note": "the same classifier under another fingerprint"}
    b = shipped.save(other)
    a = load_model().fingerprint
    assert a != b
    live = tmp_path / "model.npz"
    shutil.copy(default_model_path(), live)
    config = tmp_path / "c.toml"
    config.write_text(f'[model]\npath = "{live}"\n')
    got: list[object] = []
    with board_and_daemon(tmp_path, "--config", str(config), params=SimParams(mode="robot"), seed=6) as running_daemon:
        proc = running_daemon.proc
        with BlockingSubscriber(running_daemon.endpoint, topics=["roughness", "slide", "status"], timeout=30) as sub:
            def final_by(fingerprint: str) -> bool:
                got.append(sub.receive())
                return isinstance(got[-1], Roughness) and got[-1].final and got[-1].model == fingerprint

            wait_for(lambda: final_by(a), timeout=60, what="a label by the first model")
            os.replace(other, live)
            proc.send_signal(signal.SIGHUP)
            wait_for(lambda: final_by(b), timeout=60, what="a label by the reloaded model")
            live.write_bytes(b"PK\x03\x04 not a model")
            proc.send_signal(signal.SIGHUP)
            wait_for(lambda: final_by(b), timeout=60, what="another label by the model that stayed")
            err = running_daemon.stop()
    assert proc.returncode == 0, err
    summary = [line for line in err.splitlines() if "stopped after" in line]  # the one-line summary on SIGTERM
    assert len(summary) == 1 and all(f" {word}" in summary[0] for word in ("samples,", "lost,", "slides,", "labels,")), err
    refused = [line for line in err.splitlines() if "reload refused" in line]
    assert len(refused) == 1 and str(live) in refused[0] and b in refused[0]
    swapped = [line for line in err.splitlines() if "reload: model" in line]  # said without -v: systemctl reload says nothing
    assert len(swapped) == 1 and b in swapped[0] and f"was {a}" in swapped[0], err
    assert any(line.endswith(f"sensor fingertip0, model {a}") for line in err.splitlines()), err  # what it runs, at the start
    assert sum("publishing on" in line for line in err.splitlines()) == 1, err  # said once
    ends = [m.slide_id for m in got if isinstance(m, Slide) and m.event == "end"]
    finals = [m for m in got if isinstance(m, Roughness) and m.final]
    assert {m.slide_id for m in finals} >= set(ends[:-1]) and all(m.label is not None or m.reason for m in finals)
    assert [m.model for m in finals] == sorted((m.model for m in finals), key=lambda fp: fp == b), [  # a, then b: never back
        (m.slide_id, m.final, m.model, m.label, m.reason) for m in got if isinstance(m, Roughness)]
    statuses = statuses_after_first_label(got)
    assert statuses and statuses[-1].model == b
    assert lost_across(statuses) <= running_daemon.overrun_samples(first_label(got).start)  # nothing lost but what the board could not send


def test_a_shadow_model_runs_on_the_same_slides_without_publishing_its_labels_as_the_live_ones(tmp_path: Path) -> None:
    """run --shadow: the candidate's labels on shadow/<id> (not Roughness), its agreement with the live labels in status."""
    from tactiled_client import Shadow

    shipped = load_model()
    live_fingerprint = shipped.fingerprint
    candidate = tmp_path / "candidate.npz"
    shipped.summary = {**shipped.summary, "note": "the same classifier under another fingerprint"}
    fingerprint = shipped.save(candidate)
    got: list[object] = []
    with board_and_daemon(tmp_path, "--shadow", str(candidate), params=SimParams(mode="robot"), seed=7) as live, \
            BlockingSubscriber(live.endpoint, topics=["roughness", "shadow", "status"], timeout=30) as sub:
        def compared() -> bool:
            got.append(sub.receive())
            return isinstance(got[-1], Status) and got[-1].shadow is not None and got[-1].shadow["slides"] >= 3

        wait_for(compared, timeout=90, what="three slides compared in status.shadow")
    shadows = [m for m in got if isinstance(m, Shadow) and m.final]
    # keyed by start and stop: a slide that ended early and went on has two finals with one start (the first withdrawn)
    lives = {(m.start, m.stop): m for m in got if isinstance(m, Roughness) and m.final}
    assert shadows and all(not isinstance(m, Roughness) and m.model == fingerprint for m in shadows)
    assert lives and all(m.model == live_fingerprint != fingerprint for m in lives.values())  # the live labels stay the live model's
    paired = [(m, lives[m.start, m.stop]) for m in shadows if (m.start, m.stop) in lives]
    differ = [(s.start, s.stop, s.label, live.label) for s, live in paired if s.label != live.label]
    assert paired and not differ, differ  # the same classifier on the same slides: the same labels
    status = got[-1]
    assert isinstance(status, Status) and status.shadow is not None
    assert status.shadow["model"] == fingerprint and status.shadow["agreement"] == 1.0 and 0.0 < status.shadow["confidence"] <= 1.0


def test_a_control_request_swaps_the_model_refuses_a_bad_one_and_starts_and_stops_a_shadow(tmp_path: Path) -> None:
    """python -m tactiled_client control: load (atomic between slides, no sample lost), a bad file refused in one line, shadow on and off."""
    import sys

    def control(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "tactiled_client", "control", ctl, *args], capture_output=True, text=True, timeout=60)

    shipped = load_model()
    a = shipped.fingerprint
    shipped.summary = {**shipped.summary, "note": "the same classifier under another fingerprint"}
    b = shipped.save(tmp_path / "b.npz")
    (tmp_path / "bad.npz").write_bytes(b"PK\x03\x04 not a model")
    ctl = f"ipc://{tmp_path}/control"
    config = tmp_path / "c.toml"
    config.write_text(f'[control]\nendpoint = "{ctl}"\n')
    got: list[object] = []
    with board_and_daemon(tmp_path, "--config", str(config), params=SimParams(mode="robot"), seed=8) as live:
        proc = live.proc
        with BlockingSubscriber(live.endpoint, topics=["roughness", "slide", "status"], timeout=30) as sub:
            def final_by(fingerprint: str) -> bool:
                got.append(sub.receive())
                return isinstance(got[-1], Roughness) and got[-1].final and got[-1].model == fingerprint

            wait_for(lambda: final_by(a), timeout=60, what="a label by the first model")
            res = control("load", str(tmp_path / "b.npz"))
            assert res.returncode == 0 and f'"model": "{b}"' in res.stdout, res.stderr
            wait_for(lambda: final_by(b), timeout=60, what="a label by the loaded model")
            res = control("load", str(tmp_path / "bad.npz"))
            assert res.returncode == 1 and res.stderr.count("\n") == 1 and "bad.npz" in res.stderr, res.stderr
            assert raw_request(ctl, {"cmd": "load", "path": "a\0b"}) == {"ok": False, "error": "request: path holds a NUL character"}
            res = control("shadow", str(tmp_path / "b.npz"))
            assert res.returncode == 0 and b in res.stdout, res.stderr
            wait_for(lambda: (m := sub.receive()) and isinstance(m, Status) and m.shadow is not None and m.shadow["slides"] >= 1,
                     timeout=60, what="a slide compared by the shadow")
            assert control("shadow").returncode == 0
            wait_for(lambda: (m := sub.receive()) and isinstance(m, Status) and m.shadow is None, timeout=20, what="the shadow stopped")
            status = control("status")
            assert status.returncode == 0 and f'"model": "{b}"' in status.stdout
            wait_for(lambda: final_by(b), timeout=60, what="another label by the model that stayed")
        live.stop()
    assert proc.returncode == 0
    finals = [m for m in got if isinstance(m, Roughness) and m.final]
    assert [m.model for m in finals] == sorted((m.model for m in finals), key=lambda fp: fp == b), [  # a, then b: never back
        (m.slide_id, m.final, m.model, m.label, m.reason) for m in got if isinstance(m, Roughness)]
    statuses = statuses_after_first_label(got)
    assert statuses and lost_across(statuses) <= live.overrun_samples(first_label(got).start)  # no sample lost across the swap


def raw_request(endpoint: str, request: dict[str, object]) -> object:
    """One control request sent as it is (what the client would refuse to send) and its reply, unpacked (30 s at most)."""
    import msgpack
    import zmq

    with zmq.Context() as ctx, ctx.socket(zmq.REQ) as req:
        req.setsockopt(zmq.LINGER, 0)
        req.connect(endpoint)
        req.send(msgpack.packb(request))
        assert req.poll(30_000), f"no reply to {request}"
        return msgpack.unpackb(req.recv())


def first_label(got: list[object]) -> Roughness:
    """The first final label among the messages ``got``."""
    return next(m for m in got if isinstance(m, Roughness) and m.final)


def statuses_after_first_label(got: list[object]) -> list[Status]:
    """The status messages that came after the first final label."""
    first = got.index(first_label(got))
    return [m for m in got[first:] if isinstance(m, Status)]


def lost_across(statuses: list[Status]) -> int:
    """Samples the daemon counted lost from the first to the last of ``statuses``."""
    return statuses[-1].samples_lost - statuses[0].samples_lost


def _ignores_hangup(pid: int) -> bool:
    """Whether process ``pid`` ignores SIGHUP (bit 0 of its SigIgn mask)."""
    try:
        mask = next(line for line in Path(f"/proc/{pid}/status").read_text().splitlines() if line.startswith("SigIgn:"))
    except FileNotFoundError:
        return False
    return bool(int(mask.split()[1], 16) & 1)


def test_a_sighup_during_start_up_does_not_end_the_daemon(tmp_path: Path) -> None:
    """SIGHUP reloads the model once the daemon runs; one during its start-up (imports, the model's load) was its default
    action, an exit of 129 with no line (an audit): ignored until the daemon's own handler is in place."""
    import signal

    endpoint = f"ipc://{tmp_path}/pub"
    with BlockingSubscriber(endpoint, topics=["status"], timeout=20) as sub, daemon_process(str(tmp_path / "absent"), endpoint) as proc:
        wait_for(lambda: proc.poll() is not None or _ignores_hangup(proc.pid), timeout=30, what="the daemon ignoring SIGHUP at start")
        proc.send_signal(signal.SIGHUP)  # before its first status: still starting
        assert isinstance(sub.receive(), Status)  # it runs
        proc.terminate()
        proc.wait(30)
    assert proc.returncode == 0, proc.stderr.read() if proc.stderr else ""
