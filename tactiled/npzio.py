"""Reading ``.npz`` files safely: no pickle, and no array larger than the bytes stored.

Shared by the recording and model loaders. Every member's ``.npy`` header is read first;
an array whose declared size exceeds what the archive stores for it (a hostile or corrupt
header asking for terabytes) is refused before anything is allocated.
"""

from __future__ import annotations

import tokenize
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt


class NpzError(ValueError):
    """``key`` is the member at fault ('' for the archive); the message says what."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(message)
        self.key = key


def read_npz(path: str | Path) -> dict[str, npt.NDArray[Any]]:
    """All arrays of an ``.npz`` archive, loaded without pickle after a size check of each."""
    try:
        zf = zipfile.ZipFile(path)
    except FileNotFoundError:
        raise NpzError("", "no such file") from None
    except (OSError, zipfile.BadZipFile, EOFError, ValueError, NotImplementedError, RuntimeError) as exc:
        # zipfile raises NotImplementedError for unknown versions and compressions, RuntimeError for encryption
        raise NpzError("", f"not a readable .npz file: {exc}") from None
    arrays: dict[str, npt.NDArray[Any]] = {}
    with zf:
        for info in zf.infolist():
            key = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            try:
                with zf.open(info) as fh:
                    version = np.lib.format.read_magic(fh)
                    readers = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
                    if version not in readers:
                        raise NpzError(key, f"unsupported .npy format version {version}")
                    shape, _, dtype = readers[version](fh)  # the header only: nothing allocated yet
                    if dtype.hasobject:
                        raise NpzError(key, "cannot load without pickle (object array)")
                    nbytes = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
                    if nbytes > info.file_size:
                        raise NpzError(key, f"declares shape {shape} ({nbytes} bytes) but stores {info.file_size} bytes")
                with zf.open(info) as fh:
                    arr = np.lib.format.read_array(fh, allow_pickle=False)
                if arr.dtype.kind == "U" and arr.size and int(np.ascontiguousarray(arr).view(np.uint32).max()) > 0x10FFFF:
                    raise NpzError(key, "invalid unicode (code point beyond U+10FFFF)")
                arrays[key] = arr
            except NpzError:
                raise
            except (ValueError, OSError, zipfile.BadZipFile, EOFError, KeyError, MemoryError, NotImplementedError, RuntimeError,
                    SyntaxError, tokenize.TokenError) as exc:  # numpy parses the .npy header dict with tokenize
                raise NpzError(key, f"corrupt array: {exc}") from None
    return arrays


def load_json_bounded(text: str, what: str, max_bytes: int = 1_000_000, max_depth: int = 32) -> Any:
    """``json.loads`` of a string read from a file, refusing more than ``max_bytes`` or nesting deeper than ``max_depth``.

    Raises ValueError naming ``what``; the depth is checked before parsing, so a deeply
    nested document cannot exhaust the recursion limit.
    """
    import json

    if len(text) > max_bytes:
        raise ValueError(f"{what}: JSON larger than {max_bytes} bytes")
    depth = deepest = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
            if deepest > max_depth:
                raise ValueError(f"{what}: JSON nested deeper than {max_depth} levels")
        elif ch in "]}":
            depth -= 1
    try:
        return json.loads(text)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise ValueError(f"{what}: not JSON: {exc}") from None
