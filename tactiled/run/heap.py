"""glibc's malloc in a process that runs whole recordings through the pipeline: its temporaries kept in the heap."""

from __future__ import annotations

import functools

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)
HEAP_BLOCK_BYTES = 4 << 20  # blocks up to this size come from the heap (the pipeline's temporaries are 0.25-1.3 MB)
HEAP_KEPT_BYTES = 8 << 20  # freed memory at the heap's top kept up to this size, not given back to the system


@functools.cache  # once per process (a replay, or each worker): every file after the first asks again for nothing
def keep_freed_memory() -> bool:
    """For a process that runs whole files through the pipeline (a replay, its workers): glibc's malloc serves blocks up to
    :data:`HEAP_BLOCK_BYTES` from its heap and keeps up to :data:`HEAP_KEPT_BYTES` freed, so that the temporaries made for
    every block of samples and batch of windows are reused rather than mapped, faulted in page by page and unmapped each
    time. glibc's own adaptive thresholds did this only after a block of some size had been freed (until 2026-11-26
    the recording's check made a 24 MB temporary); a replay of 5 minutes took 51 000 page faults without it, 11 500 with it
    (about 0.05 s of 0.6). True if set (glibc's ``mallopt``); elsewhere nothing changes. Not for the daemon, whose
    resident memory over days is a budget of its own."""
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt, macOS another allocator)
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, HEAP_BLOCK_BYTES)) and bool(mallopt(M_TRIM_THRESHOLD, HEAP_KEPT_BYTES))
