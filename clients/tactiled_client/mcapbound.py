"""How far an MCAP file's records would inflate, read before any chunk is: a few kB of zstd can declare gigabytes.

Shared by the client's session reader (:mod:`tactiled_client.log`) and tactiled's own MCAP recordings reader, so both
refuse the same files. Needs the ``mcap`` package (and ``zstandard`` for zstd chunks, which ``mcap`` reads them with).
"""

from __future__ import annotations

import os
from typing import BinaryIO

MAX_RATIO = 200  # inflated bytes per byte of file, past RATIO_FLOOR (the bound an .npz member has in tactiled)
RATIO_FLOOR = 16 << 20


def inflation_problem(fh: BinaryIO, limit: int) -> str | None:
    """Why the MCAP file open in ``fh`` (binary, seekable; its position is kept) must not be read, or None: its chunks and
    messages would inflate beyond :data:`MAX_RATIO` to 1 of its size (past :data:`RATIO_FLOOR` bytes) or beyond ``limit``
    bytes, or a chunk is compressed otherwise than with zstd or not at all. A zstd chunk counts the larger of the size
    it declares and the size its frame declares (zstandard inflates a frame to the size in its header, whatever the
    chunk says). Raises what the mcap reader raises on a file it cannot parse."""
    from mcap.records import Chunk, Message
    from mcap.stream_reader import StreamReader

    start = fh.tell()
    size = os.fstat(fh.fileno()).st_size
    inflated = 0
    for record in StreamReader(fh, emit_chunks=True, record_size_limit=limit).records:
        if isinstance(record, Chunk):
            if record.compression == "zstd":
                import zstandard

                try:
                    framed = zstandard.frame_content_size(record.data)
                except zstandard.ZstdError:
                    return "a zstd chunk that holds no zstd frame"
                inflated += max(record.uncompressed_size, framed)
            elif record.compression == "":
                inflated += len(record.data)
            else:
                return f"a chunk compressed with {record.compression!r} (tactiled writes zstd or none)"
        elif isinstance(record, Message):
            inflated += len(record.data)
    fh.seek(start)
    if inflated > limit or (inflated > RATIO_FLOOR and inflated > MAX_RATIO * size):
        return f"its records inflate {size} bytes to {inflated} (over {MAX_RATIO}:1 or past {limit}): a decompression bomb"
    return None
