"""Recording files (.npz), per docs/recordings.md.

:func:`load_recording` validates everything the spec lists and raises one
:class:`~tactiled.errors.RecordingError` naming the file and the key; it never loads
pickle. :func:`save_recording` writes atomically (temporary file, then rename), the samples
optionally block by block (:class:`StreamedArray`), so a long capture never has to fit in memory.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import unicodedata
import zipfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, BinaryIO

import numpy as np
import numpy.typing as npt

from tactiled.errors import RecordingError, TactiledError
from tactiled.files.npzio import NpzError, NpzReader, load_json_bounded, read_npz

KEYS = ("samples", "fs", "volts_per_count", "first_index", "label", "meta", "lost", "slide_start", "slide_stop", "surface", "ra_um",
        "disconnected")
MIN_FS, MAX_FS, MAX_CHANNELS = 1.0, 1e7, 64
MAX_LABEL_CHARS = 256  # a surface name (label, surface[i]): longer ones are refused at load (a 4M-character label cost score 1 GB)
MAX_VOLTS = 1e9  # |samples| in volts: 30x what a config's volts_per_count allows an int16 board; squares and sums stay far from overflow
MAX_RECORDING_BYTES = 2 << 30  # 2 GiB inflated: 7 h of 2 channels of int16 at 20 kHz; split longer recordings
MIN_VOLTS_PER_COUNT = 1e-12  # V per count: the least a config allows (tactiled.config); below, counts would be volts of nothing
INT64_MAX = (1 << 63) - 1


@dataclass
class Recording:
    """One recording. ``samples`` (n, C) int16 counts or float volts; indices are positions."""

    samples: npt.NDArray[Any]
    fs: float
    volts_per_count: float = 1.0
    slide_start: npt.NDArray[np.int64] | None = None
    slide_stop: npt.NDArray[np.int64] | None = None
    surface: npt.NDArray[np.str_] | None = None
    ra_um: npt.NDArray[np.float64] | None = None
    label: str | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    first_index: int = 0
    lost: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    # (d,) strictly increasing positions in [0, n]: at each the host lost the sensor's port (every row before it was read before)
    disconnected: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def channels(self) -> int:
        """C: the number of channels (columns of ``samples``)."""
        return int(self.samples.shape[1])

    @property
    def is_integer(self) -> bool:
        """True for integer ADC counts (volts = counts × ``volts_per_count``), False for float volts."""
        return bool(np.issubdtype(self.samples.dtype, np.integer))

    def volts(self) -> npt.NDArray[np.float64]:
        """All samples in volts, float64 (n, C)."""
        if self.is_integer:
            return self.samples.astype(np.float64) * self.volts_per_count
        return self.samples.astype(np.float64)

    def valid_mask(self) -> npt.NDArray[np.bool_]:
        """(n,) False where samples were lost."""
        mask = np.ones(self.samples.shape[0], dtype=bool)
        for pos, count in merge_ranges(self.lost):
            mask[pos:pos + count] = False
        return mask

    def slides(self) -> list[tuple[int, int, str | None]]:
        """Ground-truth slides as (start, stop, surface) positions; empty if none."""
        if self.slide_start is None or self.slide_stop is None:
            return []
        names = self.surface if self.surface is not None else [self.label] * len(self.slide_start)
        return [(int(a), int(b), None if s is None else str(s)) for a, b, s in zip(self.slide_start, self.slide_stop, names, strict=True)]


def merge_ranges(ranges: npt.ArrayLike) -> npt.NDArray[np.int64]:
    """(g, 2) [position, count] ranges, sorted by position, overlapping and touching ones joined: the same rows, each
    once. ``lost`` of a file may list ranges in any order and overlapping; a sweep over these is linear. O(g log g)."""
    r = np.asarray(ranges, dtype=np.int64).reshape(-1, 2)
    if len(r) < 2:
        return r
    r = r[np.argsort(r[:, 0], kind="stable")]
    start, end = r[:, 0], r[:, 0] + r[:, 1]
    new = np.concatenate(([True], start[1:] > np.maximum.accumulate(end)[:-1]))
    first = np.flatnonzero(new)
    ends = np.maximum.reduceat(end, first)
    return np.column_stack([start[first], ends - start[first]])


def largest_magnitude(samples: npt.NDArray[Any]) -> float:
    """max |x| of the non-empty array ``samples`` (int16 counts or finite floats), as a float, from its least and greatest
    values: no array of |x| (24 MB for a 5-minute recording), and an int16 -32768 counts as 32768 (np.abs wraps it to itself)."""
    return max(-float(samples.min()), float(samples.max()))


def lost_rows_budget(file_bytes: int, floor: int) -> int:
    """Rows of zeros a reader may make for the lost samples a file of ``file_bytes`` declares or implies (index gaps,
    lost ranges): one per byte of the file, and at least ``floor``. Beyond it, a few bytes could claim terabytes."""
    return max(floor, file_bytes)


UNPRINTABLE = frozenset({"Cc", "Cs", "Zl", "Zp"})  # control characters, lone surrogates, line and paragraph separators
INVISIBLE = frozenset({"Cf"})  # format characters (zero-width space, bidi overrides, BOM): unseen, or they reorder what is seen
JOINERS = frozenset({"\u200c", "\u200d", "\u00ad"})  # format characters that spell words (ZWNJ in Persian, ZWJ in Indic scripts
# and emoji, the soft hyphen): accepted


def surface_name_problem(name: str) -> str | None:
    """What is wrong with ``name`` as a surface name (a recording's ``label`` or ``surface[i]``, ``enrol --label``), or None.

    A name must hold something other than white space ("" is how training marks an unlabelled slide: such a surface
    would be listed, then silently left out of the model), neither begin nor end with it, at most :data:`MAX_LABEL_CHARS` characters, no control
    character, lone surrogate or line separator (replay and score print one line per slide), no format character (category Cf:
    "Ra0.44\u200b" would print as "Ra0.44", "\u202e44.0aR" as "Ra0.44") but those that spell words (:data:`JOINERS`): two names
    that print alike would be two surfaces. Such names are refused. Spellings of one name that differ only in Unicode
    normalisation ("Pone\u0301" and "Pon\u00e9") are one surface: recordings' names are read in NFC (:func:`surface_name`)."""
    if len(name) > MAX_LABEL_CHARS:
        return f"{len(name)} characters, more than the {MAX_LABEL_CHARS} a surface name may have"
    if not name.strip():
        return f"must not be empty or blank, got {name!r}"
    if name != name.strip():  # "P120 " and "P120" would be two surfaces that print alike
        return f"{name!r} begins or ends with white space; a surface name is printed as it is, so two would look alike"
    bad = next((ch for ch in name if unicodedata.category(ch) in UNPRINTABLE), None)
    if bad is not None:
        return f"{name!r} holds the control character U+{ord(bad):04X}; a surface name is one printable line"
    bad = next((ch for ch in name if unicodedata.category(ch) in INVISIBLE and ch not in JOINERS), None)
    if bad is not None:
        return (f"{name!a} holds the format character U+{ord(bad):04X} ({unicodedata.name(bad, 'unnamed')}), which does not print "
                "as itself; a surface name is printed as it is, so two would look alike")
    return None


def surface_name(name: str) -> str:
    """``name`` in Unicode normal form NFC: how a recording's names are read, so that two spellings that print alike
    (a label typed on macOS, "Pone\u0301", and elsewhere, "Pon\u00e9") are one surface."""
    return unicodedata.normalize("NFC", name)


def case_twins(names: Iterable[str]) -> list[list[str]]:
    """The groups (each sorted, two or more) of ``names`` that differ only in case ("Ra1.00" and "ra1.00"): two surfaces to
    a model, and most often one surface typed twice."""
    groups: dict[str, set[str]] = {}
    for name in names:
        groups.setdefault(name.casefold(), set()).add(name)
    return sorted(sorted(g) for g in groups.values() if len(g) > 1)


def first_index_problem(first: int, n: int) -> str | None:
    """What is wrong with ``first`` as the sensor sample index of row 0 of ``n`` rows, or None: the indices
    ``first .. first + n`` are int64 (the sensor's index unwrapped to 64 bits: what files and messages carry)."""
    if not -INT64_MAX - 1 <= first <= INT64_MAX - n:
        return f"must be an int64 with first_index + {n} samples within int64 (at most {INT64_MAX - n}), got {first}"
    return None


def volts_per_count_problem(vpc: float) -> str | None:
    """What is wrong with ``vpc`` (V per count) as a recording's scale, or None: finite and at least :data:`MIN_VOLTS_PER_COUNT`."""
    if not (np.isfinite(vpc) and vpc >= MIN_VOLTS_PER_COUNT):
        return f"must be finite and >= {MIN_VOLTS_PER_COUNT:g} V per count, got {vpc}"
    return None


def peak_problem(peak: float) -> str | None:
    """What is wrong with samples whose largest magnitude is ``peak`` volts, or None (at most :data:`MAX_VOLTS`)."""
    if not peak <= MAX_VOLTS:
        return f"reach {peak:.3g} V, beyond the {MAX_VOLTS:g} V of any sensor (samples are volts, or counts times volts_per_count)"
    return None


def check_label_option(label: str | None) -> None:
    """Raise :class:`TactiledError` (``--label: ...``) unless ``label`` is None or a valid surface name
    (:func:`surface_name_problem`): what ``record --label`` and ``enrol --label`` check before any work."""
    problem = None if label is None else surface_name_problem(label)
    if problem:
        raise TactiledError(f"--label: {problem}")


def _fail(path: object, key: str, message: str) -> RecordingError:
    return RecordingError(f"{path}: {key}: {message}")


def load_recording(path: str | Path) -> Recording:
    """Load and validate a recording; raises :class:`RecordingError` naming file and key.

    Only the arrays of docs/recordings.md are read, at most :data:`MAX_RECORDING_BYTES` inflated
    (:mod:`tactiled.files.npzio` refuses decompression bombs before inflating them).
    """
    try:
        arrays = read_npz(path, KEYS, MAX_RECORDING_BYTES)
        if "samples" not in arrays:
            with NpzReader(path, MAX_RECORDING_BYTES) as reader:
                if "header" in reader:  # tactiled's model and features files carry a JSON header, recordings do not
                    raise RecordingError(f"{path}: a model or features file (it has a header and no samples), not a recording")
    except NpzError as exc:
        raise RecordingError(f"{path}: {exc.key}: {exc}" if exc.key else f"{path}: {exc}") from None
    return validate_arrays(path, arrays)


def _scalar(path: object, arrays: dict[str, Any], key: str, kind: str) -> Any:
    arr = arrays[key]
    if arr.shape != ():
        raise _fail(path, key, f"must be a scalar, got shape {arr.shape}")
    if kind == "f" and arr.dtype.kind not in "fiu":
        raise _fail(path, key, f"must be a number, got {arr.dtype}")
    if kind == "i" and arr.dtype.kind not in "iu":
        raise _fail(path, key, f"must be an integer, got {arr.dtype}")
    if kind == "U" and arr.dtype.kind != "U":
        raise _fail(path, key, f"must be a unicode string, got {arr.dtype}")
    return arr.item()


def validate_arrays(path: object, a: dict[str, npt.NDArray[Any]]) -> Recording:
    """The recording the arrays ``a`` (the keys of docs/recordings.md) make, checked; :class:`RecordingError` names ``path`` and key."""
    for key in ("samples", "fs"):
        if key not in a:
            raise _fail(path, key, "missing (required)")
    samples = a["samples"]
    if samples.ndim != 2 or not 1 <= samples.shape[1] <= MAX_CHANNELS:
        raise _fail(path, "samples", f"must have shape (n, C) with 1 <= C <= {MAX_CHANNELS}, got {samples.shape}")
    if samples.dtype not in (np.int16, np.float32, np.float64):
        raise _fail(path, "samples", f"must be int16, float32 or float64, got {samples.dtype}")
    if samples.dtype.kind == "f" and not np.all(np.isfinite(samples)):
        raise _fail(path, "samples", "contains NaN or Inf")
    n = samples.shape[0]
    fs = float(_scalar(path, a, "fs", "f"))
    if not (np.isfinite(fs) and MIN_FS <= fs <= MAX_FS):
        raise _fail(path, "fs", f"must be in [{MIN_FS:g}, {MAX_FS:g}] Hz, got {fs}")
    vpc = float(_scalar(path, a, "volts_per_count", "f")) if "volts_per_count" in a else 1.0
    if problem := volts_per_count_problem(vpc):
        raise _fail(path, "volts_per_count", problem)
    peak = largest_magnitude(samples) * (vpc if samples.dtype.kind == "i" else 1.0) if samples.size else 0.0
    if problem := peak_problem(peak):
        raise _fail(path, "samples", problem)
    rec = Recording(samples=samples, fs=fs, volts_per_count=vpc)
    if "first_index" in a:
        rec.first_index = int(_scalar(path, a, "first_index", "i"))
        if problem := first_index_problem(rec.first_index, n):
            raise _fail(path, "first_index", problem)
    if "label" in a:
        rec.label = surface_name(str(_scalar(path, a, "label", "U")))
        problem = surface_name_problem(rec.label)
        if problem:
            raise _fail(path, "label", problem)
    if "meta" in a:
        try:
            meta = load_json_bounded(_scalar(path, a, "meta", "U"), "meta")
        except ValueError as exc:
            raise RecordingError(f"{path}: {exc}") from None
        if not isinstance(meta, dict):
            raise _fail(path, "meta", "must be a JSON object")
        rec.meta = meta
    if "lost" in a:
        lost = a["lost"]
        if lost.ndim != 2 or lost.shape[1] != 2 or lost.dtype.kind not in "iu":
            raise _fail(path, "lost", f"must be (g, 2) integers, got {lost.shape} {lost.dtype}")
        lost = lost.astype(np.int64)  # a uint64 above int64 wraps negative: refused below
        # position + count <= n as position <= n - count: no sum of two large positions to wrap past int64
        if lost.size and (np.any(lost[:, 0] < 0) or np.any(lost[:, 1] <= 0) or np.any(lost[:, 0] > n - lost[:, 1])):
            raise _fail(path, "lost", "ranges must lie inside samples with count > 0")
        rec.lost = lost
    if "disconnected" in a:
        rec.disconnected = _disconnected(path, a["disconnected"], n)
    has_start, has_stop = "slide_start" in a, "slide_stop" in a
    if has_start != has_stop:
        raise _fail(path, "slide_stop" if has_start else "slide_start", "missing (slide_start and slide_stop go together)")
    if has_start:
        start, stop = a["slide_start"], a["slide_stop"]
        for key, arr in (("slide_start", start), ("slide_stop", stop)):
            if arr.ndim != 1 or arr.dtype.kind not in "iu":
                raise _fail(path, key, f"must be (k,) integers, got {arr.shape} {arr.dtype}")
        if start.shape != stop.shape:
            raise _fail(path, "slide_stop", f"length {stop.shape[0]} differs from slide_start's {start.shape[0]}")
        if np.any(stop <= start):
            raise _fail(path, "slide_stop", "stop must be > start")
        if start.size and (start.min() < 0 or stop.max() > n):
            raise _fail(path, "slide_start", f"indices outside samples (0..{n})")
        rec.slide_start, rec.slide_stop = start.astype(np.int64), stop.astype(np.int64)
        k = start.shape[0]
        for key in ("surface", "ra_um"):
            if key in a and a[key].shape != (k,):
                raise _fail(path, key, f"must have shape ({k},), got {a[key].shape}")
        if "surface" in a:
            if a["surface"].dtype.kind != "U":
                raise _fail(path, "surface", f"must be unicode, got {a['surface'].dtype}")
            longest = int(np.char.str_len(a["surface"]).max()) if k else 0
            if longest > MAX_LABEL_CHARS:
                raise _fail(path, "surface", f"a name of {longest} characters, more than the {MAX_LABEL_CHARS} a surface name may have")
            names, first = np.unique(a["surface"], return_index=True)  # each name checked once, however many slides carry it
            bad = sorted((int(i), problem) for name, i in zip(names, first, strict=True) if (problem := surface_name_problem(str(name))))
            if bad:
                raise _fail(path, "surface", f"slide {bad[0][0]}: {bad[0][1]}")
            rec.surface = a["surface"].astype(f"<U{max(1, longest)}")  # no wider than its longest name, whatever the file declared
            if any(surface_name(str(n)) != n for n in names):  # read in NFC: spellings that print alike are one surface
                rec.surface = np.array([surface_name(str(n)) for n in rec.surface], dtype=np.str_)
        elif rec.label is None:
            raise _fail(path, "surface", "missing (slides need a surface, or a file-level label)")
        if "ra_um" in a:
            if a["ra_um"].dtype.kind != "f":
                raise _fail(path, "ra_um", f"must be float, got {a['ra_um'].dtype}")
            if not np.all(np.isfinite(a["ra_um"])):
                raise _fail(path, "ra_um", f"slide {int(np.flatnonzero(~np.isfinite(a['ra_um']))[0])}: must be finite, got NaN or Inf")
            rec.ra_um = a["ra_um"].astype(np.float64)
    return rec


def _disconnected(path: object, marks: npt.NDArray[Any], n: int) -> npt.NDArray[np.int64]:
    """The ``disconnected`` key checked: (d,) integers, strictly increasing, in [0, ``n``] (``n`` rows of samples)."""
    if marks.ndim != 1 or marks.dtype.kind not in "iu":
        raise _fail(path, "disconnected", f"must be (d,) integers, got {marks.shape} {marks.dtype}")
    if marks.size and (marks.min() < 0 or marks.max() > n):
        raise _fail(path, "disconnected", f"positions outside samples (0..{n})")
    out = marks.astype(np.int64)
    if np.any(np.diff(out) <= 0):
        raise _fail(path, "disconnected", "positions must be strictly increasing")
    return out


@dataclass
class StreamedArray:
    """An array written block by block (bounded memory): its final ``shape`` and ``dtype``, and ``blocks`` of rows.

    The blocks must add up to ``shape`` exactly (C order, first axis); :func:`atomic_savez` checks that.
    """

    shape: tuple[int, ...]
    dtype: np.dtype[Any]
    blocks: Iterable[npt.NDArray[Any]]


def save_recording(path: str | Path, rec: Recording, samples: StreamedArray | None = None) -> None:
    """Write ``rec`` to ``path`` atomically: a temporary file in the same folder, then rename.

    ``samples``, if given, replaces ``rec.samples``: a recording written from blocks (the journal, the recorder).
    """
    arrays: dict[str, Any] = {
        "samples": rec.samples if samples is None else samples,
        "fs": np.float64(rec.fs),
        "volts_per_count": np.float64(rec.volts_per_count),
        "first_index": np.int64(rec.first_index),
        "lost": np.asarray(rec.lost, dtype=np.int64).reshape(-1, 2),
        "meta": np.str_(json.dumps(rec.meta, sort_keys=True)),
    }
    if rec.slide_start is not None and rec.slide_stop is not None:
        arrays["slide_start"] = np.asarray(rec.slide_start, dtype=np.int64)
        arrays["slide_stop"] = np.asarray(rec.slide_stop, dtype=np.int64)
    if rec.surface is not None:
        arrays["surface"] = np.asarray(rec.surface, dtype=np.str_)
    if rec.ra_um is not None:
        arrays["ra_um"] = np.asarray(rec.ra_um, dtype=np.float64)
    if rec.label is not None:
        arrays["label"] = np.str_(rec.label)
    if len(rec.disconnected):  # only when there is one: a file without disconnections is what it was before the key
        arrays["disconnected"] = np.asarray(rec.disconnected, dtype=np.int64).reshape(-1)
    atomic_savez(path, arrays)


@contextlib.contextmanager
def atomic_file(path: str | Path) -> Iterator[BinaryIO]:
    """A binary file to write ``path`` through: a temporary file beside it, then (when the block ends without an error)
    fsync and rename over ``path`` and fsync the folder. ``path`` is the old file or the whole new one, even after a power
    cut; an error, a full disk or a Ctrl-C in the block leaves no file behind (the temporary one is removed)."""
    path = Path(path)
    folder = path.parent or Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    done = False
    try:
        with os.fdopen(fd, "wb") as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
        done = True
        fsync_dir(folder)
    finally:
        if not done:  # interrupted or failed: never leave a half-written file behind
            os.unlink(tmp)


def atomic_savez(path: str | Path, arrays: dict[str, Any]) -> None:
    """What ``np.savez`` writes (uncompressed zip of ``.npy`` members), through :func:`atomic_file`: ``path`` is the old
    file or the whole new one. A :class:`StreamedArray` value is written block by block."""
    with atomic_file(path) as fh, zipfile.ZipFile(fh, mode="w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for key, value in arrays.items():
            with zf.open(f"{key}.npy", "w", force_zip64=True) as member:
                if isinstance(value, StreamedArray):
                    _write_streamed(member, key, value)
                else:
                    np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)


def _write_streamed(member: IO[bytes], key: str, value: StreamedArray) -> None:
    dtype = np.dtype(value.dtype)
    np.lib.format.write_array_header_1_0(member, {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False,
                                                  "shape": tuple(value.shape)})
    row = value.shape[1:]
    rows = 0
    for block in value.blocks:
        if block.shape[1:] != row:
            raise ValueError(f"{key}: block of shape {block.shape} in an array of rows {row}")
        member.write(np.ascontiguousarray(block, dtype=dtype).tobytes())
        rows += block.shape[0]
    if rows != value.shape[0]:
        raise ValueError(f"{key}: blocks hold {rows} rows, the header says {value.shape[0]}")


def fsync_dir(path: str | Path) -> None:
    """fsync a folder, so a file just created or renamed in it survives a power cut."""
    fd = os.open(path or ".", os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
