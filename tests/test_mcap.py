"""MCAP export: every sample, the ground-truth slides and the labels read back with the mcap reader."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from tactiled.files.formats import open_recording
from tactiled.files.recording import Recording, load_recording, save_recording
from tactiled.service.mcap_export import read_mcap_samples
from tactiled.sim.physics import SensorSimulator, SimParams, default_surfaces
from tactiled.sim.virtualboard import VirtualBoard
from tests.conftest import cli_here, lossy_recording, run_cli, running, tactiled_cmd


def test_export_round_trips_every_sample_slide_and_label(tmp_path: Path) -> None:
    rec = lossy_recording(123_456)
    params = SimParams()
    save_recording(tmp_path / "r.npz", rec)
    res = run_cli("export", str(tmp_path / "r.npz"), "-o", str(tmp_path / "r.mcap"), "--batch", "64")
    assert res.returncode == 0, res.stderr
    volts, valid, first, fs = read_mcap_samples(tmp_path / "r.mcap")
    assert (first, fs) == (123_456, params.fs)
    assert np.array_equal(valid, rec.valid_mask())
    assert np.array_equal(np.rint(volts / params.volts_per_count).astype(np.int16), rec.samples)  # every sample, exactly
    by_topic: dict[str, list[tuple[int, dict]]] = {}
    with open(tmp_path / "r.mcap", "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None and {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
        assert {c.message_encoding for c in summary.channels.values()} == {"json"}
        for _schema, channel, message in reader.iter_messages():
            by_topic.setdefault(channel.topic, []).append((message.log_time, json.loads(message.data)))
        meta = {m.name: m.metadata for m in reader.iter_metadata()}["tactiled.recording"]
    assert set(by_topic) == {"/tactiled/fingertip0/samples", "/tactiled/fingertip0/slides", "/tactiled/fingertip0/roughness"}
    # one frame of reference: absolute sensor indices everywhere; log time is host time from the file's modification time
    assert (meta["log_time_origin"], meta["first_index"], meta["fs"]) == ("file_mtime", "123456", repr(params.fs))
    origin = (tmp_path / "r.npz").stat().st_mtime - len(rec.samples) / params.fs
    assert by_topic["/tactiled/fingertip0/samples"][0] == (round(origin * 1e9), by_topic["/tactiled/fingertip0/samples"][0][1])
    assert by_topic["/tactiled/fingertip0/samples"][0][1]["index"] == 123_456
    slides = by_topic["/tactiled/fingertip0/slides"]
    assert [(b["start"] - 123_456, b["stop"] - 123_456, b["surface"]) for _, b in slides] == rec.slides()
    assert slides[0][0] == round(origin * 1e9) + round(rec.slides()[0][0] * 1e9 / params.fs)
    labels = [b for _, b in by_topic["/tactiled/fingertip0/roughness"]]
    # each label logged when it could first have been published, at the end of what it read (not at its slide's onset)
    assert all(t == round(origin * 1e9) + round((b["stop"] - 123_456) * 1e9 / params.fs) for t, b in by_topic["/tactiled/fingertip0/roughness"])
    finals = [b for b in labels if b["final"]]  # and the provisional labels given while each slide went on
    assert len(finals) == 3 and sum(b["label"] == "Ra2.29" for b in finals) >= 2
    truth = [(a + 123_456, b + 123_456) for a, b, _ in rec.slides()]
    assert all(any(a <= f["start"] < b for a, b in truth) for f in finals)  # the same index base as the samples and the slides
    assert all(f["t_start"] == f["start"] / params.fs and f["model"] for f in finals)
    assert all(b["used_s"] < (b["stop"] - b["start"]) / params.fs + 1e-9 for b in labels if not b["final"])
    assert f"{res.stdout}".strip().endswith(f"3 slides, {len(labels)} roughness messages")


def test_record_format_mcap(tmp_path: Path) -> None:
    link = str(tmp_path / "tty")
    board = VirtualBoard(SensorSimulator(SimParams(), seed=2), default_surfaces()[:2], link=link, speed=2.0, seed=2)
    board.open()
    proc = subprocess.Popen(tactiled_cmd("record", "--port", link, "--seconds", "8", "--format", "mcap", "--label", "Ra0.44",
                                         "-o", str(tmp_path / "r.mcap")), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with running(board):
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    volts, valid, first, _ = read_mcap_samples(tmp_path / "r.mcap")
    assert volts.shape == (160_000, 2) and valid.all() and np.abs(volts).max() > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.mcap", "r.npz", "tty"] and "the recording stays in" in out  # both kept
    rec = load_recording(tmp_path / "r.npz")
    assert rec.label == "Ra0.44" and np.array_equal(np.rint(volts / rec.volts_per_count).astype(np.int16), rec.samples)
    with open(tmp_path / "r.mcap", "rb") as fh:
        reader = make_reader(fh)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}["tactiled.recording"]
        labels = [(m.log_time, json.loads(m.data)) for _, c, m in reader.iter_messages(topics=["/tactiled/fingertip0/roughness"])]
    assert meta["label"] == "Ra0.44" and meta["log_time_origin"] == "recorded_at" and json.loads(meta["meta"])["port"] == link
    assert labels and all(b["reason"] != "no_model" and b["model"] for _, b in labels)  # labelled by the shipped model
    assert all(b["start"] >= first for _, b in labels)
    assert abs(labels[0][0] / 1e9 - time.time()) < 120  # host time, not sensor time from 1970


def test_export_marks_a_thousand_lost_ranges_exactly(tmp_path: Path) -> None:
    """Lost ranges are swept once with the batches (linear), and each batch carries exactly the ones inside it."""
    rng = np.random.default_rng(3)
    n = 200_000
    starts = np.sort(rng.choice(np.arange(0, n - 50, 150), 1000, replace=False))
    lost = np.column_stack([starts, rng.integers(1, 120, 1000)])
    rec = Recording(rng.integers(-1000, 1000, (n, 2)).astype(np.int16), 20000.0, 5.0 / 32768.0, lost=lost)
    save_recording(tmp_path / "r.npz", rec)
    res = run_cli("export", str(tmp_path / "r.npz"), "-o", str(tmp_path / "r.mcap"), "--no-model", "--batch", "37")
    assert res.returncode == 0, res.stderr
    _, valid, _, _ = read_mcap_samples(tmp_path / "r.mcap")
    assert np.array_equal(valid, rec.valid_mask())


def test_export_never_replaces_its_input_nor_a_file_unasked(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    import shutil

    from tests.conftest import REPO

    src = tmp_path / "a.npz"
    shutil.copy(REPO / "tests" / "hostile" / "rec-good.npz", src)
    before = src.read_bytes()
    res = cli_here(capfd, "export", str(src), "-o", str(src))
    assert res.returncode == 2 and "is the recording being exported" in res.stderr and src.read_bytes() == before
    res = cli_here(capfd, "export", str(src), "-o", str(tmp_path / "no" / "x.mcap"))
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1 and "does not exist" in res.stderr
    (tmp_path / "x.mcap").write_bytes(b"keep")
    res = cli_here(capfd, "export", str(src), "-o", str(tmp_path / "x.mcap"))
    assert res.returncode == 2 and "--force" in res.stderr and (tmp_path / "x.mcap").read_bytes() == b"keep"
    assert cli_here(capfd, "export", str(src), "-o", str(tmp_path / "x.mcap"), "--force").returncode == 0


def test_replay_of_an_mcap_file_that_is_not_tactileds_is_one_line(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "junk.mcap").write_bytes(b"\x89MCAP0\r\n" + b"not records")
    res = cli_here(capfd, "replay", str(tmp_path / "junk.mcap"))
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1 and "junk.mcap: not a readable MCAP file" in res.stderr, res.stderr


def test_replay_of_the_exported_mcap_gives_the_npz_replays_labels(tmp_path: Path) -> None:
    """tactiled replay rec.mcap: the recording read back (counts, lost rows, truth, label, meta), labelled as the .npz is."""
    from dataclasses import replace as dc_replace

    from tactiled.config import Config
    from tactiled.files.formats import open_recording
    from tactiled.learn.model import load_model
    from tactiled.run.replay import replay_recording

    rec = dc_replace(lossy_recording(123_456), label="Ra1.00", meta={"note": "kept"})
    save_recording(tmp_path / "r.npz", rec)
    assert run_cli("export", str(tmp_path / "r.npz"), "-o", str(tmp_path / "r.mcap"), "--batch", "500").returncode == 0
    back, npz = open_recording(tmp_path / "r.mcap"), load_recording(tmp_path / "r.npz")
    assert isinstance(back, Recording)
    assert back.samples.dtype == npz.samples.dtype and np.array_equal(back.samples[npz.valid_mask()], npz.samples[npz.valid_mask()])
    assert np.array_equal(back.valid_mask(), npz.valid_mask()) and back.slides() == npz.slides() and back.first_index == npz.first_index
    assert (back.fs, back.volts_per_count, back.label, back.meta["note"]) == (npz.fs, npz.volts_per_count, "Ra1.00", "kept")
    model = load_model()
    ours, theirs = replay_recording(npz, Config(), model), replay_recording(back, Config(), model)
    fields = ("slide_id", "start", "stop", "window", "label", "reason", "confidence", "top", "final", "novelty")
    assert ours and [[getattr(r, f) for f in fields] for r in ours] == [[getattr(r, f) for f in fields] for r in theirs]
    ros = run_cli("export", str(tmp_path / "r.npz"), "-o", str(tmp_path / "ros.mcap"), "--profile", "ros2")
    assert ros.returncode == 0, ros.stderr
    refused = run_cli("replay", str(tmp_path / "ros.mcap"))
    assert refused.returncode == 2 and "a ROS 2 bag" in refused.stderr and len(refused.stderr.strip().splitlines()) == 1, refused.stderr


def test_a_recording_of_no_samples_round_trips(tmp_path: Path) -> None:
    """An export of 0 samples has no samples message; replay read it as "no samples channel", exit 2."""
    src, out = tmp_path / "zero.npz", tmp_path / "zero.mcap"
    save_recording(src, Recording(np.zeros((0, 3), np.int16), 20_000.0, 5 / 32768))
    assert run_cli("export", "--no-model", str(src), "-o", str(out)).returncode == 0
    back = open_recording(out)
    assert isinstance(back, Recording) and back.samples.shape == (0, 3) and back.fs == 20_000.0
    res = run_cli("replay", str(out))
    assert res.returncode == 0, res.stderr


def test_an_int16_recording_at_full_scale_round_trips(tmp_path: Path) -> None:
    """-32768 is a count int16 holds (a clipped ADC); the reader checked |counts| < 32767.5 and refused the export of any
    recording that had one (an outside audit): every sample back, bit for bit; one beyond the range is still refused."""
    from mcap.writer import Writer

    samples = np.random.default_rng(0).integers(-3000, 3000, (4000, 2), dtype=np.int16)
    samples[100, 1], samples[200, 0] = -32768, 32767
    src, out = tmp_path / "clip.npz", tmp_path / "clip.mcap"
    save_recording(src, Recording(samples, 20_000.0, 5 / 32768))
    assert run_cli("export", "--no-model", str(src), "-o", str(out)).returncode == 0
    back = open_recording(out)
    assert isinstance(back, Recording) and np.array_equal(back.samples, samples)
    res = run_cli("replay", str(out))
    assert res.returncode == 0, res.stderr
    beyond = tmp_path / "beyond.mcap"
    with open(beyond, "wb") as fh:  # a count of -32769
        w = Writer(fh)
        w.start(profile="", library="x")
        cid = w.register_channel("/tactiled/fingertip0/samples", "json", w.register_schema("tactiled.Samples", "jsonschema", b"{}"))
        w.add_metadata("tactiled.recording", {"fs": "20000.0", "channels": "1", "volts_per_count": "1.0", "first_index": "0",
                                              "samples_dtype": "int16", "meta": "{}"})
        w.add_message(cid, log_time=0, publish_time=0, data=b'{"index":0,"n":2,"lost":[],"film1":[0,-32769]}')
        w.finish()
    res = run_cli("replay", str(beyond))
    assert res.returncode == 2 and "samples: -32769 counts at volts_per_count 1.0, beyond the int16 of samples_dtype" in res.stderr, res.stderr


def _bomb(path: Path, n: int, frame_size: bool = True) -> Path:
    """A tactiled-looking MCAP file of one samples message of ``n`` zeros per film in one zstd chunk (a few kB on disk, 4n
    bytes of JSON inflated); ``frame_size`` False: the chunk declares 1 kB, only its zstd frame the true size."""
    from mcap.writer import CompressionType, Writer

    with open(path, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD, chunk_size=1 << 40)
        w.start(profile="", library="x")
        cid = w.register_channel("/tactiled/fingertip0/samples", "json", w.register_schema("tactiled.Samples", "jsonschema", b"{}"))
        w.add_metadata("tactiled.recording", {"fs": "20000.0", "channels": "2", "volts_per_count": "0.000152587890625",
                                              "first_index": "0", "samples_dtype": "int16", "meta": "{}"})
        zeros = ",".join(["0"] * n).encode()
        w.add_message(cid, log_time=0, publish_time=0, data=b'{"index":0,"n":%d,"lost":[],"film1":[' % n + zeros + b'],"film2":[' + zeros + b']}')
        w.finish()
    if not frame_size:  # the chunk record (opcode 6: start and end times, then its uncompressed size) says 1 kB
        data = bytearray(path.read_bytes())
        at = 8  # past the magic
        while data[at] != 6:
            at += 9 + int.from_bytes(data[at + 1: at + 9], "little")
        data[at + 25: at + 33] = (1024).to_bytes(8, "little")
        path.write_bytes(bytes(data))
    return path


def test_an_mcap_decompression_bomb_is_refused_before_it_is_inflated(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Bound: a few kB of zstd declaring 20 MB of JSON zeros (which json and numpy make several hundred MB) is one line
    naming the file, exit 2, as an .npz member over 200:1 is; an audit's 8 kB file took 13 s and 1.3 GB before."""
    from tactiled.cli.main import main

    for frame_size in (True, False):
        bomb = _bomb(tmp_path / f"bomb{frame_size}.mcap", 5_000_000, frame_size)
        assert bomb.stat().st_size < 20_000
        code = main(["replay", "--no-model", str(bomb)])
        out, err = capsys.readouterr()
        assert code == 2 and out == "", (out, err)
        line = err.strip()
        assert len(line.splitlines()) == 1 and str(bomb) in line and "a decompression bomb" in line, line
    small = _bomb(tmp_path / "small.mcap", 1000)  # the same shape, small: no bomb, a recording
    assert open_recording(small).samples.shape == (1000, 2)
