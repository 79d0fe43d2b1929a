"""A storm of subscriber connections that open and close at once costs the publisher one pending heap trim per step, not
two per peer (an audit: 15 000 connect-and-close in a second queued 30 000 trims on the daemon's loop and put its
analysis 1.5 s behind)."""

from __future__ import annotations

import asyncio
import contextlib
import socket
from pathlib import Path

import pytest

from tactiled.config import PublishConfig
from tactiled.service import publish
from tactiled.service.publish import Publisher


def test_peers_that_come_and_go_leave_one_pending_trim_per_step(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(publish, "TRIM_AFTER_S", (60.0, 120.0))  # due long after the test: what is pending is counted
    path = tmp_path / "pub.sock"
    pub = Publisher(PublishConfig(endpoint=f"ipc://{path}"))
    peers = 300

    async def main() -> int:
        all_left = asyncio.Event()  # set by the publisher's own event handling once every peer's close was seen
        seen = pub._on_event

        def on_event(head: bytes) -> None:
            seen(head)
            if pub.departed >= peers:
                all_left.set()

        pub._on_event = on_event  # type: ignore[method-assign]
        task = asyncio.create_task(pub.limit_connections())
        try:
            for _ in range(peers):
                with socket.socket(socket.AF_UNIX) as s:
                    s.connect(str(path))
            await asyncio.wait_for(all_left.wait(), 30)  # every connection seen to close (the monitor's events), then count
            return len(pub._trims_due)
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    try:
        pending = asyncio.run(main())
    finally:
        pub.close()
    assert pending == 2  # one per step of TRIM_AFTER_S, however many peers left
