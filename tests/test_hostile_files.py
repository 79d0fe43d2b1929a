"""Hostile files (issue 22, items 4 and 6/7): recordings, captures and journals that claim more than they hold, or hold
numbers at the edge of float64, are bounded by their size and refused in one line, never a traceback.

Every test builds real files in ``tmp_path`` and states the bound it checks.
"""

from __future__ import annotations

import binascii
import errno
import os
import tracemalloc
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tactiled.board.frames import encode_frame
from tactiled.cli.main import main
from tactiled.config import Config
from tactiled.files import journal
from tactiled.files.capture import Capture
from tactiled.files.journal import CHUNK_MAGIC, encode_chunk, encode_header, read_journal
from tactiled.files.npzio import MAX_FILE_BYTES
from tactiled.files.recording import load_recording
from tactiled.run.replay import replay_capture, summary_line
from tests.conftest import REPO

MB = 1 << 20


def test_a_capture_whose_index_jumps_keeps_zero_rows_bounded_by_its_size_and_counts_every_gap(tmp_path: Path) -> None:
    """Bound: 100 one-sample frames (1.6 kB), each 399 000 samples after the last (each
    gap is lost samples), peak Python allocation < 50 MB (it was ~160 MB: 1.6 MB of zero rows per gap); every gap still
    counted: 99 x 398 999 samples lost, in the meta and the summary line."""
    path = tmp_path / "gaps.bin"
    path.write_bytes(b"".join(encode_frame(i * 399_000, np.array([[i, -i]], dtype=np.int16)) for i in range(100)))
    tracemalloc.start()
    try:
        _, rec = replay_capture(Capture(path), Config(), None)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 50 * MB, f"peak {peak / MB:.0f} MB for a {path.stat().st_size} byte capture"
    assert rec.meta["samples_lost"] == 99 * 398_999 and rec.meta["samples"] == 100
    assert rec.samples.shape[0] <= Capture(path).lost_rows_budget() + 100 and "truncated_at" in rec.meta
    assert summary_line([], rec).endswith(f", {99 * 398_999} samples lost")


def test_a_capture_of_another_channel_count_is_one_line_not_an_empty_replay(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Every frame of a one-channel board, replayed with a two-channel config: nothing could be decoded, so replay says why
    (exit 2) instead of "0 slides"; with the config's channels set, the same capture replays."""
    path = tmp_path / "one.bin"
    path.write_bytes(b"".join(encode_frame(k * 64, np.full((64, 1), 120, dtype=np.int16)) for k in range(100)))
    code, errors = _cli(capsys, "replay", str(path))
    assert code == 2 and len(errors) == 1 and "frames of 1 channel(s) skipped, sensor.channels is 2" in errors[0] and str(path) in errors[0]
    config = tmp_path / "one.toml"
    config.write_text("[sensor]\nchannels = 1\n")
    assert _cli(capsys, "replay", "--config", str(config), "--no-model", str(path)) == (0, [])


def _journal(path: Path, *chunks: bytes) -> Path:
    path.write_bytes(encode_header(20_000.0, 2, 1e-4, "a", {}) + b"".join(chunks))
    return path


def _good_chunk(position: int = 0, rows: int = 10) -> bytes:
    return encode_chunk(position, position, rows, [], {"samples": rows}, np.arange(2 * rows, dtype=np.int16).reshape(rows, 2))


def _cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, list[str]]:
    code = main(list(argv))
    return code, capsys.readouterr().err.strip().splitlines()


def test_a_journal_claiming_2_to_the_40_rows_is_refused_before_writing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Bound: lost rows written <= max(2^24, bytes of the journal); 2^40 rows of zeros from 205 bytes (it filled the
    disk) is one line, exit 2, and nothing written, not even a temporary file."""
    j = _journal(tmp_path / "huge.npz.journal", encode_chunk(0, 0, 1 << 40, [(0, 1 << 40)], {}, np.zeros((0, 2), np.int16)))
    code, err = _cli(capsys, "recover", str(j), "-o", str(tmp_path / "out.npz"))
    assert code == 2 and len(err) == 1 and "1099511627776 rows" in err[0] and str(j) in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["huge.npz.journal"]


def test_a_journal_within_its_lost_rows_budget_still_recovers(tmp_path: Path) -> None:
    """Bound: a gap of 2^24 rows (14 min at 20 kHz) between two chunks is still recovered, listed as lost."""
    j = _journal(tmp_path / "gap.npz.journal", _good_chunk(0), _good_chunk(10 + (1 << 24)))
    result = journal.recover(j, tmp_path / "gap.npz")
    assert result.samples_lost == 1 << 24 and result.samples == 20 + (1 << 24)
    assert load_recording(tmp_path / "gap.npz").lost.tolist() == [[10, 1 << 24]]


@pytest.mark.parametrize("padding", ["markers", "markers claiming the rest of the file"])
def test_resync_over_a_journal_padded_with_chunk_markers_is_linear(padding: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Bound: bytes CRC-checked <= 2 x the journal's size (each byte at most once, plus the header), for 512 kB of
    chunk markers (it took 68 s: every marker re-read the rest of the file); the good chunks before and after are kept."""
    n = 512 << 10
    if padding == "markers":
        pad = CHUNK_MAGIC * (n // 4)
    else:  # every 8 bytes a marker whose declared body ends exactly at the end of the file, and fails its CRC
        tail = _good_chunk(20)
        pad = b"".join(CHUNK_MAGIC + (n - 8 * i - 12 + len(tail)).to_bytes(4, "little") for i in range(n // 8))
    j = _journal(tmp_path / "pad.npz.journal", _good_chunk(0), pad, _good_chunk(20) if padding == "markers" else tail)
    crc = binascii.crc32
    checked = 0

    def counting(data: Any, value: int = 0) -> int:
        nonlocal checked
        checked += len(data)
        return crc(data, value)

    monkeypatch.setattr(binascii, "crc32", counting)
    scan = read_journal(j)
    assert checked <= 2 * j.stat().st_size, f"{checked} bytes CRC-checked for a {j.stat().st_size} byte journal"
    if padding == "markers":
        assert [c.position for c in scan.chunks] == [0, 20] and scan.dropped_bytes == len(pad)
    else:  # the first padding marker frames the rest of the file as one damaged chunk
        assert [c.position for c in scan.chunks] == [0] and scan.dropped_chunks == 1


def test_a_chunk_declaring_more_lost_ranges_than_it_holds_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Bound: a chunk (CRC intact) declaring 1 000 lost ranges in 2 bytes is dropped as damaged (it raised struct.error):
    one line, exit 2; with a good chunk before it, that one is recovered."""
    body = journal._body.pack(0, 0, 10, 1000, 2) + b"{}"
    head = CHUNK_MAGIC + journal._u32.pack(len(body)) + body
    bad = head + journal._u32.pack(binascii.crc32(head))
    code, err = _cli(capsys, "recover", str(_journal(tmp_path / "r.npz.journal", bad)), "-o", str(tmp_path / "r.npz"))
    assert code == 2 and len(err) == 1 and "no intact chunk" in err[0], err
    scan = read_journal(_journal(tmp_path / "r2.npz.journal", _good_chunk(0), bad.replace(journal._body.pack(0, 0, 10, 1000, 2),
                                                                                           journal._body.pack(10, 10, 10, 1000, 2))))
    assert [c.position for c in scan.chunks] == [0] and scan.dropped_chunks == 1


def test_recover_into_a_full_disk_is_one_line_exit_1_and_leaves_no_temporary(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """Bound: ENOSPC while writing the recording (injected: no tmpfs without privileges) is one line naming the output,
    exit 1 (a failure, not bad input); no .tmp is left and the journal is kept."""
    from tactiled.files import recording

    def full(*_: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(recording, "_write_streamed", full)
    j = _journal(tmp_path / "ok.npz.journal", _good_chunk(0))
    code, err = _cli(capsys, "recover", str(j), "-o", str(tmp_path / "ok.npz"))
    assert code == 1 and len(err) == 1 and "No space left on device" in err[0] and "ok.npz" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ok.npz.journal"]


def test_a_full_disk_while_writing_features_is_one_line_exit_1(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """Any command that meets ENOSPC (injected) says so in one line, exit 1, and leaves no temporary file (was a traceback)."""
    from tactiled.files.recording import save_recording
    from tests.conftest import lossy_recording

    save_recording(tmp_path / "r.npz", lossy_recording(0))

    def full(*_: object, **__: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np.lib.format, "write_array", full)
    code, err = _cli(capsys, "features", str(tmp_path / "r.npz"), "-o", str(tmp_path / "f.npz"), "--jobs", "1")
    err = [line for line in err if not line.startswith("features: ")]  # its progress lines before
    assert code == 1 and len(err) == 1 and "No space left on device" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.npz"]


def _not_a_file(kind: str, tmp_path: Path, suffix: str) -> str:
    if kind == "fifo":
        path = tmp_path / f"fifo{suffix}"
        os.mkfifo(path)
        return str(path)
    if kind == "oversize":  # sparse: the size the file system states, nothing written
        path = tmp_path / f"big{suffix}"
        with open(path, "wb") as fh:
            fh.truncate(MAX_FILE_BYTES + 1)
        return str(path)
    return "/dev/zero"


@pytest.mark.parametrize("kind", ["fifo", "device", "oversize"])
@pytest.mark.parametrize("command, suffix", [("replay", ".bin"), ("replay", ".npz"), ("recover", ".journal"), ("export", ".npz"),
                                             ("features", ".npz"), ("score", ".npz")])
def test_a_recording_that_is_not_a_regular_file_below_the_limit_is_refused_without_reading_it(
        command: str, suffix: str, kind: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Bound: 0 bytes read from a FIFO (it would block), /dev/zero (it never ends) or a file over the limit (sparse,
    16 GiB + 1): exit 2 and one line naming the path (score and features: the file is skipped in one line, then say
    nothing was left)."""
    path = _not_a_file(kind, tmp_path, suffix)
    argv = {"replay": ["replay", "--no-model", path], "recover": ["recover", path, "-o", str(tmp_path / "o.npz")],
            "export": ["export", "--no-model", path, "-o", str(tmp_path / "o.mcap")], "features": ["features", path, "-o", str(tmp_path / "f.npz")],
            "score": ["score", str(REPO / "tactiled" / "data" / "default_model.npz"), path]}[command]
    code, err = _cli(capsys, *argv)
    named = [line for line in err if path in line]
    assert code == 2 and len(named) == 1 and ("not a regular file" if kind != "oversize" else "more than the") in named[0], err
    assert len(err) == (2 if command in ("features", "score") else 1), err
    assert not (tmp_path / "o.npz").exists() and not (tmp_path / "o.mcap").exists()


GOOD = REPO / "tests" / "hostile" / "rec-good.npz"
MODEL = str(REPO / "tactiled" / "data" / "default_model.npz")


def _window(seed: int = 3, n: int = 4096) -> np.ndarray:
    return np.random.default_rng(seed).standard_normal((n, 2)) * 0.01


def test_features_of_a_huge_window_are_the_scaled_features_bit_for_bit_or_a_window_error() -> None:
    """Bound: features of x·2^300 are the features of x times 2^(300·degree), bit for bit but for the ones through
    logarithms (flatness, slope: within 1e-12), as the window is scaled by a power of two before squaring; at 1e307 V,
    where energies pass float64, a WindowError 'non_finite', never OverflowError or inf."""
    from tactiled.core.analysis import AnalysisSettings
    from tactiled.core.features import FeaturePlan, feature_degree
    from tactiled.errors import WindowError

    names = AnalysisSettings.from_config(Config(), 2, 20_000.0).names
    plan = FeaturePlan(names, fs=20_000.0)
    x = _window()
    degrees = np.array([feature_degree(n) for n in names])
    big, small = plan.compute(np.ldexp(x, 300)), np.ldexp(plan.compute(x), 300 * degrees)
    logs = np.array([n.endswith((".flatness", ".slope")) for n in names])
    assert np.array_equal(big[~logs], small[~logs]) and np.allclose(big[logs], small[logs], rtol=1e-12, atol=0)
    with pytest.raises(WindowError) as err:
        plan.compute(x / np.abs(x).max() * 1e307)
    assert err.value.reason == "non_finite"


def test_the_median_of_two_samples_near_the_float64_limit_stays_finite() -> None:
    """Bound: median_last of (1.7e308, 1.7e308) is 1.7e308, not inf (halves summed, not the sum halved)."""
    from tactiled.core.spikes import median_last

    assert median_last(np.array([[1.7e308, 1.7e308]]))[0] == 1.7e308


def _huge(tmp_path: Path) -> Path:
    from tactiled.files.recording import Recording, save_recording

    path = tmp_path / "huge.npz"
    save_recording(path, Recording(samples=_window() / 0.04 * 1e307, fs=20_000.0, label="Ra0.44"))
    return path


def test_samples_near_1e307_are_one_line_and_a_multi_file_replay_goes_on(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Bound: |samples| <= 1e9 V at load; a file of samples near 1e307 V is one line naming it and its key, exit 2, and
    replay then plays the next file."""
    huge = _huge(tmp_path)
    code = main(["replay", "--no-model", str(huge), str(GOOD)])
    out, err = capsys.readouterr()
    assert code == 2 and err.strip().splitlines() == [err.strip()] and f"{huge}: samples: reach" in err and "Traceback" not in err, err
    assert f"{GOOD}: " in out


@pytest.mark.parametrize("command", ["features", "score", "export"])
def test_samples_near_1e307_are_one_line_for_features_score_and_export(command: str, tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """Bound: exit 2, a line naming the file and 'samples' (features and score skip it, then say nothing was left)."""
    huge = str(_huge(tmp_path))
    argv = {"features": ["features", huge, "-o", str(tmp_path / "f.npz")], "score": ["score", "--jobs", "1", MODEL, huge],
            "export": ["export", "--no-model", huge, "-o", str(tmp_path / "x.mcap")]}[command]
    code, err = _cli(capsys, *argv)
    assert code == 2 and sum(f"{huge}: samples: reach" in line for line in err) == 1 and len(err) <= 2, err


@pytest.mark.parametrize("json_out", [False, True])
def test_score_of_recordings_with_no_detected_slide_is_one_line_not_a_score(json_out: bool, tmp_path: Path,
                                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """Bound: labelled files of silence (no slide to detect) are one line naming them, exit 2; no "accuracy 0.0000 (0 of 0)"
    with exit 0, as an audit found (before that it raised IndexError)."""
    from tactiled.files.recording import Recording, save_recording

    flats = [tmp_path / f"flat{k}.npz" for k in range(2)]
    for flat in flats:
        save_recording(flat, Recording(samples=np.zeros((40_000, 2), np.int16), fs=20_000.0, label="Ra0.44"))
    code = main(["score", "--jobs", "1", *(["--json"] if json_out else []), MODEL, *map(str, flats)])
    out, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if "error" in line]  # beside the progress line
    assert code == 2 and out == "" and len(lines) == 1, (out, err)
    assert "no true slide to score" in lines[0] and all(str(f) in lines[0] for f in flats), lines


@pytest.mark.parametrize("key", ["label", "surface"])
def test_a_4m_character_label_is_refused_at_load_within_a_bounded_allocation(key: str, tmp_path: Path) -> None:
    """Bound: surface names <= 256 characters; a 4M-character one (16 MB as UTF-32; score used 1 GB) is one
    RecordingError naming the key, with a peak allocation < 50 MB while loading."""
    from tactiled.errors import RecordingError
    from tactiled.files.recording import Recording, load_recording, save_recording

    name = "x" * 4_000_000
    rec = Recording(samples=np.zeros((1000, 2), np.int16), fs=20_000.0, label=name if key == "label" else None)
    if key == "surface":
        rec.slide_start, rec.slide_stop, rec.surface = np.array([10]), np.array([900]), np.array([name])
    save_recording(tmp_path / "l.npz", rec)
    tracemalloc.start()
    try:
        with pytest.raises(RecordingError, match=f"{key}: .*4000000 characters, more than the 256"):
            load_recording(tmp_path / "l.npz")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 50 * MB, f"peak {peak / MB:.0f} MB"


@pytest.mark.parametrize("layout", ["disjoint", "overlapping"])
def test_export_with_1000_lost_ranges_is_one_sweep_and_lists_every_lost_row_once(layout: str, tmp_path: Path,
                                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """Bound: over 1 000 lost ranges (disjoint, or every one running to the end of the file), the ranges the samples
    messages list add up to at most messages + merged ranges (linear: overlapping ranges made every message scan, and
    list, all of them: 37 s for 12 s of samples), and the MCAP gives back exactly the recording's valid rows and samples."""
    from tactiled.files.recording import Recording, merge_ranges, save_recording
    from tactiled.service.mcap_export import BATCH, batches, read_mcap_samples

    n = 40_000
    rng = np.random.default_rng(5)
    samples = rng.integers(-2000, 2000, size=(n, 2)).astype(np.int16)
    if layout == "disjoint":
        starts = np.arange(1000) * 40 + 3
        lost = np.column_stack([starts, np.full(1000, 7)])
    else:
        starts = rng.integers(0, n, size=1000)
        lost = np.column_stack([starts, n - starts])
    rec = Recording(samples=samples, fs=20_000.0, volts_per_count=1e-3, label="a", lost=lost)
    samples[~rec.valid_mask()] = 0
    save_recording(tmp_path / "l.npz", rec)
    listed = sum(len(inside) for _, _, inside in batches(n, lost, BATCH))
    assert listed <= -(-n // BATCH) + len(merge_ranges(lost))
    code = main(["export", "--no-model", str(tmp_path / "l.npz"), "-o", str(tmp_path / "l.mcap")])
    assert code == 0, capsys.readouterr().err
    volts, valid, _, _ = read_mcap_samples(tmp_path / "l.mcap")
    assert np.array_equal(valid, rec.valid_mask()) and np.allclose(volts, samples * 1e-3, rtol=0, atol=1e-12)
    assert (~valid).sum() == merge_ranges(lost)[:, 1].sum()


def test_a_journal_whose_label_is_longer_than_a_surface_name_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Bound: the same 256 characters as a recording's label (what recovers must load): one line, exit 2, nothing written."""
    j = tmp_path / "l.npz.journal"
    j.write_bytes(encode_header(20_000.0, 2, 1e-4, "x" * 300_000, {}) + _good_chunk(0))
    code, err = _cli(capsys, "recover", str(j), "-o", str(tmp_path / "l.npz"))
    assert code == 2 and len(err) == 1 and "label: 300000 characters" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["l.npz.journal"]


def test_the_peak_bound_counts_an_int16_minus_32768_at_its_magnitude(tmp_path: Path) -> None:
    """The load bound's peak is max |x| from the least and greatest sample (no |x| array): equal to np.abs's for floats, and an
    int16 -32768 counts as 32768 volts-per-count (np.abs wraps it to -32768), so counts just over the bound are refused."""
    from tactiled.errors import RecordingError
    from tactiled.files.recording import MAX_VOLTS, Recording, largest_magnitude, save_recording

    rng = np.random.default_rng(3)
    for x in (rng.standard_normal((999, 2)), rng.standard_normal((5, 1)).astype(np.float32) - 7, np.array([[-0.0], [0.0]])):
        assert largest_magnitude(x) == float(np.max(np.abs(x)))
    counts = np.array([[-32768, 5], [100, 32767]], dtype=np.int16)
    assert largest_magnitude(counts) == 32768.0
    path = tmp_path / "edge.npz"
    save_recording(path, Recording(samples=counts, fs=20_000.0, volts_per_count=MAX_VOLTS / 32767.5))
    with pytest.raises(RecordingError, match="samples: reach"):
        load_recording(path)
