"""Where the live daemon's CPU goes, without I/O: the ingest core and the pipeline per batch size, and the cost of a wake-up.

Usage: python bench/bench_ingest.py [--seconds 60]

1. ``seconds`` of the simulator's hand scene as frame bytes, fed in reads of ``read`` seconds
   through :class:`tactiled.run.ingest.Ingest` (batches of ``batch`` seconds) alone, then through
   the pipeline with the shipped model too: CPU time (``time.process_time``) per second of
   stream, i.e. the share of one core the daemon spends on it at 20 kHz.
2. One wake-up per 10 ms for 10 s (reading a silent pty each time) through ``asyncio.sleep``,
   ``loop.call_later`` and a plain thread's ``time.sleep``: CPU per wake-up.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import sys
import time
import tty

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from bench_daemon import FS, make_stream


def ingest_costs(data: bytes, seconds: float) -> None:
    from tactiled.config import Config
    from tactiled.learn.model import load_model
    from tactiled.run.stream import Stream

    config, model = Config(), load_model()
    line_rate = len(data) / seconds
    for batch, read in ((0.0, 0.005), (0.04, 0.01), (0.1, 0.02), (0.25, 0.03)):
        shares = []
        for with_pipeline in (False, True):
            stream = Stream(config, model, min_batch=round(batch * FS))
            chunk = max(1, round(line_rate * read))
            t0 = time.process_time()
            for i in range(0, len(data), chunk):
                batches = stream.decode(data[i:i + chunk])
                if batches and with_pipeline:
                    stream.process(batches)
            shares.append(100 * (time.process_time() - t0) / seconds)
        print(f"reads every {read * 1e3:.0f} ms, batches of {batch * 1e3:.0f} ms: ingest {shares[0]:.2f} %, "
              f"ingest + pipeline (shipped model) {shares[1]:.2f} % of one core", flush=True)


def wakeup_costs(n: int = 1000, period: float = 0.01) -> None:
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(slave, False)

    def read() -> None:
        with contextlib.suppress(BlockingIOError):  # a silent pty: nothing to read
            os.read(slave, 65536)

    async def with_sleep() -> None:
        for _ in range(n):
            await asyncio.sleep(period)
            read()

    async def with_call_later() -> None:
        loop = asyncio.get_running_loop()
        done = loop.create_future()
        count = 0

        def tick() -> None:
            nonlocal count
            read()
            count += 1
            if count >= n:
                done.set_result(None)
            else:
                loop.call_later(period, tick)

        loop.call_later(period, tick)
        await done

    def with_thread_sleep() -> None:
        for _ in range(n):
            time.sleep(period)  # the wake-up being measured
            read()

    for name, run in (("asyncio.sleep", lambda: asyncio.run(with_sleep())), ("loop.call_later", lambda: asyncio.run(with_call_later())),
                      ("thread time.sleep", with_thread_sleep)):
        t0, w0 = time.process_time(), time.monotonic()
        run()
        cpu, wall = time.process_time() - t0, time.monotonic() - w0
        print(f"wake-ups via {name}: {cpu / n * 1e6:.0f} us of CPU each, {100 * cpu / wall:.2f} % of one core at {n / wall:.0f} Hz", flush=True)
    os.close(master)
    os.close(slave)


def main() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=60.0)
    args = ap.parse_args()
    print(f"load average at start {os.getloadavg()[0]:.2f}", flush=True)
    ingest_costs(make_stream(args.seconds), args.seconds)
    wakeup_costs()
    print(f"load average at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
