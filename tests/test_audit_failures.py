"""A machine that misbehaves under the daemon (an outside audit, nineteenth session): a raw capture the disk refuses ends
alone, and a first look at the port keeps the stale bytes for the reader to count.

Real ptys (the virtual board), a real daemon process under a file-size limit, real ZeroMQ sockets on ipc.
"""

from __future__ import annotations

import os
import resource
import tty
from pathlib import Path

import numpy as np
import pytest
from tactiled_client import BlockingSubscriber, Status

from tactiled.board.frames import encode_frames
from tactiled.board.serialsource import SerialSource, check_port
from tactiled.sim.physics import SensorSimulator, SimParams, pick_surfaces
from tactiled.sim.virtualboard import VirtualBoard
from tests.conftest import cli_here, daemon_process, run_cli, running, wait_for

RAW_LIMIT = 200_000  # bytes: about 2.2 s of the standard board's frames


def _small_files() -> None:
    """In the daemon's process, before it starts: no file may grow past RAW_LIMIT (Python ignores SIGXFSZ, so a write past
    it fails with EFBIG, as one on a full disk fails with ENOSPC)."""
    resource.setrlimit(resource.RLIMIT_FSIZE, (RAW_LIMIT, RAW_LIMIT))


def test_a_raw_capture_the_machine_refuses_ends_alone_and_the_daemon_reads_on(tmp_path: Path) -> None:
    """``run --raw`` past a file-size limit: one line naming the file, the capture ends with what is on disk (it replays),
    the daemon keeps reading without a reconnect or a lost sample, and exits 1 as for a failed recording. The write's
    error used to reach the serial reader, which took it for an unplug and reopened the port ~80 times a second."""
    link, endpoint, raw = str(tmp_path / "tty"), f"ipc://{tmp_path}/pub", tmp_path / "out.bin"
    with open(tmp_path / "board.jsonl", "w") as log:
        board = VirtualBoard(SensorSimulator(SimParams(), seed=0), pick_surfaces(2), link=link, speed=3.0, seed=0, log=log)
        with running(board), daemon_process(link, endpoint, "--no-model", "--raw", str(raw), preexec_fn=_small_files) as proc, \
                BlockingSubscriber(endpoint, topics=["status"], timeout=30) as sub:

            def far_enough() -> Status | None:
                msg = sub.receive()
                return msg if isinstance(msg, Status) and msg.samples > 2 * RAW_LIMIT // 4 else None  # twice what it holds (4.6 B a sample)

            last = wait_for(far_enough, 60, "the daemon reading past the capture's end")
            proc.terminate()
            _, err = proc.communicate(timeout=30)
    assert isinstance(last, Status) and (last.reconnects, last.samples_lost) == (0, 0), last
    said = [line for line in err.splitlines() if "raw capture stopped" in line]
    assert len(said) == 1 and str(raw) in said[0] and "File too large" in said[0], err
    assert proc.returncode == 1 and "Traceback" not in err, err
    assert 0 < raw.stat().st_size <= RAW_LIMIT
    replay = run_cli("replay", "--no-model", str(raw))
    assert replay.returncode == 0, replay.stderr


def test_a_first_look_at_the_port_keeps_what_it_holds_for_the_reader_to_count() -> None:
    """``record`` and ``run --no-wait`` look at the port before the reader opens it. pyserial's open empties a tty's input,
    so the frames the board had sent by then vanished uncounted: ``discarded_at_start`` said 2 668 of 21 528 stale bytes.
    After :func:`check_port` the reader still finds, and counts, every byte the port held."""
    master, slave = os.openpty()
    try:
        tty.setraw(slave)
        held = encode_frames(0, np.zeros((400, 2), dtype=np.int16))  # sent before anyone read: held in the tty
        assert os.write(master, held) == len(held) < 4096
        check_port(os.ttyname(slave))
        source = SerialSource(os.ttyname(slave), lambda data: None)
        port = source._open()
        try:
            assert source._discard_waiting(port) == len(held)
        finally:
            port.close()
    finally:
        os.close(master)
        os.close(slave)


def test_an_export_the_machine_refuses_leaves_no_file_under_its_name(tmp_path: Path) -> None:
    """``export`` past a file-size limit (a full disk, a Ctrl-C: the same path): exit 1, and no MCAP file without its
    footer under the output's name, which a rerun then took for a finished one ("exists (--force overwrites it)"; an
    outside audit). It writes to a temporary file beside it and renames it when whole, as features and recover do."""
    import subprocess

    from tactiled.files.recording import Recording, save_recording
    from tests.conftest import tactiled_cmd

    rec = tmp_path / "r.npz"
    save_recording(rec, Recording(np.random.default_rng(0).integers(-3000, 3000, (100_000, 2)).astype(np.int16), 20_000.0, 1e-4))
    res = subprocess.run(tactiled_cmd("export", str(rec), "-o", str(tmp_path / "out.mcap"), "--no-model"), capture_output=True,
                         text=True, timeout=120, preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (RAW_LIMIT, RAW_LIMIT)))
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.npz"]


def test_an_output_that_is_one_of_the_inputs_is_refused_even_with_force(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """``features r.npz -o r.npz --force`` replaced the recording with its features table, exit 0 (an outside audit);
    ``train`` and ``recover`` could do the same. One line, exit 2, the input as it was."""
    from tactiled.files.recording import Recording, save_recording

    rec = tmp_path / "r.npz"
    save_recording(rec, Recording(np.zeros((20_000, 2), dtype=np.int16), 20_000.0, 1e-4))
    before = rec.read_bytes()
    for argv in (["features", str(rec), "-o", str(rec), "--force"], ["train", str(rec), "-o", str(rec), "--force"],
                 ["recover", str(rec), "-o", str(rec), "--force"]):
        res = cli_here(capfd, *argv)
        assert res.returncode == 2 and res.stderr.strip().splitlines() == [
            f"tactiled: error: {rec}: is one of the files it reads; write it elsewhere"], (argv, res.stderr)
    assert rec.read_bytes() == before
