"""Work over many files on every core: one worker process per core, results in the order of the inputs.

Replay, scoring and feature extraction treat each recording on its own, so a folder of recordings is spread
over worker processes (joblib's loky backend: the workers start once per call, import tactiled once, and
receive large arrays as memory maps rather than copies). One file, or ``jobs=1``, runs in this process.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from typing import TypeVar

AUTO_MIN_SIGNAL_S = 600.0  # below this much signal in all, "every core" stays in this process: starting workers costs more
T = TypeVar("T")
R = TypeVar("R")


def cores() -> int:
    """Cores this process may run on (its CPU affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def workers(jobs: int | None, items: int, signal_s: float | None = None) -> int:
    """How many processes ``jobs`` means for ``items`` tasks: None or 0 every core, never more than the tasks.

    ``signal_s``: seconds of signal in all the tasks; with less than :data:`AUTO_MIN_SIGNAL_S`, None or 0 means 1
    (a worker takes about half a second to start; replay runs at hundreds of times real time).
    """
    if jobs is not None and jobs < 0:
        raise ValueError(f"jobs: must be >= 0, got {jobs}")
    if not jobs and signal_s is not None and signal_s < AUTO_MIN_SIGNAL_S:
        return 1
    return max(1, min(jobs or cores(), items))


def map_files(fn: Callable[[T], R], items: Sequence[T], jobs: int | None = None,
              done: Callable[[int, int], None] | None = None, signal_s: float | None = None) -> Iterator[R]:
    """``fn(item)`` for every item, yielded in order as soon as each and those before it are ready.

    ``fn`` must be a module-level function (it is sent to the workers by name). ``jobs``: processes (None or 0:
    every core). ``done(finished, total)`` is called after each result. An exception in ``fn`` is raised here,
    at its item, after the results before it. ``signal_s``: see :func:`workers`.
    """
    n = workers(jobs, len(items), signal_s)
    if n == 1:
        results: Iterator[R] = (fn(item) for item in items)
    else:
        from joblib import Parallel, delayed

        results = Parallel(n_jobs=n, return_as="generator")(delayed(fn)(item) for item in items)
    try:
        for i, result in enumerate(results, 1):
            if done is not None:
                done(i, len(items))
            yield result
    finally:  # the consumer stopped early (a closed stdout): the pool ends here, without joblib's note of results unused
        close = getattr(results, "close", None)
        if n > 1 and close is not None:
            import warnings

            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", category=UserWarning, module="joblib.parallel")  # tasks unused, or cancelled
                close()
