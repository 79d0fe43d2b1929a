"""`tactiled record` end to end from a virtual board on a real pty, with faults and an unplug; kills, signals, full disks, `recover`."""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import signal
import subprocess
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from tactiled.board.frames import Frame, frame_size
from tactiled.files.journal import JournalWriter, encode_chunk, encode_header, journal_path, read_journal, recover
from tactiled.files.recording import load_recording
from tactiled.service.recorder import RecordingSink
from tactiled.sim.physics import SensorSimulator, SimParams, Surface, default_surfaces
from tactiled.sim.virtualboard import VirtualBoard, read_log
from tests.conftest import REPO, cli_here, run_cli, running, tactiled_cmd, wait_for

SURFACES = default_surfaces()[:2]


@contextlib.contextmanager
def running_board(tmp_path: Path, seed: int) -> Iterator[VirtualBoard]:
    """A virtual board streaming on ``tmp_path/dev`` until the block ends, its events in ``tmp_path/board.jsonl``."""
    with open(tmp_path / "board.jsonl", "w") as log, \
            running(VirtualBoard(SensorSimulator(SimParams(), seed=seed), SURFACES, link=str(tmp_path / "dev"), seed=seed, log=log)) as board:
        yield board


@contextlib.contextmanager
def spawned(*args: str) -> Iterator[subprocess.Popen[str]]:
    """``tactiled ARGS`` with piped output; killed on leaving the block if it is still running."""
    proc = subprocess.Popen(tactiled_cmd(*args), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def board_truth(seed: int, surfaces: list[Surface], start: int, n: int) -> np.ndarray:
    """The ``n`` samples a seeded virtual board sends from its ``start``-th sample on."""
    model = SensorSimulator(SimParams(), seed=seed)
    model.schedule_random(surfaces, start + n)
    if start:
        model.read(start)
    return model.read(n)


def wait_journal(board: VirtualBoard, journal: Path, nbytes: int) -> None:
    """Wait (on the board's progress, never a sleep) until ``journal`` holds at least ``nbytes``."""
    def grown() -> bool:
        board.wait_sent(board.sent_samples + 400, timeout=1.0)
        return journal.exists() and journal.stat().st_size >= nbytes
    wait_for(grown, timeout=30, what=f"{journal} to reach {nbytes} bytes")


def test_record_keeps_every_intact_sample_through_faults_and_unplug(tmp_path: Path) -> None:
    params = SimParams()
    link = str(tmp_path / "tactile0")
    log_path = tmp_path / "board.jsonl"
    first = 2**32 - 30_000  # the 32-bit index wraps 1.5 s in
    with open(log_path, "w") as log:
        board = VirtualBoard(SensorSimulator(params, seed=3), default_surfaces()[:3], link=link, speed=2.0, corrupt=0.01,
                             drop=0.005, garbage=0.01, unplug_at=[1.0], unplug_s=0.2, seed=3, log=log, first_index=first)
        board.open()
        out = tmp_path / "rec.npz"
        proc = subprocess.Popen(tactiled_cmd("-v", "record", "--port", link, "--seconds", "2.5", "-o", str(out)),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert proc.stderr is not None
        assert "recording" in proc.stderr.readline()  # the port checked and open: the unplug cannot come before
        with running(board):
            stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 0, stderr
    rec = load_recording(out)
    events = read_log(log_path)
    n = rec.samples.shape[0]
    assert n == 50_000
    assert "1 reconnects" in stdout
    # the expected stream: regenerate the same seeded samples
    truth = board_truth(3, default_surfaces()[:3], rec.first_index - first, n)
    bad = np.zeros(n, dtype=bool)
    unplugged: dict[str, int] | None = None
    for e in events:
        if e["event"] in ("drop", "corrupt", "overrun"):
            lo = e["index"] - rec.first_index
            bad[max(lo, 0):max(min(lo + e["count"], n), 0)] = True
        elif e["event"] == "unplug":
            unplugged = e
        elif e["event"] == "open" and unplugged is not None:
            # the unplug: the frames the reader had not taken when the pty closed (the board logs their bytes), then every
            # sample up to the first frame of the new pty (frames the new pty would not take before the reader reopened it
            # are logged as overruns)
            stranded = -(-unplugged["unread"] // frame_size(2, 20)) * 20
            bad[max(unplugged["index"] - stranded - rec.first_index, 0):max(min(e["index"] - rec.first_index, n), 0)] = True
            unplugged = None
    valid = rec.valid_mask()
    # every intact sample the board sent is present at its index
    assert np.array_equal(rec.samples[valid], truth[valid])
    # every sample not received is listed as lost, and only samples the board did not deliver intact
    assert not np.any(~valid & ~bad)
    assert rec.lost[:, 1].sum() == int((~valid).sum()) > 0
    assert np.all(rec.samples[~valid] == 0)
    assert any(e["event"] == "unplug" for e in events) and any(e["event"] == "corrupt" for e in events)


def test_record_missing_port_is_one_line_and_no_file(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "x.npz"
    res = cli_here(capfd, "record", "--port", str(tmp_path / "nope"), "--seconds", "1", "-o", str(out))
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [f"tactiled: error: {tmp_path / 'nope'}: no such serial device"]
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("label", ["", "a\nb"])
def test_record_refuses_a_label_its_file_could_not_load_with(tmp_path: Path, label: str, capfd: pytest.CaptureFixture[str]) -> None:
    """A recording's label follows the surface-name rule (docs/recordings.md); record wrote such a file, which train,
    score and replay then refused."""
    out = tmp_path / "x.npz"
    res = cli_here(capfd, "record", "--port", str(tmp_path / "nope"), "--seconds", "1", "--label", label, "-o", str(out))
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and lines[0].startswith("tactiled: error: --label: "), res.stderr
    assert list(tmp_path.iterdir()) == []


def test_record_bad_config_value(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text("[sensor]\nchannels = 0\n")
    res = cli_here(capfd, "record", "--config", str(cfg), "--port", "/dev/null", "--seconds", "1", "-o", str(tmp_path / "x.npz"))
    assert res.returncode == 2
    assert "sensor.channels: must be in 1..8" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x.npz").exists()


def test_record_ctrl_c_saves_what_was_captured(tmp_path: Path) -> None:
    out = tmp_path / "r.npz"
    with running_board(tmp_path, seed=1) as board, spawned("-v", "record", "--port", board.link or "", "--seconds", "600", "-o", str(out)) as proc:
        assert proc.stderr is not None
        assert "recording" in proc.stderr.readline()
        started = board.sent_samples
        assert board.wait_sent(started + 4000, timeout=20), "board streaming to the recorder"
        proc.send_signal(signal.SIGINT)
        _stdout, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 0, stderr
    rec = load_recording(out)
    assert rec.samples.shape[0] > 0 and rec.samples.shape[1] == 2
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


# ---- crash-safe recording: the journal (tactiled/files/journal.py) -----------------------------------------------

def test_sigkill_loses_at_most_a_second_and_recover_gives_the_boards_samples(tmp_path: Path) -> None:
    out = tmp_path / "r.npz"
    journal = tmp_path / "r.npz.journal"
    fs = SimParams().fs
    with running_board(tmp_path, seed=7) as board, spawned("record", "--port", board.link or "", "--seconds", "600", "-o", str(out)) as proc:
        wait_journal(board, journal, round(2.5 * fs) * 4)  # 2.5 s of 2 x int16 samples
        sent = board.sent_samples
        proc.kill()
        proc.wait(10)
    assert proc.returncode == -signal.SIGKILL
    assert not out.exists()
    res = run_cli("recover", str(journal), "-o", str(out))
    assert res.returncode == 0, res.stderr
    rec = load_recording(out)
    n = rec.samples.shape[0]
    assert res.stdout.strip().startswith(f"{out}: recovered {n} samples") and "nothing dropped" in res.stdout
    # everything the board got into the pty up to one second before the kill is there, and equal to what it sent
    # (a recorder starved of CPU lets the pty overflow: the board logs those frames as overruns, never received)
    overruns = {e["index"] for e in read_log(tmp_path / "board.jsonl") if e["event"] == "overrun"}
    delivered_end = max(i + 20 for i in range(0, round(sent - fs), 20) if i not in overruns)
    assert rec.first_index + n >= delivered_end, f"recovered {rec.first_index}..{rec.first_index + n}, sent {sent}, {len(overruns)} overruns"
    truth = board_truth(7, SURFACES, rec.first_index, n)
    valid = rec.valid_mask()
    assert np.array_equal(rec.samples[valid], truth[valid])
    for pos, count in rec.lost:
        assert all(i in overruns for i in range(rec.first_index + pos, rec.first_index + pos + count, 20))
    assert rec.meta["recovered_from"] == str(journal) and rec.meta["port"] == board.link
    assert journal.exists()  # recover never removes the journal


def _frames(samples: np.ndarray, first: int, skip: tuple[int, ...] = ()) -> list[Frame]:
    return [Frame(first + i, samples[i:i + 20]) for i in range(0, samples.shape[0], 20) if i // 20 not in skip]


def _journal_of(tmp_path: Path, samples: np.ndarray, first: int) -> Path:
    """A journal as a killed recorder leaves it (chunks of 1000 rows, no .npz)."""
    journal = journal_path(tmp_path / "k.npz")
    writer = JournalWriter(journal, encode_header(20000.0, 2, 1e-4, "P120", {}))
    for at in range(0, samples.shape[0], 1000):
        block = samples[at:at + 1000]
        writer.append(encode_chunk(at, first + at, block.shape[0], [], {"crc_errors": 0}, block))
    writer.close()
    return journal


def test_sink_places_every_frame_at_its_index_and_lists_gaps(tmp_path: Path) -> None:
    samples = np.random.default_rng(1).integers(-3000, 3000, (5000, 2), dtype=np.int16)
    sink = RecordingSink(tmp_path / "s.npz", fs=20000.0, channels=2, volts_per_count=1e-4, limit=4500)
    for frame in _frames(samples, 10**9, skip=(3, 4, 100)):
        sink.add(frame)
    assert sink.done
    result = sink.finish()
    rec = load_recording(tmp_path / "s.npz")
    assert result.error is None and result.samples == 4500 and result.samples_lost == 60
    assert rec.first_index == 10**9 and rec.lost.tolist() == [[60, 40], [2000, 20]]
    expected = samples[:4500].copy()
    expected[60:100] = expected[2000:2020] = 0
    assert np.array_equal(rec.samples, expected)
    assert not (tmp_path / "s.npz.journal").exists()  # a clean stop removes the journal


def test_recover_drops_a_torn_last_chunk_and_a_corrupt_one(tmp_path: Path) -> None:
    samples = np.random.default_rng(2).integers(-3000, 3000, (4000, 2), dtype=np.int16)
    journal = _journal_of(tmp_path, samples, 500)
    scan = read_journal(journal)
    assert [c.position for c in scan.chunks] == [0, 1000, 2000, 3000] and scan.dropped_chunks == 0
    # a torn last chunk: the power went while it was being written
    with open(journal, "r+b") as fh:
        fh.truncate(scan.size - 1234)
    res = run_cli("recover", str(journal), "-o", str(tmp_path / "torn.npz"))
    assert res.returncode == 0, res.stderr
    assert "recovered 3000 samples" in res.stdout and "dropped 1 damaged or torn chunk(s), " in res.stdout
    rec = load_recording(tmp_path / "torn.npz")
    assert np.array_equal(rec.samples, samples[:3000]) and rec.first_index == 500 and rec.lost.size == 0 and rec.label == "P120"
    # one flipped bit in the second chunk: its rows are lost, the chunks after it kept
    with open(journal, "r+b") as fh:
        fh.seek(scan.chunks[1].offset + 100)
        byte = fh.read(1)
        fh.seek(-1, os.SEEK_CUR)
        fh.write(bytes([byte[0] ^ 0x10]))
    result = recover(journal, tmp_path / "bit.npz")
    assert (result.chunks, result.dropped_chunks, result.samples, result.samples_lost) == (2, 2, 3000, 1000)
    rec = load_recording(tmp_path / "bit.npz")
    assert rec.lost.tolist() == [[1000, 1000]]
    assert np.array_equal(rec.samples[rec.valid_mask()], np.concatenate([samples[:1000], samples[2000:3000]]))


@pytest.mark.parametrize(("tail", "dropped"), [(b"\0", 0), (b"\0" * 5000, 0), (b"\xff" * 100, 1)], ids=["one-zero", "zeros", "garbage"])
def test_recover_keeps_the_last_intact_chunk_before_a_tail_of_other_bytes(tail: bytes, dropped: int, tmp_path: Path) -> None:
    """A power cut leaves zeros after the last write: the intact last chunk before them was dropped as damaged (its end
    neither the file's nor a marker), 0.5 s of fsynced samples lost for one zero byte (an outside audit)."""
    samples = np.random.default_rng(3).integers(-3000, 3000, (4000, 2), dtype=np.int16)
    samples[3500] = (19028, 19267)  # the bytes of the chunk marker, "TJCK", inside the last chunk's samples (a reviewer's case)
    journal = _journal_of(tmp_path, samples, 0)
    with open(journal, "ab") as fh:
        fh.write(tail)
    result = recover(journal, tmp_path / "r.npz")
    assert (result.chunks, result.samples, result.samples_lost, result.dropped_chunks, result.dropped_bytes) == (4, 4000, 0, dropped, len(tail))
    assert np.array_equal(load_recording(tmp_path / "r.npz").samples, samples)
    assert result.line().endswith(f"nothing dropped but {len(tail)} zero bytes after the last chunk" if not dropped
                                  else f"dropped 1 damaged or torn chunk(s), {len(tail)} bytes")


def test_recover_refuses_the_journal_of_a_running_recorder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An audit recovered a live recorder's journal (part of the capture, "nothing dropped"), removed it as after a
    recovery, and the recorder then failed at its stop with the whole capture lost: a locked journal is refused."""
    from tactiled.cli.main import main

    journal = journal_path(tmp_path / "live.npz")
    writer = JournalWriter(journal, encode_header(20000.0, 2, 1e-4, "P120", {}))  # holds the lock, as a recorder does
    writer.append(encode_chunk(0, 0, 1000, [], {"crc_errors": 0}, np.zeros((1000, 2), np.int16)))
    out = tmp_path / "copy.npz"
    assert main(["recover", str(journal), "-o", str(out)]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"tactiled: error: {journal}: in use by a running recorder (it holds the journal's lock), which writes its recording itself "
        "when it stops; nothing written"]
    assert not out.exists()
    writer.close()  # the recorder gone (killed or stopped): its journal is recovered
    assert recover(journal, out).samples == 1000


def test_recover_refuses_what_is_not_a_journal(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "x.journal"
    bad.write_bytes(b"PK\x03\x04 not a journal")
    res = cli_here(capfd, "recover", str(bad), "-o", str(tmp_path / "x.npz"))
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [f"tactiled: error: {bad}: not a tactiled journal (no TACTJNL header)"]
    assert not (tmp_path / "x.npz").exists()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_and_sighup_save_a_recording(tmp_path: Path, sig: signal.Signals) -> None:
    out = tmp_path / "r.npz"
    with running_board(tmp_path, seed=4) as board, spawned("record", "--port", board.link or "", "--seconds", "600", "-o", str(out)) as proc:
        wait_journal(board, tmp_path / "r.npz.journal", 20000)
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 0, stderr
    rec = load_recording(out)
    n = rec.samples.shape[0]
    assert n >= 4000 and f"{n} samples" in stdout
    assert np.array_equal(rec.samples[rec.valid_mask()], board_truth(4, SURFACES, rec.first_index, n)[rec.valid_mask()])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["board.jsonl", "dev", "r.npz"]  # journal removed, no temporary file left


def test_bad_output_path_is_one_line_before_any_capture(tmp_path: Path) -> None:
    board = VirtualBoard(SensorSimulator(SimParams(), seed=1), SURFACES, link=str(tmp_path / "dev"))
    board.open()  # a port that opens, and sends nothing: the output is checked before any capture
    (tmp_path / "exists.npz").write_bytes(b"old")
    (tmp_path / "file").write_bytes(b"")
    (tmp_path / "dir.npz").mkdir()
    cases = {
        tmp_path / "missing" / "r.npz": f"folder {tmp_path / 'missing'} does not exist",
        tmp_path / "file" / "r.npz": f"{tmp_path / 'file'} is not a folder",
        Path("/proc/self/r.npz"): "folder /proc/self is not writable",
        tmp_path / "exists.npz": "exists (--force overwrites it)",
        tmp_path / "dir.npz": "is a folder",
    }
    try:
        for out, message in cases.items():
            res = run_cli("record", "--port", str(tmp_path / "dev"), "--seconds", "1", "-o", str(out), timeout=20)
            assert res.returncode == 2
            assert res.stderr.strip().splitlines() == [f"tactiled: error: {out}: {message}"]
    finally:
        board.close()
    assert (tmp_path / "exists.npz").read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dev", "dir.npz", "exists.npz", "file"]


def test_a_leftover_journal_is_kept_aside_never_overwritten(tmp_path: Path) -> None:
    samples = np.random.default_rng(3).integers(-3000, 3000, (2000, 2), dtype=np.int16)
    journal = _journal_of(tmp_path, samples, 0)
    before = journal.read_bytes()
    sink = RecordingSink(tmp_path / "k.npz", fs=20000.0, channels=2, volts_per_count=1e-4)
    assert sink.finish().error is None
    assert Path(f"{journal}.1").read_bytes() == before and not journal.exists()


def test_full_disk_stops_the_capture_and_keeps_the_journal(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import tactiled.files.journal

    room = [60_000]  # bytes the "disk" takes before it is full
    real_write = os.write

    def write(fd: int, data: memoryview) -> int:
        if room[0] <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        n = min(len(data), room[0])
        room[0] -= n
        return real_write(fd, data[:n])

    monkeypatch.setattr(tactiled.files.journal.os, "write", write)
    samples = np.random.default_rng(5).integers(-3000, 3000, (20000, 2), dtype=np.int16)
    errors: list[str] = []
    out = tmp_path / "f.npz"
    sink = RecordingSink(out, fs=20000.0, channels=2, volts_per_count=1e-4, on_error=errors.append, commit_s=0.2)  # 16 kB chunks
    for frame in _frames(samples, 0):
        sink.add(frame)
    result = sink.finish()
    assert result.error is not None and errors == [result.error] and len(result.error.splitlines()) == 1
    assert "No space left on device" in result.error and f"tactiled recover {sink.journal} -o {out}" in result.error
    assert not out.exists()
    monkeypatch.undo()
    scan = read_journal(sink.journal)
    assert scan.dropped_chunks == 0 and scan.dropped_bytes == 0  # cut back to the last whole chunk
    assert 0 < result.samples == scan.rows < 20000 and sink.journal.stat().st_size <= 60_000
    recover(sink.journal, tmp_path / "back.npz")
    assert np.array_equal(load_recording(tmp_path / "back.npz").samples, samples[:scan.rows])


def _can_mount_tmpfs(tmp_path: Path) -> bool:
    probe = subprocess.run(["unshare", "-rm", "sh", "-c", f"mount -t tmpfs -o size=64k tmpfs {tmp_path}"], capture_output=True)
    return probe.returncode == 0


def test_full_tmpfs_stops_record_cleanly_and_the_journal_recovers(tmp_path: Path) -> None:
    if shutil.which("unshare") is None or not _can_mount_tmpfs(tmp_path):
        pytest.skip("needs unprivileged user and mount namespaces (unshare -rm) for a small tmpfs")
    disk = tmp_path / "disk"
    disk.mkdir()
    keep = tmp_path / "kept.journal"
    with running_board(tmp_path, seed=6) as board:
        # a 160 kB disk: the header and about 2 s of samples; the journal is copied out before the namespace goes
        script = (f'mount -t tmpfs -o size=160k tmpfs {disk} && "$@"; rc=$?; cp {disk}/r.npz.journal {keep}; ls -a {disk} >&2; exit $rc')
        proc = subprocess.run(["unshare", "-rm", "sh", "-c", script, "sh",
                               *tactiled_cmd("record", "--port", board.link or "", "--seconds", "600", "-o", f"{disk}/r.npz")],
                              capture_output=True, text=True, timeout=60, cwd=REPO)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 1, proc.stderr
    assert lines[0].startswith(f"tactiled: error: {disk}/r.npz.journal: No space left on device: capture stopped after ")
    assert lines[0].endswith(f"kept in the journal: tactiled recover {disk}/r.npz.journal -o {disk}/r.npz")
    assert lines[1:] == [".", "..", "r.npz.journal"]  # no .npz, no temporary file
    res = run_cli("recover", str(keep), "-o", str(tmp_path / "r.npz"))
    assert res.returncode == 0 and "nothing dropped" in res.stdout, res.stdout + res.stderr
    rec = load_recording(tmp_path / "r.npz")
    n = rec.samples.shape[0]
    assert n >= 20000 and keep.stat().st_size <= 160 * 1024
    assert np.array_equal(rec.samples[rec.valid_mask()], board_truth(6, SURFACES, rec.first_index, n)[rec.valid_mask()])


def test_run_record_streams_to_the_journal_and_sigterm_saves(tmp_path: Path) -> None:
    out = tmp_path / "d.npz"
    with running_board(tmp_path, seed=8) as board, spawned("run", "--no-model", "--port", board.link or "", "--publish", f"ipc://{tmp_path}/pub",
                                                           "--record", str(out)) as proc:
        wait_journal(board, tmp_path / "d.npz.journal", 40000)  # on disk while the daemon runs
        proc.send_signal(signal.SIGHUP)  # reload: without a model, refused in one line, and the daemon goes on recording
        proc.send_signal(signal.SIGTERM)
        _stdout, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 0, stderr
    rec = load_recording(out)
    n = rec.samples.shape[0]
    assert n >= 8000 and rec.meta["source"] == "tactiled run --record"  # 40 kB of journal: ~10k samples less chunk headers
    assert np.array_equal(rec.samples[rec.valid_mask()], board_truth(8, SURFACES, rec.first_index, n)[rec.valid_mask()])
    assert not (tmp_path / "d.npz.journal").exists()


def _record_bytes(tmp_path: Path, data: bytes, seconds: float) -> tuple[Path, str]:
    """``tactiled record`` of a pty to which ``data`` (board frames) is written once the recorder holds the port; (output, stderr)."""
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    out = tmp_path / "r.npz"
    name = os.ttyname(slave)
    try:
        with spawned("-v", "record", "--port", name, "--seconds", str(seconds), "-o", str(out)) as proc:
            assert proc.stderr is not None
            assert "recording" in proc.stderr.readline()  # the port checked, the reader started

            def port_open() -> bool:  # once it holds the port, what we write is the recorder's alone (no other reader)
                try:
                    proc.wait(0.05)  # the predicate waits: a short block on the process instead of a spin
                except subprocess.TimeoutExpired:
                    return any(os.path.realpath(fd) == name for fd in Path(f"/proc/{proc.pid}/fd").iterdir() if fd.is_symlink())
                raise AssertionError(f"record ended before opening the port: {proc.communicate()[1]}")
            wait_for(port_open, timeout=30, what="the recorder to open the port")
            os.write(master, data)
            try:
                _stdout, stderr = proc.communicate(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()
                pytest.fail(f"record did not finish on the {len(data)} bytes sent: {proc.communicate()[1]}")
    finally:
        os.close(master)
        os.close(slave)
    assert proc.returncode == 0, stderr
    return out, stderr


def test_record_takes_a_board_restart_far_ahead_as_a_restart_not_as_lost_samples(tmp_path: Path) -> None:
    """A 2**31 forward jump of the index (a board reset past half its counter) is a restart: the capture goes on, nothing zero-filled."""
    from tactiled.board.frames import encode_frames

    rng = np.random.default_rng(4)
    before, after = (rng.integers(-900, 900, (800, 2)).astype(np.int16) for _ in range(2))
    out, _ = _record_bytes(tmp_path, encode_frames(1000, before) + encode_frames((1000 + 800 + 2**31) % 2**32, after), 0.08)
    rec = load_recording(out)
    assert rec.first_index == 1000 and rec.lost.size == 0 and rec.meta["restarts"] == 1
    assert np.array_equal(rec.samples, np.concatenate([before, after]))


def test_record_drops_a_duplicated_frame_and_counts_it_in_meta(tmp_path: Path) -> None:
    from tactiled.board.frames import encode_frames

    rng = np.random.default_rng(5)
    before, after = (rng.integers(-900, 900, (800, 2)).astype(np.int16) for _ in range(2))
    again = encode_frames(1400, before[400:420])  # a frame the board sent twice
    out, _ = _record_bytes(tmp_path, encode_frames(1000, before) + again + encode_frames(1800, after), 0.08)
    rec = load_recording(out)
    assert rec.lost.size == 0 and rec.meta["duplicate_frames"] == 1
    assert np.array_equal(rec.samples, np.concatenate([before, after]))


def test_record_writes_an_unplug_as_a_gap_never_a_splice(tmp_path: Path) -> None:
    """A 25 s unplug (the index 500 000 samples ahead when frames come back) is a lost range of 500 000 rows, counted: the rows
    after it keep their sensor time, never spliced onto the rows before it."""
    from tactiled.board.frames import encode_frames

    rng = np.random.default_rng(6)
    before, after = (rng.integers(-900, 900, (800, 2)).astype(np.int16) for _ in range(2))
    gap = 500_000
    out, _ = _record_bytes(tmp_path, encode_frames(1000, before) + encode_frames(1000 + 800 + gap, after), (1600 + gap) / 20000)
    rec = load_recording(out)
    assert rec.first_index == 1000 and rec.lost.tolist() == [[800, gap]] and rec.meta["restarts"] == 0
    assert rec.samples.shape[0] == 1600 + gap
    assert np.array_equal(rec.samples[:800], before) and np.array_equal(rec.samples[800 + gap:], after)


def test_record_takes_a_board_reset_at_a_small_index_as_a_restart_not_duplicates(tmp_path: Path) -> None:
    """A board reset while its index is under the duplicate window (65 536): other samples at indices already recorded are a
    restart (counted in meta), never dropped as duplicates: every sample after the reset is kept."""
    from tactiled.board.frames import encode_frames

    rng = np.random.default_rng(7)
    before, after = (rng.integers(-900, 900, (800, 2)).astype(np.int16) for _ in range(2))
    out, _ = _record_bytes(tmp_path, encode_frames(1000, before) + encode_frames(0, after), 0.08)
    rec = load_recording(out)
    assert rec.meta["restarts"] == 1 and rec.meta["duplicate_frames"] == 0 and rec.lost.size == 0
    assert np.array_equal(rec.samples, np.concatenate([before, after]))


@pytest.mark.parametrize("what", ["fifo", "file"])
def test_the_sink_never_replaces_what_appeared_at_its_output(what: str, tmp_path: Path) -> None:
    """At the end the output is checked again: a FIFO (or a device) there is never written, even with force; a file that
    appeared is not replaced without force. The journal keeps the capture either way."""
    out = tmp_path / "o.npz"
    sink = RecordingSink(out, fs=20000.0, channels=2, volts_per_count=1e-4, force=what == "fifo")
    for frame in _frames(np.ones((400, 2), dtype=np.int16), 0):
        sink.add(frame)
    if what == "fifo":
        os.mkfifo(out)
    else:
        out.write_bytes(b"someone else's")
    result = sink.finish()
    assert result.error is not None and len(result.error.splitlines()) == 1
    assert ("not a regular file" if what == "fifo" else "exists (--force overwrites it)") in result.error
    assert sink.journal.exists() and read_journal(sink.journal).rows == 400
    if what == "file":
        assert out.read_bytes() == b"someone else's"


def test_run_record_on_a_full_disk_exits_1(tmp_path: Path) -> None:
    """``run --record`` on a disk that fills: the capture stops (one line), the daemon goes on publishing until SIGTERM, then
    exits 1 (not 0), the journal kept for ``tactiled recover``."""
    if shutil.which("unshare") is None or not _can_mount_tmpfs(tmp_path):
        pytest.skip("needs unprivileged user and mount namespaces (unshare -rm) for a small tmpfs")
    disk = tmp_path / "disk"
    disk.mkdir()
    with running_board(tmp_path, seed=9) as board:
        # a 100 kB disk: the header and about a second of samples; the daemon runs until the capture stopped, then SIGTERM
        script = f'mount -t tmpfs -o size=100k tmpfs {disk} && exec "$@"'
        with subprocess.Popen(["unshare", "-rm", "sh", "-c", script, "sh",
                               *tactiled_cmd("run", "--no-model", "--port", board.link or "", "--publish", f"ipc://{tmp_path}/pub",
                                             "--record", f"{disk}/r.npz")],
                              stderr=subprocess.PIPE, text=True, cwd=REPO) as proc:
            assert proc.stderr is not None
            lines: list[str] = []

            def stopped_line() -> bool:
                line = proc.stderr.readline()  # blocks until the daemon writes a line (or exits: "")
                if not line:
                    raise AssertionError(f"run ended early: {''.join(lines)}")
                lines.append(line)
                return "No space left on device: capture stopped after" in line

            try:
                wait_for(stopped_line, timeout=60, what="the capture to stop on the full disk")
                proc.send_signal(signal.SIGTERM)  # sh exec'd the daemon: the signal is its own
                rest = proc.stderr.read()
                proc.wait(30)
            finally:
                if proc.poll() is None:
                    proc.kill()
    assert proc.returncode == 1, "".join(lines) + rest
    assert "Traceback" not in "".join(lines) + rest


def test_a_jump_the_recording_cannot_hold_ends_it_in_bounded_memory(tmp_path: Path) -> None:
    """A 2**31 - 1 jump (the longest the counter can say: 8 GiB of zero rows at 2 channels) never reaches the journal or the .npz
    as rows: the recording ends before it, the gap in meta. Memory stays small."""
    import tracemalloc

    rng = np.random.default_rng(8)
    before, after = (rng.integers(-900, 900, (800, 2)).astype(np.int16) for _ in range(2))
    out = tmp_path / "o.npz"
    sink = RecordingSink(out, fs=20000.0, channels=2, volts_per_count=1e-4)
    jump = (1 << 31) - 1
    tracemalloc.start()
    try:
        for frame in _frames(before, 1000):
            sink.add(frame)
        for frame in _frames(after, 1800 + jump):
            sink.add(frame)
        result = sink.finish()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 16 << 20, peak
    assert result.error is None and sink.done and sink.ended_by_gap == jump
    rec = load_recording(out)
    assert np.array_equal(rec.samples, before) and rec.lost.size == 0 and rec.meta["ended_by_gap"] == jump


def test_a_gap_across_the_limit_ends_a_limited_recording(tmp_path: Path) -> None:
    """``record --seconds``: a gap that runs past the limit ends the recording at its last row received (it used to wait
    for ever: rows beyond the limit were dropped one frame at a time without ever reaching it)."""
    before = np.ones((400, 2), dtype=np.int16)
    sink = RecordingSink(tmp_path / "o.npz", fs=20000.0, channels=2, volts_per_count=1e-4, limit=1000)
    for frame in _frames(before, 0):
        sink.add(frame)
    assert not sink.done
    sink.add(Frame(5000, before[:20]))
    assert sink.done and sink.finish().error is None
    assert load_recording(tmp_path / "o.npz").samples.shape[0] == 400


def record_until_said(tmp_path: Path, text: str, *options: str) -> str:
    """``tactiled record OPTIONS`` from a virtual board (2 channels, 20 kHz) until a line of its log holds ``text``, then
    Ctrl-C; everything it wrote (log, summary)."""
    with running_board(tmp_path, seed=1) as board, \
            spawned("record", "--port", board.link or "", *options, "--seconds", "600", "-o", str(tmp_path / "r.npz")) as proc:
        assert proc.stderr is not None
        lines: list[str] = []
        wait_for(lambda: lines.append(proc.stderr.readline()) or text in lines[-1], 30, text)  # type: ignore[union-attr]
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=30)
    return "".join(lines) + stdout + stderr


def test_record_says_at_once_that_the_boards_frames_have_another_channel_count(tmp_path: Path) -> None:
    """A two-channel board recorded as one channel: every frame is skipped, so the recording would never fill; the recorder
    says why at once (not after the seconds it would never reach), and the summary counts the frames after Ctrl-C."""
    said = record_until_said(tmp_path, "channel(s) skipped", "--channels", "1")
    assert "frames of 2 channel(s) skipped, sensor.channels is 1" in said and said.count("channel(s) skipped") == 1, said
    assert "frames of another channel count skipped" in said, said


def test_record_says_when_the_boards_rate_is_not_sensor_fs(tmp_path: Path) -> None:
    """sensor.fs is written into the recording, and the board does not send its rate: recorded as 2 kHz, a 20 kHz board
    is said once, naming both rates, after the few seconds the recorder measures it over."""
    said = [line for line in record_until_said(tmp_path, "samples arrive at about", "--fs", "2000").splitlines() if "samples arrive" in line]
    assert len(said) == 1 and "sensor.fs is 2000 Hz" in said[0], said
    rate = float(said[0].split("samples arrive at about ")[1].split(" Hz")[0])
    assert 15_000 < rate < 25_000, said[0]


def test_record_shorter_than_the_rate_measurement_says_the_rate_at_its_end(tmp_path: Path) -> None:
    """An outside audit: --fs 10000 on a 20 kHz board for a few seconds (a first day's recordings) wrote the wrong rate in
    silence, since the rate was measured over RATE_AFTER_S (5 s) only. A recording that ends sooner is measured over what
    it had, at least RATE_MIN_S (1 s): said once, the file written as asked (exit 0)."""
    with running_board(tmp_path, seed=1) as board:
        res = run_cli("record", "--port", board.link or "", "--fs", "10000", "--seconds", "3", "-o", str(tmp_path / "r.npz"))
    said = [line for line in res.stderr.splitlines() if "samples arrive at about" in line]
    assert res.returncode == 0 and len(said) == 1 and "sensor.fs is 10000 Hz" in said[0], res.stderr
    assert 15_000 < float(said[0].split("samples arrive at about ")[1].split(" Hz")[0]) < 25_000, said[0]
