"""Hostile files, configs, flags and subscribers: each is refused with one line (exit 2 from the CLI), never a traceback, never unbounded memory.

The corpus in tests/hostile/ is committed; ``python tests/hostile/make_corpus.py`` rebuilds it.
"""

from __future__ import annotations

import io
import json
import math
import subprocess
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest
import zmq

from tactiled.errors import RecordingError
from tactiled.features_file import load_features
from tactiled.model import load_model, softmax
from tactiled.npzio import NpzError, read_npz
from tactiled.recording import atomic_savez, load_recording
from tests.conftest import REPO, run_cli, tactiled_cmd, wait_for

CORPUS = REPO / "tests" / "hostile"
GOOD_REC, GOOD_MODEL = str(CORPUS / "rec-good.npz"), str(CORPUS / "model-good.npz")

# file -> what its one-line error must say
EXPECTED = {
    "rec-bomb-bzip2.npz": "samples: compression method bzip2 refused",
    "rec-meta-nested.npz": "meta: JSON nested deeper than 32 levels",
    "rec-meta-huge-int.npz": "meta: not JSON: Exceeds the limit",
    "rec-samples-nan.npz": "samples: contains NaN or Inf",
    "rec-samples-complex.npz": "samples: dtype complex128 refused",
    "rec-samples-uint8.npz": "samples: must be int16, float32 or float64",
    "rec-samples-object.npz": "samples: cannot load without pickle",
    "rec-samples-struct.npz": "samples: dtype [('a', '<i2')] refused",
    "rec-fs-tiny.npz": "fs: must be in [1, 1e+07] Hz",
    "rec-fs-nan.npz": "fs: must be in [1, 1e+07] Hz",
    "rec-channels-1000.npz": "samples: must have shape (n, C) with 1 <= C <= 64",
    "rec-truncated.npz": "not a readable .npz file",
    "rec-declares-more.npz": "samples: declares shape (1000000, 2)",
    "rec-members-100.npz": "lists 104 members, more than the 64",
    "rec-not-zip.npz": "not a readable .npz file",
    "model-temperature-zero.npz": "header.temperature: must be a finite number",
    "model-temperature-nan.npz": "header.temperature: must be a finite number",
    "model-temperature-inf.npz": "header.temperature: must be a finite number",
    "model-temperature-string.npz": "header.temperature: must be a finite number",
    "model-window-huge.npz": "settings.duration_s: 1..1048576 samples",
    "model-level-99.npz": "settings.level: must be in 1..8",
    "model-half-width-0.npz": "settings: spike removal out of range",
    "model-half-width-float.npz": "settings: max_windows, half_width, level must be integers",
    "model-wavelet-bogus.npz": "settings: wavelet or mode unknown",
    "model-band-beyond-nyquist.npz": "band must satisfy 0 <= lo < hi <= fs/2",
    "model-third-channel.npz": "settings.names: features of 3 channels, the model has 2",
    "model-coef-nan.npz": "coef, intercept: shapes do not match the header or not finite",
    "model-coef-shape.npz": "coef, intercept: shapes do not match the header or not finite",
    "model-scale-zero.npz": "scaler_scale: must be > 0",
    "model-svm-huge.npz": "train_x, train_y: shapes do not match the header (at most 4000 rows for svm)",
    "model-svm-gamma-negative.npz": "gamma scale, auto or a number in (0, 1e6]",
    "model-svm-c-huge.npz": "params.C: must be a number in [1e-06, 10000]",
    "model-header-nested.npz": "header: JSON nested deeper than 32 levels",
    "model-extra-member.npz": "junk: not an array of a linear model",
    "config-fs-inf.toml": "sensor.fs: must be a finite number",
    "config-ring-1e9.toml": "ring.seconds: must be in [1, 3600] s",
    "config-fs-1e12.toml": "sensor.fs: must be in [100, 1e6] Hz",
    "config-fs-tiny.toml": "sensor.fs: must be in [100, 1e6] Hz",
    "config-half-width-huge.toml": "spikes.half_width: must be in 1..1000",
    "config-baudrate-2p63.toml": "sensor.baudrate: must be an integer",
    "config-nested-arrays.toml": "not valid TOML: arrays or tables nested too deeply",
    "config-port-socket.toml": "sensor.port: is a URL (socket://), not a device path",
    "config-retry-nan.toml": "serial.retry_max_s: must be a finite number",
}


def _commands(name: str) -> list[list[str]]:
    path = str(CORPUS / name)
    if name.startswith("rec-"):
        return [["replay", "--no-model", path], ["features", path, "-o", "/dev/null"]]
    if name.startswith("model-"):
        return [["replay", "--model", path, GOOD_REC], ["score", path, GOOD_REC]]
    return [["check-config", path], ["run", "--config", path, "--no-model"]]


def test_corpus_is_complete() -> None:
    files = {p.name for p in CORPUS.iterdir() if p.suffix in (".npz", ".toml")}
    assert files == set(EXPECTED) | {"rec-good.npz", "model-good.npz"}


def test_corpus_bases_are_valid() -> None:
    """Each hostile variant differs from a valid file only where it is hostile."""
    assert load_recording(GOOD_REC).samples.shape == (4000, 2)
    model = load_model(GOOD_MODEL)
    assert model.kind == "linear" and model.classes == ["rough", "smooth"]


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_hostile_file_is_refused_with_one_line(name: str) -> None:
    for argv in _commands(name):
        res = run_cli(*argv, timeout=60)
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2, (argv, res.stderr[-2000:])
        assert "Traceback" not in res.stderr, res.stderr[-2000:]
        errors = [line for line in lines if line.startswith("tactiled: error:") or "skipped:" in line]
        assert len(errors) == 1 and EXPECTED[name] in errors[0] and (name in errors[0] or argv[0] == "run"), (argv, lines)


def test_bomb_is_refused_before_inflating() -> None:
    """The committed bzip2 member inflates to 2 GiB from 2 kB: refused with next to no memory."""
    path = CORPUS / "rec-bomb-bzip2.npz"
    assert path.stat().st_size < 4096
    info = zipfile.ZipFile(path).getinfo("samples.npy")
    assert info.file_size > 2**31  # what it would inflate to
    tracemalloc.start()
    try:
        with pytest.raises(RecordingError) as err:
            load_recording(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 << 20, peak
    assert str(err.value).splitlines() == [f"{path}: samples: compression method bzip2 refused (NumPy writes stored or deflate members only)"]


def _deflate_bomb(path: Path, nbytes: int, extra: dict[str, bytes] | None = None) -> None:
    """A recording whose ``samples`` member is ``nbytes`` of deflated zeros, sizes declared truthfully."""
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<i2", "fortran_order": False, "shape": (nbytes // 4, 2)})
    fs = io.BytesIO()
    np.save(fs, np.float64(20000))
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("fs.npy", fs.getvalue())
        with zf.open("samples.npy", "w", force_zip64=True) as out:
            out.write(header.getvalue())
            zeros = bytes(1 << 22)
            for _ in range(nbytes // len(zeros)):
                out.write(zeros)
        for name, data in (extra or {}).items():
            zf.writestr(name, data)


def test_deflate_bomb_is_refused_by_its_ratio(tmp_path: Path) -> None:
    path = tmp_path / "bomb.npz"
    _deflate_bomb(path, 64 << 20)
    assert path.stat().st_size < 200_000
    tracemalloc.start()
    try:
        with pytest.raises(RecordingError, match=r"samples: inflates \d+ bytes to 67108864 \(over 200:1\): a decompression bomb") as err:
            load_recording(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 << 20 and "\n" not in str(err.value)


def test_budget_is_shared_by_the_members_read(tmp_path: Path) -> None:
    path = tmp_path / "two.npz"
    np.savez(path, a=np.zeros(1000), b=np.zeros(1000))
    assert set(read_npz(path, max_bytes=16_000)) == {"a", "b"}
    with pytest.raises(NpzError, match="more than the 12000 bytes allowed") as err:
        read_npz(path, max_bytes=12_000)
    assert err.value.key == "b"


def test_members_nobody_reads_are_never_opened(tmp_path: Path) -> None:
    """A valid recording with a corrupt member and a deflate bomb beside it loads: neither member is read."""
    path = tmp_path / "extra.npz"
    _deflate_bomb(path, 64 << 20, extra={"junk.npy": b"not an array"})
    with zipfile.ZipFile(CORPUS / "rec-good.npz") as good, zipfile.ZipFile(path) as bomb, zipfile.ZipFile(tmp_path / "both.npz", "w") as out:
        for info in good.infolist():
            out.writestr(info, good.read(info))
        for name in ("junk.npy", "samples.npy"):
            out.writestr(name.replace("samples", "bomb"), bomb.read("junk.npy") if name == "junk.npy" else b"\x93NUMPY")
    tracemalloc.start()
    try:
        rec = load_recording(tmp_path / "both.npz")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert rec.samples.shape == (4000, 2) and peak < 8 << 20


def test_stream_stops_at_the_declared_size(tmp_path: Path) -> None:
    """The zip says more bytes than the .npy header needs: reading stops at the header's size."""
    path = tmp_path / "long.npz"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        buf = io.BytesIO()
        np.save(buf, np.arange(10, dtype=np.int16))
        zf.writestr("x.npy", buf.getvalue() + bytes(10 << 20))  # 10 MiB of trailing zeros nobody needs
    tracemalloc.start()
    try:
        x = read_npz(path)["x"]
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert x.tolist() == list(range(10)) and peak < 4 << 20


def test_features_file_with_nested_header_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "f.npz"
    arrays = {"header": np.str_("[" * 50_000 + "]" * 50_000), "x": np.zeros((1, 1)), "names": np.array(["a"]), "label": np.array([""]),
              "file": np.zeros(1, int), "slide": np.zeros(1, int), "span": np.zeros((1, 2), int), "files": np.array(["r.npz"])}
    atomic_savez(path, arrays)
    with pytest.raises(RecordingError, match="header: JSON nested deeper than 32 levels") as err:
        load_features(path)
    assert str(path) in str(err.value)


def test_multi_file_replay_goes_on_after_a_nested_meta() -> None:
    res = run_cli("replay", "--no-model", str(CORPUS / "rec-meta-nested.npz"), GOOD_REC)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert f"{GOOD_REC}: " in res.stdout and "slides" in res.stdout


@pytest.mark.parametrize("z", [[np.nan, 1.0], [np.inf, 1.0], [-np.inf, -np.inf], [1e308, -1e308], [np.nan, np.nan]])
@pytest.mark.parametrize("temperature", [1.0, 0.0, math.nan, math.inf, 1e-300])
def test_confidences_are_always_probabilities(z: list[float], temperature: float) -> None:
    p = softmax(np.array(z), temperature)
    assert np.all(np.isfinite(p)) and np.all((p >= 0) & (p <= 1)) and abs(p.sum() - 1) < 1e-9


def test_a_model_that_loads_labels_a_slide(tmp_path: Path) -> None:
    """The corpus' valid model gives finite confidences in [0, 1] on a real recording (replay --json is valid JSON)."""
    res = run_cli("replay", "--json", "--model", GOOD_MODEL, str(REPO / "tests" / "hostile" / "rec-good.npz"))
    assert res.returncode == 0, res.stderr
    for line in res.stdout.splitlines():
        obj = json.loads(line)
        assert obj["confidence"] is None or 0.0 <= obj["confidence"] <= 1.0


@pytest.mark.parametrize(("argv", "message"), [
    (["replay", "--speed", "inf", GOOD_REC], "argument --speed: must be a finite number > 0, got inf"),
    (["replay", "--speed", "-1", GOOD_REC], "argument --speed: must be a finite number > 0, got -1"),
    (["replay", "--speed", "nan", GOOD_REC], "argument --speed: must be a finite number > 0, got nan"),
    (["replay", "--speed", "abc", GOOD_REC], "argument --speed: invalid positive number value: 'abc'"),
    (["replay", "--block", "-5", GOOD_REC], "argument --block: must be an integer in 1..2**31, got -5"),
    (["replay", "--block", "0", GOOD_REC], "argument --block: must be an integer in 1..2**31, got 0"),
    (["replay", "--block", "x", GOOD_REC], "argument --block: invalid positive integer value: 'x'"),
    (["export", GOOD_REC, "-o", "/dev/null", "--batch", "0"], "argument --batch: must be an integer in 1..2**31, got 0"),
    (["record", "--seconds", "inf", "-o", "/dev/null"], "argument --seconds: must be a finite number > 0, got inf"),
    (["record", "--seconds", "1", "-o", "/dev/null", "--channels", "9"], "argument --channels: must be in 1..8, got 9"),
    (["simulate", "serial", "--corrupt", "nan"], "argument --corrupt: must be in [0, 1], got nan"),
    (["train", GOOD_REC, "-o", "/dev/null", "--folds", "0"], "argument --folds: must be an integer in 1..2**31, got 0"),
    (["simulate", "dataset", "--out", "/dev/null", "--seed", "-1"], "argument --seed: must be an integer in 0..2**32-1, got -1"),
])
def test_bad_flags_are_one_line(argv: list[str], message: str) -> None:
    res = run_cli(*argv, timeout=60)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert res.stderr.strip().splitlines()[-1].endswith(f"error: {message}")


def _rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


def test_huge_subscription_does_not_grow_the_daemon(tmp_path: Path) -> None:
    """A SUB sending a 16 MB SUBSCRIBE prefix is disconnected by the daemon (MAXMSGSIZE); its memory stays put, status keeps coming."""
    endpoint = f"ipc://{tmp_path}/pub"
    daemon = subprocess.Popen(tactiled_cmd("run", "--port", str(tmp_path / "no-such-port"), "--no-model", "--publish", endpoint),
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=REPO)
    ctx = zmq.Context()
    status = ctx.socket(zmq.SUB)
    status.setsockopt(zmq.SUBSCRIBE, b"status")
    status.connect(endpoint)
    try:
        wait_for(lambda: status.poll(1000), 60, "a status message")
        status.recv_multipart()
        before = _rss_kb(daemon.pid)
        hostile = ctx.socket(zmq.SUB)
        monitor = hostile.get_monitor_socket(zmq.EVENT_DISCONNECTED)
        hostile.setsockopt(zmq.RECONNECT_IVL, 60_000)  # one attempt: a reconnect would send the subscription again
        hostile.setsockopt(zmq.SUBSCRIBE, b"s" * (16 << 20))
        hostile.connect(endpoint)

        def disconnected() -> bool:
            return bool(monitor.poll(1000)) and zmq.utils.monitor.recv_monitor_message(monitor)["event"] == zmq.EVENT_DISCONNECTED

        wait_for(disconnected, 60, "the daemon to drop the hostile subscriber")
        for _ in range(3):  # the daemon is alive and publishing after it
            wait_for(lambda: status.poll(1000), 30, "status after the hostile subscription")
            status.recv_multipart()
        after = _rss_kb(daemon.pid)
        assert daemon.poll() is None
        assert after - before < 32 * 1024, (before, after)  # kB: the 16 MB prefix never landed in the daemon
        hostile.disable_monitor()
        monitor.close(0)
        hostile.close(0)
    finally:
        status.close(0)
        ctx.term()
        daemon.terminate()
        daemon.wait(10)
