"""Hostile files, configs, flags and subscribers: each is refused with one line (exit 2 from the CLI), never a traceback, never unbounded memory.

The corpus in tests/hostile/ is committed; ``python tests/hostile/make_corpus.py`` rebuilds it.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import socket
import struct
import subprocess
import sys
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest
import zmq
from tactiled_client import schema

from tactiled.config import PublishConfig
from tactiled.errors import ModelError, RecordingError
from tactiled.files.npzio import NpzError, read_npz
from tactiled.files.recording import Recording, atomic_savez, load_recording, save_recording
from tactiled.learn.feature_table import load_features
from tactiled.learn.model import load_model, softmax
from tactiled.service.publish import Publisher
from tactiled.sim.simulate import write_dataset
from tests.conftest import REPO, cli_here, run_cli, tactiled_cmd, usage_error, wait_for

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
    "model-svm-huge.npz": "train_x: 20000 rows, more than the 4000 an svm is refit on at load",
    "model-svm-fitted-bad.npz": "svm_support, svm_n_support, svm_dual_coef, svm_intercept, svm_gamma: shapes or values do not match",
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


RECORDINGS = sorted(n for n in EXPECTED if n.startswith("rec-"))
MODELS = sorted(n for n in EXPECTED if n.startswith("model-"))
CONFIGS = sorted(n for n in EXPECTED if n.startswith("config-"))


def test_corpus_is_complete() -> None:
    files = {p.name for p in CORPUS.iterdir() if p.suffix in (".npz", ".toml")}
    assert files == set(EXPECTED) | {"rec-good.npz", "model-good.npz"}


def test_corpus_bases_are_valid() -> None:
    """Each hostile variant differs from a valid file only where it is hostile."""
    assert load_recording(GOOD_REC).samples.shape == (4000, 2)
    model = load_model(GOOD_MODEL)
    assert model.kind == "linear" and model.classes == ["rough", "smooth"]


@pytest.mark.parametrize("name", RECORDINGS + MODELS)
def test_hostile_file_is_refused_at_load_with_one_line(name: str) -> None:
    path = CORPUS / name
    with pytest.raises(RecordingError if name.startswith("rec-") else ModelError) as err:
        (load_recording if name.startswith("rec-") else load_model)(path)
    assert str(err.value).startswith(f"{path}: ") and "\n" not in str(err.value) and EXPECTED[name] in str(err.value)


def _errors(res: subprocess.CompletedProcess[str]) -> list[str]:
    assert "Traceback" not in res.stderr, res.stderr[-3000:]
    return [line for line in res.stderr.splitlines() if line.startswith("tactiled: error:") or line.startswith("tactiled: skipped:")]


@pytest.fixture(scope="module")
def labelled_good(tmp_path_factory: pytest.TempPathFactory) -> str:
    """The corpus' valid recording with a file label (score and train need ground truth)."""
    rec = load_recording(GOOD_REC)
    rec.label = "rough"
    path = tmp_path_factory.mktemp("good") / "labelled.npz"
    save_recording(path, rec)
    return str(path)


@pytest.mark.parametrize("command", ["replay", "features", "score"])
def test_multi_file_run_names_each_hostile_recording_once_and_goes_on(command: str, labelled_good: str, tmp_path: Path,
                                                                     capfd: pytest.CaptureFixture[str]) -> None:
    """Every hostile recording (the 2 kB bzip2 bomb among them) is one line naming it; the valid file after them is still processed; exit 2.
    (By main() in the test's process, cli_here: the same handler and lines.)"""
    files = [str(CORPUS / n) for n in RECORDINGS] + [labelled_good]
    argv = {"replay": ["replay", "--no-model", *files], "features": ["features", *files, "-o", str(tmp_path / "f.npz")],
            "score": ["score", GOOD_MODEL, *files]}[command]
    res = cli_here(capfd, *argv)
    assert res.returncode == 2, res.stderr[-3000:]
    errors = _errors(res)
    assert len(errors) == len(RECORDINGS), errors
    for name, line in zip(RECORDINGS, errors, strict=True):
        assert f"{CORPUS / name}: " in line and EXPECTED[name] in line, (name, line)
    if command == "replay":
        assert f"{labelled_good}: 1 slides" in res.stdout
    elif command == "features":
        assert load_features(tmp_path / "f.npz")["files"].tolist() == [labelled_good]
    else:
        assert res.stdout.startswith("accuracy ") and "of 1 true slides" in res.stdout


def test_train_names_the_bomb_and_writes_nothing(labelled_good: str, tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "m.npz"
    res = cli_here(capfd, "train", str(CORPUS / "rec-bomb-bzip2.npz"), labelled_good, "-o", str(out), "--method", "quick")
    assert res.returncode == 2 and not out.exists()
    bomb = CORPUS / "rec-bomb-bzip2.npz"
    named = [line for line in res.stderr.splitlines() if str(bomb) in line]
    assert named == [f"train: skipped: {bomb}: {EXPECTED['rec-bomb-bzip2.npz']} (NumPy writes stored or deflate members only)"], res.stderr
    assert _errors(res) == ["tactiled: error: unreadable recordings (listed above); nothing written"]


def test_evaluate_skips_the_bomb_reports_on_the_rest_and_exits_2(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    files = [str(p) for p in write_dataset(tmp_path / "sim", scene="robot", surfaces="2", files_per_surface=2, slides_per_file=2)]
    res = cli_here(capfd, "evaluate", str(CORPUS / "rec-bomb-bzip2.npz"), *files, "--report", str(tmp_path / "rep"), "--experiments", "e",
                   "--quick", "--folds", "2")  # by main() in this process: the same handler and lines
    assert res.returncode == 2
    errors = _errors(res)
    assert len(errors) == 1 and errors[0].startswith(f"tactiled: skipped: {CORPUS / 'rec-bomb-bzip2.npz'}: samples: compression method bzip2")
    assert (tmp_path / "rep" / "report.md").exists() and "4 recordings" in res.stdout


@pytest.mark.parametrize("name", ["model-temperature-zero.npz", "model-header-nested.npz", "model-svm-huge.npz"])
def test_hostile_model_is_one_line_for_replay_score_and_run(name: str, tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    path = str(CORPUS / name)
    for argv in (["replay", "--model", path, GOOD_REC], ["score", path, GOOD_REC],
                 ["run", "--model", path, "--port", str(tmp_path / "no-port"), "--publish", f"ipc://{tmp_path}/pub"]):
        # replay and score by main() in this process (cli_here: the same handler and lines); run, the daemon, as a process
        res = run_cli(*argv, timeout=60) if argv[0] == "run" else cli_here(capfd, *argv)
        errors = _errors(res)
        assert res.returncode == 2 and len(errors) == 1 and f"{path}: {EXPECTED[name]}" in errors[0], (argv, res.stderr[-2000:])


@pytest.mark.parametrize("name", CONFIGS)
def test_hostile_config_is_one_line_naming_the_key_for_check_config(name: str, capfd: pytest.CaptureFixture[str]) -> None:
    res = cli_here(capfd, "check-config", str(CORPUS / name))  # by main() in this process: the same handler and lines
    errors = _errors(res)
    assert res.returncode == 2 and len(errors) == 1 and errors[0].startswith(f"tactiled: error: {CORPUS / name}: {EXPECTED[name]}"), res.stderr


@pytest.mark.parametrize("name", ["config-fs-inf.toml", "config-baudrate-2p63.toml", "config-nested-arrays.toml", "config-port-socket.toml"])
def test_run_refuses_the_same_configs(name: str, tmp_path: Path) -> None:
    res = run_cli("run", "--config", str(CORPUS / name), "--no-model", "--publish", f"ipc://{tmp_path}/pub", timeout=60)
    errors = _errors(res)
    assert res.returncode == 2 and len(errors) == 1 and f"{CORPUS / name}: {EXPECTED[name]}" in errors[0], res.stderr


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


def _zero_member(zf: zipfile.ZipFile, name: str, nbytes: int) -> None:
    """An int16 (n, 2) ``.npy`` member of ``nbytes`` zeros, streamed in (compressed as ``zf`` compresses), sizes declared truthfully."""
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<i2", "fortran_order": False, "shape": (nbytes // 4, 2)})
    with zf.open(name, "w", force_zip64=True) as out:
        out.write(header.getvalue())
        zeros = bytes(1 << 22)
        for _ in range(nbytes // len(zeros)):
            out.write(zeros)


def _deflate_bomb(path: Path, nbytes: int) -> None:
    """A recording whose ``samples`` member is ``nbytes`` of deflated zeros."""
    fs = io.BytesIO()
    np.save(fs, np.float64(20000))
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("fs.npy", fs.getvalue())
        _zero_member(zf, "samples.npy", nbytes)


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
    with zipfile.ZipFile(CORPUS / "rec-good.npz") as good, zipfile.ZipFile(tmp_path / "both.npz", "w", compression=zipfile.ZIP_DEFLATED) as out:
        for info in good.infolist():
            out.writestr(info, good.read(info))
        out.writestr("junk.npy", b"not an array")
        _zero_member(out, "bomb.npy", 64 << 20)
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


def test_an_unterminated_string_of_escaped_quotes_is_refused_without_a_quadratic_scan() -> None:
    """Bound: a 666 kB header of one unterminated string of escaped quotes (4 kB deflated in a model file) is refused as not
    JSON; the depth check's string pattern tried again from every quote, an hour of CPU holding the GIL (a daemon asked to
    load such a model lost 100 s of samples). In a process of its own, so a regression is killed, not waited for."""
    code = ("from tactiled.files.npzio import load_json_bounded\n"
            "try:\n    load_json_bounded('\"' + '\\\\\"' * 333_000, 'header')\n"
            "except ValueError as exc:\n    print(exc)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and res.stdout.startswith("header: not JSON: Unterminated string"), res


@pytest.mark.parametrize(("name", "why"), [("", "must not be empty or blank"), ("Ra0\n.44", "holds the control character U+000A"),
                                           ("a\x1b[2J", "holds the control character U+001B"), ("Ra0.44 ", "begins or ends with white space"),
                                           ("x" * 300, "300 characters, more than the 256")])
def test_a_model_class_that_is_no_surface_name_is_refused_at_load(name: str, why: str, tmp_path: Path) -> None:
    """A model's classes follow a recording's surface-name rule (an audit's newline class split replay's lines, an escape
    wrote to the terminal, "" was published as a label that reads as none): one line naming file and class."""
    from dataclasses import replace

    from tactiled.errors import ModelError
    from tactiled.learn.model import load_model

    shipped = load_model()
    path = tmp_path / "m.npz"
    replace(shipped, classes=[*shipped.classes[:1], name, *shipped.classes[2:]], fingerprint="").save(path)
    with pytest.raises(ModelError, match=f"^{tmp_path / 'm.npz'}: header.classes\\[1\\]: .*{re.escape(why)}"):
        load_model(path)


def test_a_path_with_a_nul_character_is_no_file() -> None:
    """Bound: os.stat raises ValueError on a NUL character (a path from a control request): one reason, no exception."""
    from tactiled.readable import file_problem

    assert file_problem("model\0.npz", 1 << 20) == "not a path (embedded null byte)"


def test_features_file_with_nested_header_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "f.npz"
    arrays = {"header": np.str_("[" * 50_000 + "]" * 50_000), "x": np.zeros((1, 1)), "names": np.array(["a"]), "label": np.array([""]),
              "file": np.zeros(1, int), "slide": np.zeros(1, int), "span": np.zeros((1, 2), int), "files": np.array(["r.npz"])}
    atomic_savez(path, arrays)
    with pytest.raises(RecordingError, match="header: JSON nested deeper than 32 levels") as err:
        load_features(path)
    assert str(path) in str(err.value)


@pytest.mark.parametrize("z", [[np.nan, 1.0], [np.inf, 1.0], [-np.inf, -np.inf], [1e308, -1e308], [np.nan, np.nan]])
@pytest.mark.parametrize("temperature", [1.0, 0.0, math.nan, math.inf, 1e-300])
def test_confidences_are_always_probabilities(z: list[float], temperature: float) -> None:
    p = softmax(np.array(z), temperature)
    assert np.all(np.isfinite(p)) and np.all((p >= 0) & (p <= 1)) and abs(p.sum() - 1) < 1e-9


def test_a_model_that_loads_labels_a_slide(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """The corpus' valid model gives finite confidences in [0, 1] on a real recording (replay --json is valid JSON)."""
    res = cli_here(capfd, "replay", "--json", "--model", GOOD_MODEL, str(REPO / "tests" / "hostile" / "rec-good.npz"))
    assert res.returncode == 0, res.stderr
    for line in res.stdout.splitlines():
        obj = json.loads(line)
        assert obj["confidence"] is None or 0.0 <= obj["confidence"] <= 1.0


@pytest.mark.parametrize(("argv", "message"), [
    (["replay", "--speed", "inf", GOOD_REC], "argument --speed: must be a finite number, got inf"),
    (["replay", "--speed", "nan", GOOD_REC], "argument --speed: must be a finite number, got nan"),
    (["replay", "--block", "-5", GOOD_REC], "argument --block: must be an integer >= 1, got -5"),
    (["replay", "--block", str(2**63), GOOD_REC], f"argument --block: must be an integer <= {2**31}, got {2**63}"),
    (["replay", "--wait-subscriber", "1e300", "--publish", "ipc:///x", GOOD_REC], "argument --wait-subscriber: must be in [0, 3600], got 1e300"),
    (["export", GOOD_REC, "-o", "x.mcap", "--batch", "0"], "argument --batch: must be an integer >= 1, got 0"),
    (["record", "--seconds", "1", "-o", "x.npz", "--channels", "9"], "argument --channels: must be an integer <= 8, got 9"),
    (["simulate", "dataset", "--out", "x", "--seed", str(2**32)], f"argument --seed: must be an integer <= {2**32 - 1}, got {2**32}"),
    (["simulate", "serial", "--corrupt", "nan"], "argument --corrupt: must be a finite number, got nan"),
])
def test_bad_flags_are_one_usage_line(argv: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert f"error: {message} (see " in usage_error(argv, capsys)


def _rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


# a ZMTP 3.0 peer by hand (what libzmq's SUB sends), so the test controls every byte: greeting with the NULL mechanism,
# READY naming a SUB socket, then one message whose 8-byte length says 16 MB (a subscription: 0x01 + the prefix)
GREETING = b"\xff" + bytes(8) + b"\x7f" + b"\x03\x00" + b"NULL".ljust(20, b"\x00") + b"\x00" + bytes(31)
READY_BODY = b"\x05READY" + b"\x0bSocket-Type" + struct.pack(">I", 3) + b"SUB"
READY = b"\x04" + bytes([len(READY_BODY)]) + READY_BODY


def _hostile_subscriber(endpoint: str, times: int = 3, prefix_bytes: int = 16 << 20) -> None:
    """Send a ``prefix_bytes`` SUBSCRIBE to an ipc publisher ``times`` times; each time the publisher must drop the connection
    (it never reads the prefix: a publisher that did would hold it, and keep the connection, past the 30 s timeout)."""
    assert endpoint.startswith("ipc://")
    chunk = b"s" * (1 << 20)
    for attempt in range(times):
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as peer:
            peer.settimeout(30)
            peer.connect(endpoint[len("ipc://"):])
            try:
                peer.sendall(GREETING + READY + b"\x02" + struct.pack(">Q", prefix_bytes + 1) + b"\x01")
                for _ in range(prefix_bytes // len(chunk)):
                    peer.sendall(chunk)
                while peer.recv(1 << 16):  # the publisher's greeting, then its close
                    pass
            except (BrokenPipeError, ConnectionResetError):
                pass  # dropped while we were still sending
            except TimeoutError:
                raise AssertionError(f"attempt {attempt}: the publisher kept a connection that sent a {prefix_bytes}-byte subscription") from None


def _subscriber(ctx: zmq.Context[zmq.Socket[bytes]], endpoint: str, topic: bytes) -> zmq.Socket[bytes]:
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, topic)
    sub.connect(endpoint)
    return sub


def test_huge_subscription_does_not_grow_the_daemon(tmp_path: Path) -> None:
    """The daemon's PUB drops a SUB sending a 16 MB SUBSCRIBE (MAXMSGSIZE), again on each reconnect; its memory stays put and a new subscriber is served."""
    endpoint = f"ipc://{tmp_path}/pub"
    daemon = subprocess.Popen(tactiled_cmd("run", "--port", str(tmp_path / "no-such-port"), "--no-model", "--publish", endpoint),
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO)
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
    try:
        first = _subscriber(ctx, endpoint, b"status")
        wait_for(lambda: first.poll(1000), 60, "a status message")
        before = _rss_kb(daemon.pid)
        _hostile_subscriber(endpoint)
        late = _subscriber(ctx, endpoint, b"status")  # connected after the hostile one: still served
        wait_for(lambda: late.poll(1000), 60, "status for a subscriber that came after the hostile one")
        assert schema.decode(late.recv_multipart())[0].startswith("status/")
        after = _rss_kb(daemon.pid)
        assert daemon.poll() is None and after - before < 8 * 1024, (before, after)  # kB: not one 16 MB prefix landed in the daemon
    finally:
        ctx.destroy(linger=0)
        daemon.terminate()
        daemon.wait(30)


def test_xpub_publisher_drops_a_huge_subscription_too(tmp_path: Path) -> None:
    """replay --publish uses an XPUB socket (it sees subscriptions): the hostile one never reaches it, the next one does and is served."""
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
    publisher = Publisher(PublishConfig(endpoint=f"ipc://{tmp_path}/xpub"), ctx, see_subscribers=True)
    try:
        _hostile_subscriber(publisher.endpoint)
        assert not publisher.socket.poll(0)  # no subscription message was delivered to the application
        sub = _subscriber(ctx, publisher.endpoint, b"status")
        assert publisher.wait_subscriber(60)
        assert publisher.socket.recv() == b"\x01status"  # the first subscription the XPUB saw is the well-formed one
        publisher.publish(schema.status("fingertip0"))

        def received() -> bool:
            return bool(sub.poll(1000))

        wait_for(received, 30, "the message published after the hostile subscriber")
        assert schema.decode(sub.recv_multipart())[0] == "status/fingertip0"
    finally:
        publisher.close()
        ctx.destroy(linger=0)


@pytest.mark.parametrize("kind", ["fifo", "device", "folder"])
@pytest.mark.parametrize("role", ["recording", "model"])
def test_a_non_regular_file_is_refused_in_one_line_without_reading_it(kind: str, role: str, tmp_path: Path) -> None:
    """A FIFO would hang a reader and /dev/zero never ends: neither is opened as a recording or a model."""
    if kind == "fifo":
        path = tmp_path / "x.npz"
        os.mkfifo(path)
    elif kind == "folder":
        path = tmp_path / "d.npz"
        path.mkdir()
    else:
        path = Path("/dev/zero")
    args = ("replay", str(path)) if role == "recording" else ("replay", "--model", str(path), str(REPO / "tests" / "hostile" / "rec-good.npz"))
    res = run_cli(*args, timeout=60)
    assert res.returncode == 2 and "not a regular file" in res.stderr and len(res.stderr.strip().splitlines()) == 1, res.stderr


@pytest.mark.parametrize("target", ["existing", "device"])
def test_run_record_never_replaces_a_file_unasked_nor_writes_a_device(target: str, tmp_path: Path) -> None:
    out = tmp_path / "old.npz"
    if target == "existing":
        out.write_bytes(b"a recording a lab cares about")
    path = str(out) if target == "existing" else "/dev/null"
    res = run_cli("run", "--port", str(tmp_path / "no-such-tty"), "--no-wait", "--publish", f"ipc://{tmp_path}/p", "--record", path, timeout=60)
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert ("exists (--force overwrites it)" if target == "existing" else "not a regular file") in res.stderr
    if target == "existing":
        assert out.read_bytes() == b"a recording a lab cares about"


def test_a_recording_given_as_a_model_is_named_as_such(capfd: pytest.CaptureFixture[str]) -> None:
    res = cli_here(capfd, "replay", "--model", str(CORPUS / "rec-good.npz"), str(CORPUS / "rec-good.npz"))  # by main() in this process
    assert res.returncode == 2 and "a recording (it holds samples), not a model file" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


def test_a_rate_too_low_for_the_features_is_one_line_naming_the_file(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    from tactiled.files.recording import Recording, save_recording

    save_recording(tmp_path / "slow.npz", Recording((np.random.default_rng(0).standard_normal((4000, 1)) * 100).astype(np.int16), 40.0, label="a"))
    res = cli_here(capfd, "replay", "--no-model", str(tmp_path / "slow.npz"), str(CORPUS / "rec-good.npz"))  # by main() in this process
    assert res.returncode == 2 and "Traceback" not in res.stderr
    errors = [line for line in res.stderr.splitlines() if "error" in line]
    assert len(errors) == 1 and "slow.npz" in errors[0] and "is too short for features.families" in errors[0] and "40 Hz" in errors[0]
    assert "rec-good.npz:" in res.stdout  # the other file is still replayed
    res = cli_here(capfd, "features", str(tmp_path / "slow.npz"), "-o", str(tmp_path / "f.npz"))
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and "slow.npz: " in lines[0] and "40 Hz" in lines[0], res.stderr


@pytest.mark.parametrize("section, key, target", [("publish", "curve_secret_key_file", "/dev/zero"), ("publish", "curve_secret_key_file", "fifo"),
                                                  ("model", "path", "/dev/zero"), ("model", "shadow", "fifo"), ("model", "path", "missing.npz")])
def test_config_files_that_are_not_regular_files_are_refused_by_check_config_and_run(section: str, key: str, target: str, tmp_path: Path) -> None:
    """A device or FIFO named as a key or model would be read without end, or block, when the daemon starts: one line, exit 2."""
    if target == "fifo":
        os.mkfifo(tmp_path / "fifo")
    path = target if target.startswith("/") else str(tmp_path / target)
    extra = f'curve_authorized_dir = "{tmp_path}"\n' if section == "publish" else ""
    config = tmp_path / "c.toml"
    config.write_text(f'[{section}]\n{key} = "{path}"\n{extra}')
    for argv in (["check-config", str(config)], ["run", "--config", str(config), "--port", str(tmp_path / "none")]):
        res = run_cli(*argv, timeout=60)
        assert res.returncode == 2 and res.stderr.strip().count("\n") == 0, res.stderr
        assert f"{section}.{key}: {path}" in res.stderr and any(w in res.stderr for w in ("not a regular file", "does not exist", "no such model file"))


def test_a_model_given_as_a_recording_is_named_as_such(capfd: pytest.CaptureFixture[str]) -> None:
    from tactiled.learn.model import default_model_path

    res = cli_here(capfd, "replay", str(default_model_path()))  # by main() in this process: the same handler and lines
    assert res.returncode == 2 and "a model or features file (it has a header and no samples), not a recording" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


def test_replay_with_a_model_of_another_rate_names_that_file_and_goes_on(labelled_good: str, tmp_path: Path,
                                                                        capfd: pytest.CaptureFixture[str]) -> None:
    """``replay --model M a.npz slow.npz b.npz``: the recording the model cannot analyse (another rate) is its one line, the
    files after it are replayed, exit 2 (it stopped the whole run there: an audit)."""
    rec = load_recording(labelled_good)
    slow = tmp_path / "slow.npz"
    save_recording(slow, Recording(rec.samples[::9].copy(), rec.fs / 9, rec.volts_per_count, label=rec.label))
    res = cli_here(capfd, "replay", "--model", GOOD_MODEL, labelled_good, str(slow), labelled_good)
    assert res.returncode == 2
    assert [line for line in _errors(res) if "slow.npz" in line] == [_errors(res)[0]] and len(_errors(res)) == 1
    assert res.stdout.count(f"{labelled_good}: 1 slides") == 2
