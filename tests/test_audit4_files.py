"""A fourth outside audit (2026-11-27) of recording files, journals, MCAP reading and surface names: what it reproduced,
each through the real CLI on real files. Surface names that print alike (format characters, NFD) are refused; a
recording's lost ranges and first_index cannot pass through int64 overflow; a hostile MCAP's metadata is refused in one
line naming the file and key while the other files are replayed; recover refuses a journal whose recording load would
refuse, writing nothing; a recorder whose folder was removed says the capture is lost, not where it is kept."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.conftest import cli_here, lossy_recording

ZWSP, RLO, BOM = "\u200b", "\u202e", "\ufeff"
NFD = "Pone\u0301"  # prints as "Poné" (NFC "Pon\u00e9")


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A short simulated recording as .npz arrays (``arrays``) and its file (``npz``), once per module."""
    from tactiled.files.recording import save_recording

    root = tmp_path_factory.mktemp("audit4")
    npz = root / "good.npz"
    save_recording(npz, lossy_recording(0, slides=2, lost=()))
    with np.load(npz, allow_pickle=False) as f:
        arrays = {k: f[k] for k in f.files}
    return {"root": root, "npz": npz, "arrays": arrays}


def _one_error(res: Any) -> str:
    """The command's only stderr line (no traceback)."""
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    return str(lines[0])


def _replay_refuses(capfd: pytest.CaptureFixture[str], base: dict[str, Any], bad: Path) -> str:
    """``replay bad good``: one error line for ``bad`` (returned), ``good`` replayed after it."""
    res = cli_here(capfd, "replay", "--jobs", "1", str(bad), str(base["npz"]))
    line = _one_error(res)
    assert res.returncode != 0 and str(bad) in line, res.stderr
    assert f"{base['npz']}: 2 slides" in res.stdout, res.stdout
    return line


def _saved(base: dict[str, Any], name: str, **changes: Any) -> Path:
    path = Path(base["root"]) / name
    np.savez(path, **{**base["arrays"], **changes})
    return path


@pytest.mark.parametrize("name, shown", [(f"Ra0.44{ZWSP}", "U+200B"), (f"{RLO}44.0aR", "U+202E"), (f"{BOM}Ra0.44", "U+FEFF")])
def test_names_that_print_alike_are_refused_in_files_and_labels(capfd: pytest.CaptureFixture[str], base: dict[str, Any],
                                                                 name: str, shown: str) -> None:
    """A recording's label and a slide's surface with a format character that does not spell a word are refused at load
    (naming the code point); so is ``enrol --label`` with such a name, before any work."""
    for key in ("label", "surface"):
        value = np.str_(name) if key == "label" else np.array([name, "Ra2.29"])
        line = _replay_refuses(capfd, base, _saved(base, f"name_{key}.npz", **{key: value}))
        assert f": {key}: " in line and shown in line, line
    res = cli_here(capfd, "enrol", "--label", name, "-o", str(Path(base["root"]) / "m.npz"), "", str(base["npz"]))
    line = _one_error(res)
    assert res.returncode != 0 and "--label: " in line and shown in line, line
    assert not (Path(base["root"]) / "m.npz").exists()


def test_nfc_name_is_still_accepted(capfd: pytest.CaptureFixture[str], base: dict[str, Any]) -> None:
    """The NFC spelling of a name with an accent loads as before."""
    res = cli_here(capfd, "replay", "--jobs", "1", str(_saved(base, "nfc.npz", label=np.str_("Pon\u00e9"))))
    assert res.returncode == 0 and "2 slides" in res.stdout, res.stderr


def test_spellings_that_differ_only_in_normalisation_are_one_surface_and_joiners_spell_words(base: dict[str, Any]) -> None:
    """"Pone\u0301" (as macOS types it) is read as "Pon\u00e9", in a label and in slides' surfaces: one surface, and files
    that hold it load (a review: refusing them broke recordings and models users had). ZWNJ, ZWJ and the soft hyphen spell
    words (Persian, Indic scripts, emoji): accepted."""
    from tactiled.files.recording import load_recording

    rec = load_recording(_saved(base, "nfd.npz", label=np.str_(NFD)))
    assert rec.label == "Pon\u00e9"
    both = load_recording(_saved(base, "nfd2.npz", surface=np.array([NFD, "Pon\u00e9"])))
    assert both.surface is not None and set(both.surface.tolist()) == {"Pon\u00e9"}
    for name in ("\u0646\u06cc\u0645\u200c\u0635\u0627\u0641", "\u0915\u094d\u200d\u0937", "Sand\u00adpaper P80"):
        assert load_recording(_saved(base, "joiner.npz", label=np.str_(name))).label == name


def test_lost_ranges_cannot_wrap_past_int64(capfd: pytest.CaptureFixture[str], base: dict[str, Any]) -> None:
    """lost [[2**62, 2**62]]: position + count wraps int64 to negative; refused as outside samples, no overflow warning."""
    line = _replay_refuses(capfd, base, _saved(base, "lost_overflow.npz", lost=np.array([[2**62, 2**62]], dtype=np.int64)))
    assert ": lost: ranges must lie inside samples" in line, line


@pytest.mark.parametrize("first", [np.uint64(2**64 - 1), np.int64(2**63 - 1), np.int64(-(2**63))])
def test_first_index_must_leave_room_for_the_rows(capfd: pytest.CaptureFixture[str], base: dict[str, Any], first: Any) -> None:
    """first_index is an int64 and first_index + n fits int64: a uint64 2**64-1 and an int64 max are refused at load.
    (The int64 minimum is an index, and loads.)"""
    path = _saved(base, "first.npz", first_index=first)
    if int(first) < 0:
        res = cli_here(capfd, "replay", "--jobs", "1", str(path))
        assert res.returncode == 0, res.stderr
        return
    line = _replay_refuses(capfd, base, path)
    assert ": first_index: " in line, line


def _mcap_with(src: Path, out: Path, change: dict[str, str | None]) -> Path:
    """The MCAP ``src`` rewritten to ``out`` with its tactiled.recording metadata's keys changed (None: removed)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as fh:
        reader = make_reader(fh)
        info = next(m.metadata for m in reader.iter_metadata() if m.name == "tactiled.recording")
        fh.seek(0)
        messages = [(s, c, m) for s, c, m in make_reader(fh).iter_messages(log_time_order=False)]
    meta = {k: v for k, v in {**info, **change}.items() if v is not None}
    with open(out, "wb") as fh:
        writer = Writer(fh)
        writer.start(profile="", library="test")
        writer.add_metadata("tactiled.recording", meta)
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in messages:
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas[schema.id] if schema is not None else 0, channel.metadata)
            writer.add_message(channels[channel.id], message.log_time, message.data, message.publish_time, message.sequence)
        writer.finish()
    return out


@pytest.fixture(scope="module")
def exported(base: dict[str, Any]) -> Path:
    """``base`` exported to MCAP (JSON profile, no model)."""
    from tactiled.cli.main import main

    out = Path(base["root"]) / "base.mcap"
    assert main(["export", "--no-model", "-o", str(out), str(base["npz"])]) == 0
    return out


@pytest.mark.parametrize("key, value", [("fs", None), ("fs", "fast"), ("volts_per_count", "abc"), ("samples_dtype", "bogus"),
                                        ("first_index", str(2**64)), ("volts_per_count", "0")])
def test_hostile_mcap_metadata_is_one_line_and_the_next_file_replays(capfd: pytest.CaptureFixture[str], base: dict[str, Any],
                                                                      exported: Path, key: str, value: str | None) -> None:
    """Each bad value of the tactiled.recording metadata: one line naming the file and the key, no traceback, and the
    good file after it is replayed."""
    bad = _mcap_with(exported, Path(base["root"]) / f"bad_{key}.mcap", {key: value})
    line = _replay_refuses(capfd, base, bad)
    assert f"{bad}: " in line and key in line, line


def test_rewritten_mcap_unchanged_still_replays(capfd: pytest.CaptureFixture[str], base: dict[str, Any], exported: Path) -> None:
    """The rewriting itself keeps a good MCAP good (the test above is about the changed key only)."""
    same = _mcap_with(exported, Path(base["root"]) / "same.mcap", {})
    res = cli_here(capfd, "replay", "--jobs", "1", str(same))
    assert res.returncode == 0 and "2 slides" in res.stdout, res.stderr


def _journal(path: Path, header: tuple[Any, ...], index: int = 0) -> Path:
    from tactiled.files.journal import encode_chunk, encode_header

    path.write_bytes(encode_header(*header, None, {}) + encode_chunk(5, index, 100, [], {}, np.full((100, 2), 5, np.int16)))
    return path


@pytest.mark.parametrize("header, index, key", [((20000.0, 2, 5 / 32768), -(2**63), "first_index"),
                                                ((20000.0, 2, 1e300), 0, "volts_per_count"),
                                                ((True, 2, 1.0), 0, "fs"), ((20000.0, 2.9, 1.0), 0, "channels"),
                                                ((20000.0, True, 1.0), 0, "channels"), ((20000.0, 2, 1e-300), 0, "volts_per_count")])
def test_recover_refuses_what_load_would_refuse(capfd: pytest.CaptureFixture[str], tmp_path: Path, header: tuple[Any, ...],
                                                index: int, key: str) -> None:
    """A journal with intact chunks but values a recording may not hold: one line naming the journal and the key, nothing
    written (no traceback, no recording that replay then refuses, no bool taken as 1 Hz or 2.9 channels as 2)."""
    journal = _journal(tmp_path / "x.npz.journal", header, index)
    out = tmp_path / "out.npz"
    res = cli_here(capfd, "recover", str(journal), "-o", str(out))
    line = _one_error(res)
    assert res.returncode == 2 and str(journal) in line and key in line, line
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == [journal.name]


def test_recover_of_a_sane_journal_still_loads(capfd: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """The same journal with sane values recovers, and what it wrote loads with the index and lost rows it said."""
    from tactiled.files.recording import load_recording

    journal = _journal(tmp_path / "x.npz.journal", (20000.0, 2, 5 / 32768), 1005)
    res = cli_here(capfd, "recover", str(journal), "-o", str(tmp_path / "out.npz"))
    assert res.returncode == 0, res.stderr
    rec = load_recording(tmp_path / "out.npz")
    assert rec.first_index == 1000 and rec.samples.shape == (105, 2) and rec.lost.tolist() == [[0, 5]]


def test_folder_removed_while_recording_says_the_capture_is_lost(tmp_path: Path) -> None:
    """The recording's folder (with its journal) removed while the sink runs: the message says the journal no longer
    exists, and does not point at it for a recover."""
    from tactiled.board.frames import Frame
    from tactiled.service.recorder import RecordingSink

    folder = tmp_path / "vd"
    folder.mkdir()
    sink = RecordingSink(folder / "r.npz", fs=20000.0, channels=2, volts_per_count=5 / 32768)
    sink.add(Frame(0, np.zeros((100, 2), np.int16)))
    shutil.rmtree(folder)
    result = sink.finish()
    assert result.error is not None and "\n" not in result.error
    assert "no longer exists" in result.error and "capture is lost" in result.error, result.error
    assert "tactiled recover" not in result.error and "kept in" not in result.error, result.error


def test_nan_ra_and_tiny_scale_are_refused(capfd: pytest.CaptureFixture[str], base: dict[str, Any]) -> None:
    """A NaN ra_um (invalid JSON once exported) and a volts_per_count of 1e-300 are refused at load in one line."""
    line = _replay_refuses(capfd, base, _saved(base, "nan_ra.npz", ra_um=np.array([np.nan, 0.4])))
    assert ": ra_um: " in line and "finite" in line, line
    line = _replay_refuses(capfd, base, _saved(base, "tiny_vpc.npz", volts_per_count=np.float64(1e-300)))
    assert ": volts_per_count: " in line and "1e-12" in line, line


def test_meta_json_round_trip_unchanged(base: dict[str, Any]) -> None:
    """The fixture's recording is as the loader reads it (guards the tests above against a broken base)."""
    from tactiled.files.recording import load_recording

    rec = load_recording(base["npz"])
    assert rec.first_index == 0 and len(rec.slides()) == 2 and json.loads(str(base["arrays"]["meta"])) == rec.meta
