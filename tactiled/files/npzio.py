"""Reading ``.npz`` files safely: no pickle, bounded memory, only the members asked for.

Shared by the recording, model and feature-file loaders. An archive is refused (one
:class:`NpzError` naming the member) before anything large is allocated or inflated when:

- it lists more than :data:`MAX_MEMBERS` entries, or a member is compressed by anything but
  stored or deflate (what NumPy writes; bzip2 and LZMA inflate a 1 kB member to gigabytes);
- a member's ``.npy`` header declares an object (pickle) or an unsupported dtype, more bytes
  than the caller's budget (``max_bytes``, all members read together), more than the zip
  says it stores, or a compression ratio no real data reaches (a decompression bomb:
  over :data:`MAX_RATIO` to 1 for a member over :data:`RATIO_FLOOR` bytes).

The data are then streamed from the zip member into an array of the declared size, chunk by
chunk, and reading stops there: the zip's own declared sizes are never trusted alone, and a
member shorter than its header says is refused as truncated. Members not asked for are never
decompressed.
"""

from __future__ import annotations

import json
import math
import re
import tokenize
import zipfile
from collections.abc import Iterable
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
import numpy.typing as npt

from tactiled.readable import MISSING, file_problem

MAX_MEMBERS = 64
MAX_FILE_BYTES = 1 << 34  # 16 GiB: a recording, model or feature file larger than this is refused before it is opened
MAX_RATIO = 200
RATIO_FLOOR = 16 << 20
CHUNK = 1 << 20
DTYPE_KINDS = "biufU"  # bool, integers, floats, unicode: everything tactiled writes
# a string, or an unterminated one to the end of the text: a match never fails once begun, so the scan is linear (a pattern
# that must find the closing quote tries again from every quote of an unterminated string of escaped quotes: quadratic)
_STRINGS = re.compile(r'"(?:[^"\\]|\\.)*"?', re.DOTALL)
_BRACKETS = re.compile(r"[\[\]{}]")
_ARCHIVE_ERRORS = (OSError, zipfile.BadZipFile, EOFError, ValueError, NotImplementedError, RuntimeError)


class NpzError(ValueError):
    """``key`` is the member at fault ('' for the archive); the message says what."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(message)
        self.key = key


def _entry_count(path: str | Path) -> int | None:
    """Entries the zip's end record declares, read before :class:`zipfile.ZipFile` parses its whole directory (None: unknown)."""
    end_record = getattr(zipfile, "_EndRecData", None)  # stable private helper of zipfile since Python 2
    if end_record is None:  # pragma: no cover - a future Python without it: zipfile's own parse is the bound
        return None
    with open(path, "rb") as fh:
        rec = end_record(fh)
    return None if rec is None else int(rec[4])  # _ECD_ENTRIES_TOTAL


class NpzReader:
    """An open ``.npz`` archive whose members are read one by one, within ``max_bytes`` in all (a context manager)."""

    def __init__(self, path: str | Path, max_bytes: int) -> None:
        self.path = path
        self.remaining = max_bytes
        self.max_bytes = max_bytes
        problem = file_problem(path, MAX_FILE_BYTES)
        if problem is not None:
            raise NpzError("", problem)
        try:
            count = _entry_count(path)
            if count is not None and count > MAX_MEMBERS:
                raise NpzError("", f"lists {count} members, more than the {MAX_MEMBERS} a tactiled file has")
            self.zf = zipfile.ZipFile(path)
        except FileNotFoundError:
            raise NpzError("", MISSING) from None
        except NpzError:
            raise
        except _ARCHIVE_ERRORS as exc:
            # zipfile raises NotImplementedError for unknown versions and compressions, RuntimeError for encryption
            raise NpzError("", f"not a readable .npz file: {exc}") from None
        infos = self.zf.infolist()
        if len(infos) > MAX_MEMBERS:
            self.zf.close()
            raise NpzError("", f"lists {len(infos)} members, more than the {MAX_MEMBERS} a tactiled file has")
        self.members = {(i.filename[:-4] if i.filename.endswith(".npy") else i.filename): i for i in infos}

    def __enter__(self) -> NpzReader:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        """Close the archive."""
        self.zf.close()

    def keys(self) -> list[str]:
        """The member names, without ``.npy``, in archive order."""
        return list(self.members)

    def __contains__(self, key: object) -> bool:
        return key in self.members

    def read(self, key: str) -> npt.NDArray[Any]:
        """The array ``key``, streamed within the remaining budget; :class:`NpzError` naming ``key`` otherwise."""
        info = self.members[key]
        try:
            arr = self._read(key, info)
        except NpzError:
            raise
        except (*_ARCHIVE_ERRORS, KeyError, MemoryError, SyntaxError, tokenize.TokenError) as exc:
            # numpy parses the .npy header dict with tokenize
            raise NpzError(key, f"corrupt array: {exc}") from None
        if arr.dtype.kind == "U" and arr.size and int(np.ascontiguousarray(arr).view(np.uint32).max()) > 0x10FFFF:
            raise NpzError(key, "invalid unicode (code point beyond U+10FFFF)")
        return arr

    def _read(self, key: str, info: zipfile.ZipInfo) -> npt.NDArray[Any]:
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            method = {zipfile.ZIP_BZIP2: "bzip2", zipfile.ZIP_LZMA: "LZMA"}.get(info.compress_type, str(info.compress_type))
            raise NpzError(key, f"compression method {method} refused (NumPy writes stored or deflate members only)")
        with self.zf.open(info) as fh:
            version = np.lib.format.read_magic(fh)
            readers = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
            if version not in readers:
                raise NpzError(key, f"unsupported .npy format version {version}")
            shape, fortran, dtype = readers[version](fh)  # the header only: nothing allocated yet
            if dtype.hasobject:
                raise NpzError(key, "cannot load without pickle (object array)")
            if dtype.kind not in DTYPE_KINDS or dtype.fields is not None or dtype.subdtype is not None:
                raise NpzError(key, f"dtype {dtype} refused (booleans, integers, floats and unicode only)")
            count = math.prod(shape)
            nbytes = count * dtype.itemsize
            if nbytes > self.remaining:
                raise NpzError(key, f"declares shape {shape} ({nbytes} bytes), more than the {self.max_bytes} bytes allowed for this file")
            if nbytes > info.file_size:
                raise NpzError(key, f"declares shape {shape} ({nbytes} bytes) but stores {info.file_size} bytes")
            if info.compress_type != zipfile.ZIP_STORED and nbytes > RATIO_FLOOR and nbytes > MAX_RATIO * info.compress_size:
                raise NpzError(key, f"inflates {info.compress_size} bytes to {nbytes} (over {MAX_RATIO}:1): a decompression bomb")
            self.remaining -= nbytes
            arr = np.empty(count, dtype=dtype)
            flat = arr.view(np.uint8).reshape(-1)
            done = 0
            while done < nbytes:
                data = fh.read(min(CHUNK, nbytes - done))
                if not data:
                    raise NpzError(key, f"truncated: {done} of {nbytes} bytes")
                flat[done:done + len(data)] = np.frombuffer(data, dtype=np.uint8)
                done += len(data)
        return arr.reshape(shape, order="F" if fortran else "C")


def read_npz(path: str | Path, members: Iterable[str] | None = None, max_bytes: int = 256 << 20) -> dict[str, npt.NDArray[Any]]:
    """The arrays ``members`` of an ``.npz`` archive (None: all) that it holds, within ``max_bytes`` in all, loaded without pickle."""
    with NpzReader(path, max_bytes) as reader:
        keys = reader.keys() if members is None else [k for k in members if k in reader]
        return {k: reader.read(k) for k in keys}


def load_json_bounded(text: str, what: str, max_bytes: int = 1_000_000, max_depth: int = 32) -> Any:
    """``json.loads`` of a string read from a file, refusing more than ``max_bytes`` or nesting deeper than ``max_depth``.

    Raises ValueError naming ``what``; the depth is checked before parsing, so a deeply
    nested document cannot exhaust the recursion limit.
    """
    if len(text) > max_bytes:
        raise ValueError(f"{what}: JSON larger than {max_bytes} bytes")
    depth = 0
    for m in _BRACKETS.finditer(_STRINGS.sub('""', text)):  # brackets outside strings
        depth += 1 if m.group() in "[{" else -1
        if depth > max_depth:
            raise ValueError(f"{what}: JSON nested deeper than {max_depth} levels")
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as exc:  # JSONDecodeError, or an integer of more digits than Python converts
        raise ValueError(f"{what}: not JSON: {exc}") from None
