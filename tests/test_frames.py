"""The sans-IO frame decoder against the spec, byte at a time, in chunks, with faults."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from tactiled.board.frames import FrameDecoder, crc16, encode_frame, encode_frames, frame_size


def test_crc_check_value() -> None:
    assert crc16(b"123456789") == 0x29B1


def test_spec_example_bytes() -> None:
    frame = encode_frame(7, np.array([[1, -1], [256, -256]], dtype=np.int16))
    assert frame.hex(" ") == "a5 5a 01 02 02 00 07 00 00 00 01 00 ff ff 00 01 00 ff 7d 11"
    (decoded,) = FrameDecoder().feed(frame)
    assert decoded.index == 7
    assert decoded.samples.tolist() == [[1, -1], [256, -256]]
    one_at_a_time = FrameDecoder()  # docs/sensor-frames.md: the same bytes, one at a time
    got = [f for b in bytes.fromhex("a55a010202000700000001 00ffff000100ff7d11".replace(" ", "")) for f in one_at_a_time.feed(bytes([b]))]
    assert len(got) == 1 and got[0].samples.tolist() == [[1, -1], [256, -256]]


def test_no_file_refers_outside_the_repository() -> None:
    """The project's docs stand alone: no tracked file points into a shared/ folder beside the repository."""
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    files = subprocess.run(["git", "ls-files"], cwd=root, capture_output=True, text=True, check=True).stdout.split()
    bad = [f for f in files if f.endswith((".py", ".md", ".toml", ".service", ".cfg", ".txt"))
           and ("shared/" + "specs" in (root / f).read_text(errors="replace") or "shared/" + "notes" in (root / f).read_text(errors="replace")
                or "shared/" + "DESIGN" in (root / f).read_text(errors="replace"))]
    assert not bad


def _stream(n_frames: int, channels: int = 2, count: int = 20, first: int = 0, seed: int = 0) -> tuple[list[bytes], np.ndarray]:
    rng = np.random.default_rng(seed)
    samples = rng.integers(-32768, 32768, (n_frames * count, channels)).astype(np.int16)
    frames = [encode_frame(first + i * count, samples[i * count:(i + 1) * count]) for i in range(n_frames)]
    return frames, samples


def _decode(data: bytes, cuts: list[int]) -> tuple[list[tuple[int, bytes]], FrameDecoder]:
    dec = FrameDecoder()
    out = []
    prev = 0
    for cut in [*sorted(cuts), len(data)]:
        out += [(f.index, f.samples.tobytes()) for f in dec.feed(data[prev:cut])]
        prev = cut
    out += [(f.index, f.samples.tobytes()) for f in dec.flush()]
    return out, dec


def test_byte_at_a_time_equals_whole() -> None:
    frames, _ = _stream(30)
    data = b"".join(frames)
    whole, _ = _decode(data, [])
    bytewise, _ = _decode(data, list(range(1, len(data))))
    assert whole == bytewise
    assert len(whole) == 30


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_chunking_never_changes_frames(data: st.DataObject) -> None:
    frames, _ = _stream(12, seed=data.draw(st.integers(0, 1000)))
    stream = b"".join(frames)
    cuts = data.draw(st.lists(st.integers(0, len(stream)), max_size=40))
    assert _decode(stream, cuts)[0] == _decode(stream, [])[0]


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_corrupted_frames_lose_exactly_those(data: st.DataObject) -> None:
    n = 20
    frames, samples = _stream(n, seed=data.draw(st.integers(0, 1000)))
    bad = set(data.draw(st.lists(st.integers(1, n - 2), max_size=5, unique=True)))
    corrupted = []
    for i, frame in enumerate(frames):
        if i in bad:
            b = bytearray(frame)
            at = data.draw(st.integers(2, len(b) - 1))
            b[at] ^= data.draw(st.integers(1, 255))
            frame = bytes(b)
        corrupted.append(frame)
    stream = b"".join(corrupted)
    cuts = data.draw(st.lists(st.integers(0, len(stream)), max_size=10))
    out, dec = _decode(stream, cuts)
    assert [i for i, _ in out] == [i * 20 for i in range(n) if i not in bad]
    for index, raw in out:
        assert raw == samples[index:index + 20].tobytes()
    assert dec.stats.samples_lost == 20 * len(bad - {n - 1})
    assert dec.stats.crc_errors + dec.stats.bad_headers + dec.stats.truncated >= len(bad)


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_garbage_between_frames_loses_nothing(data: st.DataObject) -> None:
    frames, _ = _stream(15, seed=data.draw(st.integers(0, 1000)))
    parts = []
    junk_total = 0
    for frame in frames:
        junk = data.draw(st.binary(max_size=30))
        junk_total += len(junk)
        parts += [junk, frame]
    stream = b"".join(parts)
    out, dec = _decode(stream, data.draw(st.lists(st.integers(0, len(stream)), max_size=10)))
    assert [i for i, _ in out] == [i * 20 for i in range(15)]
    assert dec.stats.samples_lost == 0
    assert dec.stats.bytes_discarded == junk_total


def test_sync_word_inside_payload_is_not_trusted() -> None:
    samples = np.array([[0x5AA5, 0x5AA5]] * 20, dtype=np.uint16).view(np.int16)
    frames = [encode_frame(i * 20, samples) for i in range(5)]
    stream = b"".join(frames)
    out, _dec = _decode(stream[3:], [])  # start mid-frame: the payload's a5 5a must not produce frames
    assert [i for i, _ in out] == [20, 40, 60, 80]


def test_index_wrap_is_seamless() -> None:
    first = 2**32 - 50
    frames, _samples = _stream(6, first=first)
    out, dec = _decode(b"".join(frames), [])
    assert [i for i, _ in out] == [first + 20 * k for k in range(6)]
    assert dec.stats.samples_lost == 0 and dec.stats.restarts == 0


def test_gap_counts_lost_samples_across_wrap() -> None:
    first = 2**32 - 30
    frames, _ = _stream(6, first=first)
    out, dec = _decode(b"".join(frames[:1] + frames[3:]), [])
    assert [i for i, _ in out] == [first, first + 60, first + 80, first + 100]
    assert dec.stats.samples_lost == 40


def test_restart_is_reported_and_duplicates_dropped() -> None:
    frames, _ = _stream(200)  # 4000 samples
    after, _ = _stream(3, first=0, seed=9)
    dec = FrameDecoder(duplicate_window=1000)
    out = dec.feed(b"".join(frames) + frames[-1])  # a duplicated frame
    assert dec.stats.duplicates == 1 and len(out) == 200
    restarted = dec.feed(b"".join(after))
    assert dec.stats.restarts == 1
    assert restarted[0].restart and restarted[0].index == 4000
    assert [f.index for f in restarted] == [4000, 4020, 4040]


def test_flush_releases_frames_behind_a_corrupted_count() -> None:
    frames, _ = _stream(3)
    bad = bytearray(frames[1])
    bad[4] ^= 32  # count 20 -> 52: the decoder waits for 220 bytes
    dec = FrameDecoder()
    assert [f.index for f in dec.feed(frames[0] + bytes(bad) + frames[2])] == [0]
    assert [f.index for f in dec.flush()] == [40]
    assert dec.pending == 0


def test_bad_headers_and_sizes() -> None:
    assert frame_size(2, 20) == 92  # the spec's layout table (its prose says 94)
    for body in (b"\xa5\x5a\x02\x02\x01\x00", b"\xa5\x5a\x01\x09\x01\x00", b"\xa5\x5a\x01\x02\x00\x00"):
        dec = FrameDecoder()
        assert dec.feed(body + bytes(20)) == []
        assert dec.stats.bad_headers >= 1


def test_encode_frames_splits_like_firmware() -> None:
    samples = np.arange(100, dtype=np.int16).reshape(50, 2)
    data = encode_frames(5, samples, count=20)
    out = FrameDecoder().feed(data)
    assert [f.index for f in out] == [5, 25, 45]
    assert np.array_equal(np.concatenate([f.samples for f in out]), samples)


def test_a_run_overlapping_what_was_placed_drops_whole_frames_like_per_frame_decoding() -> None:
    """Bulk runs give the frames one-by-one decoding gives: a repeated frame (same index, same bytes) is a duplicate, whole,
    and the new frames after it in the same run are kept."""
    frames, _ = _stream(4)  # frames at 0, 20, 40, 60
    data = b"".join(frames[:2] + frames[1:2] + frames[2:])  # the frame at 20 twice, then 40 and 60 in the same run
    runs = FrameDecoder()
    got = runs.feed_runs(data)
    assert [(f.index, f.samples.shape[0], f.lost) for f in got] == [(0, 40, 0), (40, 40, 0)]
    per_frame = FrameDecoder()
    assert [(f.index, f.lost) for f in per_frame.feed(data)] == [(0, 0), (20, 0), (40, 0), (60, 0)]
    assert runs.stats.duplicates == per_frame.stats.duplicates == 1
    assert runs.stats.samples_lost == per_frame.stats.samples_lost == 0
    assert runs.stats.restarts == per_frame.stats.restarts == 0


def test_a_repeat_of_a_frame_inside_a_long_run_is_a_duplicate_within_the_window_only() -> None:
    """The decoder remembers whole runs: a frame repeated from the middle of a run it decoded at once is a duplicate while it
    lies within ``duplicate_window`` samples of the next index, and a restart beyond, across the 32-bit wrap too."""
    for first in (0, (1 << 32) - 2000):
        frames, _ = _stream(200, first=first)  # 4000 samples in one run (the wrap inside it for the second)
        for back, duplicate in ((900, True), (1000, True), (1100, False)):
            dec = FrameDecoder(duplicate_window=1000)
            dec.feed_runs(b"".join(frames))
            again = frames[(4000 - back) // 20]
            got = dec.feed_runs(again)
            assert (dec.stats.duplicates, dec.stats.restarts) == ((1, 0) if duplicate else (0, 1)), (first, back)
            assert got == [] if duplicate else got[0].restart


def test_a_board_reset_at_a_small_index_is_a_restart_not_duplicates() -> None:
    """A board reset while its index is under the duplicate window: frames at indices already placed but with other samples are
    a new session (a restart), never dropped as duplicates; every sample after the reset is delivered."""
    before, _ = _stream(100)  # 0 .. 1999
    after, _ = _stream(50, seed=9)  # the board restarted at 0: other samples at the same indices
    for cut in (None, 1):
        dec = FrameDecoder()
        got = dec.feed(b"".join(before + after)) if cut is None else [f for b in b"".join(before + after) for f in dec.feed(bytes([b]))]
        assert dec.stats.restarts == 1 and dec.stats.duplicates == 0 and dec.stats.samples_lost == 0
        assert dec.stats.samples == 3000 and len(got) == 150
        assert got[100].restart and got[100].index == 2000  # the host timeline continues


def test_a_forward_gap_of_any_length_the_counter_can_say_is_lost_samples() -> None:
    """An unplug of 25 s at 20 kHz, and the longest jump the 32-bit counter can say (2**31 - 1): counted as lost, nothing allocated."""
    for gap in (500_000, (1 << 31) - 1 - 20):
        dec = FrameDecoder()
        a, _ = _stream(2)
        b, _ = _stream(2, first=40 + gap, seed=3)
        got = dec.feed(b"".join(a + b))
        assert [(f.index, f.lost, f.restart) for f in got] == [(0, 0, False), (20, 0, False), (40 + gap, gap, False), (60 + gap, 0, False)]
        assert dec.stats.samples_lost == gap and dec.stats.restarts == 0
    dec = FrameDecoder()  # 2**31 ahead is as far behind: the counter cannot say which, so it is a restart
    a, _ = _stream(2)
    b, _ = _stream(2, first=40 + (1 << 31), seed=3)
    got = dec.feed(b"".join(a + b))
    assert dec.stats.restarts == 1 and dec.stats.samples_lost == 0 and got[2].index == 40
